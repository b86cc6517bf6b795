"""The documentation site: `mkdocs build --strict` succeeds (a broken link or anchor would fail it), every
requirement id is an anchor of the built spec pages with the versions in the header, and a spec page opened
at an id's address in headless Chromium shows that rule."""

from __future__ import annotations

import ast
import os
import shutil
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import pytest

from tests.docs.cdp import Browser

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}


def _mkdocs(*args, cwd=ROOT) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mkdocs", *args], cwd=cwd, env=ENV, capture_output=True,
                          text=True, timeout=600)


def _constant(path: Path, name: str) -> str:
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == name for t in node.targets):
            return ast.literal_eval(node.value)
    raise AssertionError(f"{path} lacks {name}")


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    for mod in ("mkdocs", "material", "mkdocstrings", "mkdocstrings_handlers.python"):
        pytest.importorskip(mod)
    out = tmp_path_factory.mktemp("site")
    res = _mkdocs("build", "--strict", "--site-dir", str(out))
    assert res.returncode == 0, res.stdout + res.stderr
    assert "WARNING" not in res.stderr, res.stderr
    return out


def test_strict_build_has_every_id_and_the_versions(site):
    """The spec pages carry every id of spec/ as an element id, each rule links its code page line that exists,
    and every page's header names the spec and vector format versions the conformance package defines."""
    import re

    spec_version = _constant(ROOT / "conformance" / "__init__.py", "SPEC_VERSION")
    fmt = _constant(ROOT / "conformance" / "__init__.py", "FORMAT_VERSION")
    defined = set(re.findall(r"^\s*(?:[-*]|\d+\.)\s+\**\[([A-Z]{1,3}-\d+)\]",
                             "\n".join(p.read_text() for p in (ROOT / "spec").glob("*.md")), re.M))
    found = set()
    for page in (site / "spec").glob("*/index.html"):
        html = page.read_text()
        found |= set(re.findall(r'<span class="req-id" id="([A-Z]{1,3}-\d+)">', html))
        assert f"spec {spec_version}" in html and f"vectors {fmt}" in html, page
    assert found == defined
    weights = (site / "spec" / "weights" / "index.html").read_text()
    # W-4's rule names reference/weights.py; the linked line exists on the code page.
    m = re.search(r'href="\.\./\.\./code/reference/weights\.py/#L(\d+)"', weights)
    assert m, "the weights chapter links no line of reference/weights.py"
    code = (site / "code" / "reference" / "weights.py" / "index.html").read_text()
    assert f'id="L{m.group(1)}"' in code
    assert 'href="../../conformance/vectors/weights.json"' in weights
    assert (site / "conformance" / "vectors" / "weights.json").read_bytes() == \
        (ROOT / "conformance" / "vectors" / "weights.json").read_bytes()


def test_strict_build_fails_on_a_broken_anchor(tmp_path):
    """The site's link checks are errors: a project with the same validation settings and a link to a missing
    anchor fails `mkdocs build --strict` and names the anchor."""
    pytest.importorskip("mkdocs")
    config = (ROOT / "mkdocs.yml").read_text()
    validation = config[config.index("\nvalidation:"):]
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "index.md").write_text("# A\n\n[rule](b.md#W-404)\n")
    (tmp_path / "docs" / "b.md").write_text('# B\n\n<span id="W-4"></span>text\n')
    (tmp_path / "mkdocs.yml").write_text("site_name: t\n" + validation)
    res = _mkdocs("build", "--strict", cwd=tmp_path)
    assert res.returncode != 0 and "W-404" in res.stderr, res.stderr
    (tmp_path / "docs" / "index.md").write_text("# A\n\n[rule](b.md#W-4)\n")
    res = _mkdocs("build", "--strict", cwd=tmp_path)
    assert res.returncode == 0, res.stderr


def _png_distinct_bytes(path: Path) -> int:
    """How many distinct byte values the decompressed image data of a PNG holds (a blank page: very few)."""
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
    pos, idat = 8, b""
    while pos < len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        if kind == b"IDAT":
            idat += data[pos + 8:pos + 8 + length]
        pos += 12 + length
    return len(set(zlib.decompress(idat)))


def test_spec_page_opens_at_an_id_in_chromium(site, tmp_path_factory, record_property):
    """A spec page opened at `spec/weights/#W-4` in real headless Chromium: the element with that id exists,
    the view has scrolled to it, its rule's text is shown, and the screenshot is not blank."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.skip("needs Chromium (Debian package chromium; make test installs it)")
    shots = tmp_path_factory.mktemp("screenshot")
    url = (site / "spec" / "weights" / "index.html").as_uri() + "#W-4"
    with Browser(chromium, str(shots / "profile")) as browser:
        browser.open(url)
        state = browser.evaluate("""(() => {
            const el = document.getElementById('W-4');
            if (!el) return null;
            const r = el.getBoundingClientRect();
            return {hash: location.hash, top: r.top, height: window.innerHeight, scrolled: window.scrollY,
                    rule: el.closest('li').innerText.slice(0, 200), title: document.title};
        })()""")
        png = shots / "spec-weights-W-4.png"
        browser.screenshot(str(png))
    assert state is not None, "no element with id W-4 on the built page"
    assert state["hash"] == "#W-4" and state["scrolled"] > 0 and 0 <= state["top"] < state["height"], state
    assert state["rule"].startswith("[W-4] Window parametrization"), state["rule"]
    assert _png_distinct_bytes(png) > 50, f"the screenshot {png} is blank"
    record_property("screenshot", str(png))
    print(f"screenshot of {url}: {png}")
