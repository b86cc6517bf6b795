"""Every requirement id defined in spec/ is named by at least one test (spec/00-overview.md)."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEF = re.compile(r"^\s*(?:[-*]|\d+\.)\s+\**\[([A-Z]{1,3}-\d+)\]", re.M)


def spec_ids() -> dict:
    ids = {}
    for f in sorted((ROOT / "spec").glob("*.md")):
        for m in DEF.finditer(f.read_text()):
            ids.setdefault(m.group(1), f.name)
    return ids


def test_spec_defines_each_id_once():
    """Requirement ids are unique across the spec (ids are stable, so a later rule may sit in an earlier section)."""
    seen = {}
    for f in sorted((ROOT / "spec").glob("*.md")):
        for m in DEF.finditer(f.read_text()):
            assert m.group(1) not in seen, f"{m.group(1)} defined in {seen.get(m.group(1))} and {f.name}"
            seen[m.group(1)] = f.name
    assert len(seen) > 50


def test_every_requirement_id_is_named_by_a_test():
    """Fails if any requirement id in spec/ has no test naming it."""
    text = "\n".join(p.read_text() for p in (ROOT / "tests").rglob("*.py") if p.name != Path(__file__).name)
    missing = [i for i in spec_ids() if not re.search(rf"(?<![A-Z-]){re.escape(i)}(?!\d)", text)]
    assert not missing, f"requirement ids with no test naming them: {missing}"
