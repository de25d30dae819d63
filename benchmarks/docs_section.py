"""One place that writes a benchmark's section of a doc (docs/benchmarks.md unless told)
between its markers; the text around the markers is written by hand."""

from __future__ import annotations

from pathlib import Path

DOC = Path(__file__).resolve().parents[1] / "docs" / "benchmarks.md"


def write_section(name: str, body: str, doc: Path = DOC) -> None:
    """Replace the text between `<!-- name:begin -->` and `<!-- name:end -->` in `doc`, or
    append it."""
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    section = f"{begin}\n{body.rstrip()}\n{end}"
    text = doc.read_text() if doc.is_file() else ("# Benchmarks\n" if doc == DOC else "")
    if begin in text and end in text:
        text = text[: text.index(begin)] + section + text[text.index(end) + len(end):]
    elif text.strip():
        text = text.rstrip("\n") + "\n\n" + section + "\n"
    else:
        text = section + "\n"
    doc.write_text(text)
