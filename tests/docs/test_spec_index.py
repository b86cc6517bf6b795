"""The generator of the site's spec pages (docs/hooks/spec_index.py), on a small repository written here and on
the real spec: every requirement id becomes one anchor, with the code, vectors and tests that name it."""

from __future__ import annotations

import importlib.util
import json
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "docs" / "hooks" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


si = _load("spec_index")
fences = _load("griffe_doctest")

SPEC = """# 1. Tiny chapter (Q)

Intro citing [Q-2] and `[Q-1]` in code.

- **[Q-1]** First rule,
  continued on a second line; see [Q-2].
- **[Q-2]** Second rule.

```
[Q-1] inside a fence stays text
```

After the list.
"""

CODE = '''"""Module citing nothing at the top."""


def first():
    """Implements [Q-1]."""
    return 1


class Thing:
    def method(self):
        return 2  # Q-2 and Q-1 on one line
'''

TESTS = '''def test_first():
    """Q-1: checks first."""
    assert True
'''


@pytest.fixture
def tiny(tmp_path):
    (tmp_path / "spec").mkdir()
    (tmp_path / "spec" / "01-tiny.md").write_text(SPEC)
    for top in ("reference", "conformance", "softrtc", "tests"):
        (tmp_path / top).mkdir()
    (tmp_path / "reference" / "mod.py").write_text(CODE)
    (tmp_path / "tests" / "test_mod.py").write_text(TESTS)
    vdir = tmp_path / "conformance" / "vectors"
    vdir.mkdir()
    cases = [{"id": "a", "requirements": ["Q-1"]}, {"id": "b", "requirements": ["Q-1", "Q-2"]},
             {"id": "c", "requirements": ["Q-2", "Q-2"]}]
    (vdir / "tiny.json").write_text(json.dumps({"cases": cases}))
    (vdir / "index.json").write_text("{}")
    return tmp_path


def test_chapter_slug_drops_the_number_and_rejects_other_names():
    assert si.chapter_slug("01-weights.md") == "weights"
    assert si.chapter_slug("32-runtime-bench.md") == "runtime-bench"
    with pytest.raises(ValueError, match="NN-name.md"):
        si.chapter_slug("weights.md")


def test_index_of_a_small_repository(tiny):
    """Citations carry file, line and enclosing function; vector counts count a case once per id."""
    idx = si.build_index(tiny)
    assert [(c.slug, c.ids) for c in idx.chapters] == [("tiny", ("Q-1", "Q-2"))]
    assert idx.code["Q-1"] == [si.Citation("reference/mod.py", 5, "first"),
                               si.Citation("reference/mod.py", 11, "Thing.method")]
    assert idx.code["Q-2"] == [si.Citation("reference/mod.py", 11, "Thing.method")]
    assert idx.tests["Q-1"] == [si.Citation("tests/test_mod.py", 2, "test_first")]
    assert "Q-2" not in idx.tests
    # case c names Q-2 twice: it is one case
    assert idx.vectors == {"Q-1": {"tiny.json": 2}, "Q-2": {"tiny.json": 2}}
    assert idx.vector_totals == {"tiny.json": 3}
    assert idx.cited_files == ["reference/mod.py", "tests/test_mod.py"]


def test_rendered_chapter_has_one_anchor_per_id_and_links_outside_code_only(tiny):
    idx = si.build_index(tiny)
    page = si.render_chapter(idx.chapters[0], idx, tiny, header="HEADER")
    assert page.count('id="Q-1"') == 1 and page.count('id="Q-2"') == 1
    assert "- <span class=\"req-id\" id=\"Q-1\"></span>**[\\[Q-1\\]](#Q-1)** First rule," in page
    assert "Intro citing [\\[Q-2\\]](#Q-2) and `[Q-1]` in code." in page
    assert "[Q-1] inside a fence stays text" in page
    assert page.splitlines()[2] == "HEADER"
    # The where-block closes Q-1's item after its continuation line, indented into the item.
    lines = page.splitlines()
    k = lines.index("  continued on a second line; see [\\[Q-2\\]](#Q-2).")
    assert lines[k + 1] == "" and lines[k + 2] == '    <div class="req-where" markdown>'
    assert "[first](../code/reference/mod.py.md#L5)" in lines[k + 3]
    assert "[tiny.json](../conformance/vectors/tiny.json) (2 cases)" in lines[k + 4]
    assert "[test_first](../code/tests/test_mod.py.md#L2)" in lines[k + 5]
    assert "**Tests:** none names this id" in page  # Q-2 has no test


def test_code_page_anchors_every_line_and_escapes_html(tiny):
    (tiny / "reference" / "mod.py").write_text("x = '<b>' & 1\n\ny = 2\n")
    page = si.render_code_page(tiny, "reference/mod.py")
    assert re.findall(r'id="L(\d+)"', page) == ["1", "2", "3"]
    assert "&lt;b&gt;" in page and "<b>" not in page


def test_bad_inputs_are_reported(tiny):
    (tiny / "spec" / "02-dup.md").write_text("- **[Q-1]** again\n")
    with pytest.raises(ValueError, match="Q-1 is defined in both 01-tiny.md and 02-dup.md"):
        si.build_index(tiny)
    (tiny / "spec" / "02-dup.md").unlink()
    (tiny / "conformance" / "vectors" / "bad.json").write_text(json.dumps({"cases": [{"id": "x"}]}))
    with pytest.raises(ValueError, match="bad.json must carry a list 'requirements'"):
        si.build_index(tiny)
    with pytest.raises(ValueError, match="root must hold spec"):
        si.build_index(tiny / "reference")


def test_every_spec_id_of_the_repository_gets_an_anchor_and_its_vectors():
    """Each id defined in spec/ is an anchor on exactly one chapter page, and the case counts shown per id
    add up to what the vector files hold (counted here from the files directly)."""
    idx = si.build_index(ROOT)
    anchors = {}
    for ch in idx.chapters:
        page = si.render_chapter(ch, idx, ROOT)
        for ident in re.findall(r'<span class="req-id" id="([A-Z]{1,3}-\d+)">', page):
            anchors.setdefault(ident, []).append(ch.slug)
    defined = {m.group(1) for f in (ROOT / "spec").glob("*.md") for m in si.DEF.finditer(f.read_text())}
    assert set(anchors) == defined and all(len(v) == 1 for v in anchors.values())
    for name in idx.vector_totals:
        cases = json.loads((ROOT / "conformance" / "vectors" / name).read_text())["cases"]
        for ident in ("W-4", "E-2", "S-3"):
            want = sum(ident in c["requirements"] for c in cases)
            assert idx.vectors.get(ident, {}).get(name, 0) == want, (ident, name)


def test_doctest_examples_become_fenced_code():
    text = "Text.\n\n>>> 1 + 1\n2\n\nMore.\n    >>> f(\n    ... 3)\n    [0, 1]"
    assert fences.fence_examples(text).splitlines() == [
        "Text.", "", "```pycon", ">>> 1 + 1", "2", "```", "", "More.",
        "    ```pycon", "    >>> f(", "    ... 3)", "    [0, 1]", "    ```"]
