"""docs/reliability.md's fault table names tests that exist, and its fault count matches the table."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "reliability.md"


def _fault_rows() -> list[tuple[str, str]]:
    section = DOC.read_text().split("## In figures", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"^\| [^|]+ \| `(tests/[\w/]+\.py)::(test_\w+)` \|$", section, flags=re.MULTILINE)


def test_every_fault_in_the_table_is_a_test_that_exists() -> None:
    rows = _fault_rows()
    assert rows, "docs/reliability.md has no fault table under '## In figures'"
    for path, name in rows:
        source = (ROOT / path).read_text()
        assert re.search(rf"^def {name}\(", source, flags=re.MULTILINE), f"{path}::{name} does not exist"


def test_the_fault_count_matches_the_table() -> None:
    match = re.search(r"\*\*(\d+) faults survived\*\*", DOC.read_text())
    assert match is not None, "docs/reliability.md does not state the number of faults survived"
    assert int(match.group(1)) == len(_fault_rows())
