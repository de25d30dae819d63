"""One place that writes a benchmark's section of a doc (docs/benchmarks.md unless told)
between its markers; the text around the markers is written by hand."""

from __future__ import annotations

import re
from pathlib import Path

DOC = Path(__file__).resolve().parents[1] / "docs" / "benchmarks.md"
MARKER = re.compile(r"<!-- [\w.-]+:(?:begin|end) -->")


def write_section(name: str, body: str, doc: Path = DOC) -> None:
    """Replace the text between `<!-- name:begin -->` and `<!-- name:end -->` in `doc`, or
    append it. Refuses to replace a span holding another section's marker (a hand edit that
    put one section inside another would otherwise lose the inner one) and a section that
    appears twice."""
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    section = f"{begin}\n{body.rstrip()}\n{end}"
    text = doc.read_text() if doc.is_file() else ("# Benchmarks\n" if doc == DOC else "")
    if text.count(begin) > 1:
        # A pasted copy of the doc's tail: the run would update one copy and leave the stale one.
        raise ValueError(f"{doc}: the section {name!r} appears {text.count(begin)} times; "
                         "delete the stale copies")
    if begin in text and end in text:
        start, stop = text.index(begin), text.index(end) + len(end)
        inner = MARKER.findall(text, start + len(begin), stop - len(end))
        if inner:
            raise ValueError(f"{doc}: the section {name!r} holds {', '.join(inner)}; move the "
                             "markers so that each section holds only its own text")
        text = text[:start] + section + text[stop:]
    elif text.strip():
        text = text.rstrip("\n") + "\n\n" + section + "\n"
    else:
        text = section + "\n"
    doc.write_text(text)
