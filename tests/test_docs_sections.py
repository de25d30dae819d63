"""The generated sections of docs/: benchmarks rewrite the text between a section's markers,
so a section placed inside another by a hand edit would be wiped by the outer one's next run
(the round statistics' table and notes sat inside the Esc section once)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from benchmarks.docs_section import MARKER, write_section

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("doc", sorted((ROOT / "docs").glob("*.md")), ids=lambda p: p.name)
def test_sections_are_paired_and_not_nested(doc: Path) -> None:
    open_name, seen = None, set()
    for marker in MARKER.findall(doc.read_text()):
        name, kind = re.match(r"<!-- ([\w.-]+):(begin|end) -->", marker).groups()
        if kind == "begin":
            assert open_name is None, f"{doc.name}: {name} begins inside {open_name}"
            assert name not in seen, f"{doc.name}: {name} appears twice"
            open_name = name
            seen.add(name)
        else:
            assert open_name == name, f"{doc.name}: {name} ends while {open_name} is open"
            open_name = None
    assert open_name is None, f"{doc.name}: {open_name} never ends"


def test_write_section_replaces_its_own_text_only(tmp_path: Path) -> None:
    doc = tmp_path / "doc.md"
    doc.write_text("hand\n<!-- a:begin -->\nold\n<!-- a:end -->\nhand too\n")
    write_section("a", "new", doc)
    assert doc.read_text() == "hand\n<!-- a:begin -->\nnew\n<!-- a:end -->\nhand too\n"
    write_section("b", "appended", doc)
    assert doc.read_text().endswith("hand too\n\n<!-- b:begin -->\nappended\n<!-- b:end -->\n")


@pytest.mark.parametrize("text, match", [
    # a section inside another: the outer one's run would wipe it
    ("<!-- a:begin -->\n<!-- b:begin -->\nkept\n<!-- b:end -->\n<!-- a:end -->\n", "'a' holds"),
    # a pasted copy: a run would update one and leave the stale one
    ("<!-- a:begin -->\nnew\n<!-- a:end -->\n<!-- a:begin -->\nstale\n<!-- a:end -->\n",
     "'a' appears 2 times"),
], ids=["nested", "twice"])
def test_write_section_refuses_and_leaves_the_doc_as_it_was(tmp_path: Path, text: str,
                                                            match: str) -> None:
    doc = tmp_path / "doc.md"
    doc.write_text(text)
    with pytest.raises(ValueError, match=match):
        write_section("a", "new", doc)
    assert doc.read_text() == text
