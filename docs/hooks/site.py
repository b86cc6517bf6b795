"""MkDocs hook: the pages generated from the repository when the site is built (nothing here is kept by hand).

- ``spec/<chapter>/``: every chapter of spec/, each requirement id an anchor with its code, vectors and tests
  (spec_index.py), and ``spec/`` the index of every id;
- ``code/<path>/``: each source file a spec page links to, every line an anchor;
- ``conformance/vectors/``: the vector files with case counts, the files themselves downloadable;
- the reports kept beside their data (results/arm/REPORT.md with its plots, the third-party compatibility
  reports under conformance/thirdparty/, the JavaScript port's README);
- the navigation, which lists every page under docs/guides/ so a new guide appears without editing the
  configuration;
- the versions the site documents (softrtc, spec, vector format) in the header of every page.
"""

from __future__ import annotations

import ast
import logging
import posixpath
import re
from pathlib import Path

from mkdocs.structure.files import File

import spec_index as si

ROOT = Path(__file__).resolve().parents[2]
log = logging.getLogger("mkdocs.hooks.softrtc")

# Guides shown first, in this order; any other docs/guides/*.md follows in file-name order.
GUIDE_ORDER = ("validating.md", "rollouts.md", "porting.md", "commands.md", "jax.md", "torch.md", "arm.md", "kinetix.md")
# Plots of the arm experiment shown under its report, per task folder that has them.
# The index of the build in progress (on_files makes it, on_page_markdown uses it).
_INDEX: list = []
# Repository path -> site path of every published repository file, and site page -> the repository file it
# was made from (for the pages whose relative links point into the repository).
_SITE_OF: dict = {}
_SOURCE_OF: dict = {}
ARM_PLOTS = ("success_by_delay.png", "frontier.png", "sweeps.png", "window_weights.png")


def _constant(path: Path, name: str) -> str:
    """A module-level string constant read from source, so the build imports none of the package."""
    for node in ast.parse(path.read_text(encoding="utf-8")).body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == name for t in node.targets):
            value = ast.literal_eval(node.value)
            if isinstance(value, str):
                return value
    raise ValueError(f"{path} must define the string {name}")


def versions() -> dict:
    """softrtc's version, the spec version and the vector format version, from the sources that define them."""
    return {"softrtc": _constant(ROOT / "softrtc" / "__init__.py", "__version__"),
            "spec": _constant(ROOT / "conformance" / "__init__.py", "SPEC_VERSION"),
            "vectors_format": _constant(ROOT / "conformance" / "__init__.py", "FORMAT_VERSION")}


def version_line() -> str:
    v = versions()
    return (f"*Documents softrtc {v['softrtc']}: specification {v['spec']}, conformance vectors format "
            f"{v['vectors_format']}.*")


def on_config(config, **kwargs):
    v = versions()
    config.site_name = f"softrtc {v['softrtc']} · spec {v['spec']} · vectors {v['vectors_format']}"
    config.extra["versions"] = v
    return config


def _add(files, config, uri: str, *, content=None, path: Path | None = None, source: str | None = None) -> None:
    """A generated site file at ``uri``: a repository file (``path``) or text made from one (``source``)."""
    if path is not None:
        files.append(File.generated(config, uri, abs_src_path=str(path)))
        source = Path(path).resolve().relative_to(ROOT).as_posix()
    else:
        files.append(File.generated(config, uri, content=content))
    if source is not None:
        _SITE_OF[source] = uri
        if uri.endswith(".md"):
            _SOURCE_OF[uri] = source


# A relative Markdown link or image target (no scheme, not only a fragment, not absolute).
_LINK = re.compile(r"(\]\()([^)\s]+)(\))")


def _repo_target(source: str, target: str):
    """(repository path, fragment) a relative link of the repository file ``source`` points to, or None."""
    if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith(("#", "/")):
        return None
    path, _, frag = target.partition("#")
    rel = posixpath.normpath(posixpath.join(posixpath.dirname(source), path))
    return None if rel.startswith("..") else (rel, frag)


def _publish_link_targets(files, config) -> None:
    """Files the published repository pages link to, and that the site has no page for, are published under
    ``repo/`` so the links work on the site; a link to a file that does not exist stays broken (and fails
    the strict build)."""
    for uri, source in list(_SOURCE_OF.items()):
        text = (ROOT / source).read_text(encoding="utf-8")
        for m in _LINK.finditer(text):
            hit = _repo_target(source, m.group(2))
            if hit and hit[0] not in _SITE_OF and (ROOT / hit[0]).is_file():
                _add(files, config, f"repo/{hit[0]}", path=ROOT / hit[0])


def _rewrite_links(markdown: str, uri: str) -> str:
    """The relative links of a page made from a repository file, pointed at the site's copies of their targets."""
    source = _SOURCE_OF[uri]

    def repl(m):
        hit = _repo_target(source, m.group(2))
        if not hit or hit[0] not in _SITE_OF:
            return m.group(0)
        new = posixpath.relpath(_SITE_OF[hit[0]], posixpath.dirname(uri) or ".")
        return f"{m.group(1)}{new}{'#' + hit[1] if hit[1] else ''}{m.group(3)}"

    return _LINK.sub(repl, markdown)


def _arm_report(task_dirs) -> str:
    text = (ROOT / "results" / "arm" / "REPORT.md").read_text(encoding="utf-8")
    out = [text.rstrip(), "", "## Plots", ""]
    for task in task_dirs:
        for name in ARM_PLOTS:
            if (ROOT / "results" / "arm" / task / name).is_file():
                out += [f"Task `{task}`, `{name}`:", "", f"![{task} {name}](arm/{task}/{name})", ""]
    return "\n".join(out)


def on_files(files, config, **kwargs):
    index = si.build_index(ROOT)
    _INDEX[:] = [index]
    _SITE_OF.clear()
    _SOURCE_OF.clear()
    header = version_line()
    _add(files, config, "spec/index.md", content=si.render_spec_index(index, header))
    for ch in index.chapters:
        _add(files, config, f"spec/{ch.slug}.md", content=si.render_chapter(ch, index, ROOT, header))
        _SITE_OF[ch.path] = f"spec/{ch.slug}.md"
    for path in index.cited_files:
        _add(files, config, si.code_page_uri(path), content=si.render_code_page(ROOT, path))
        _SITE_OF[path] = si.code_page_uri(path)
    _add(files, config, "conformance/vectors.md", content=si.render_vectors_page(index, header))
    for name in index.vector_totals:
        _add(files, config, f"conformance/vectors/{name}", path=ROOT / "conformance" / "vectors" / name)
    for p in sorted((ROOT / "conformance" / "vectors").rglob("index.json")):
        rel = p.relative_to(ROOT / "conformance" / "vectors").as_posix()
        _add(files, config, f"conformance/vectors/{rel}", path=p)
    _add(files, config, "conformance/js-port.md", path=ROOT / "conformance" / "ports" / "js" / "README.md")
    reports = third_party_reports()
    base = ROOT / "conformance" / "thirdparty"
    # The reports with what they link beside them (their JSON, patches, scripts).
    for p in sorted(base.rglob("*")):
        if p.is_file() and "__pycache__" not in p.parts and p.suffix != ".pyc":
            rel = p.relative_to(base).as_posix()
            _add(files, config, f"reports/thirdparty/{rel}", path=p)
    _add(files, config, "reports/thirdparty.md", content=_third_party_page(reports))
    tasks = sorted(p.name for p in (ROOT / "results" / "arm").iterdir() if p.is_dir())
    _add(files, config, "reports/arm-report.md", content=_arm_report(tasks), source="results/arm/REPORT.md")
    for task in tasks:
        for name in ARM_PLOTS:
            p = ROOT / "results" / "arm" / task / name
            if p.is_file():
                _add(files, config, f"reports/arm/{task}/{name}", path=p)
    for p in sorted((ROOT / "results" / "arm" / "realtime").glob("*.png")):
        _add(files, config, f"reports/arm/realtime/{p.name}", path=p)
    for p in sorted((ROOT / "results" / "kinetix" / "study").glob("*.png")):
        _add(files, config, f"reports/kinetix/{p.name}", path=p)
    _publish_link_targets(files, config)
    config.nav = _nav(files, index)
    return files


def on_page_markdown(markdown, page, config, files, **kwargs):
    """On the hand-written pages, each bracketed requirement id links to its rule (the sources stay plain)."""
    uri = page.file.src_uri
    if uri.startswith(("spec/", "code/")):
        return markdown
    if uri in _SOURCE_OF:
        markdown = _rewrite_links(markdown, uri)
    depth = uri.count("/")
    return si.link_ids(markdown, _INDEX[0], "../" * depth + "spec/")


def third_party_reports() -> list:
    """The compatibility reports under conformance/thirdparty/ ([TP-4]), as paths relative to it."""
    base = ROOT / "conformance" / "thirdparty"
    return sorted(p.relative_to(base).as_posix() for p in base.rglob("*.md"))


def _third_party_page(reports) -> str:
    out = ["# Third-party compatibility reports", "",
           "Each report is written by `softrtc conformance report` from a run of the conformance vectors "
           "([TP-4]) and kept in `conformance/thirdparty/`; the summary and how to reproduce it are on "
           "[LeRobot compatibility](lerobot.md).", ""]
    out += [f"- [{rel}](thirdparty/{rel})" for rel in reports] or ["No report is committed."]
    return "\n".join(out) + "\n"


def _guides(files) -> list:
    names = sorted(f.src_uri[len("guides/"):] for f in files.documentation_pages()
                   if f.src_uri.startswith("guides/") and f.src_uri.count("/") == 1)
    ordered = [n for n in GUIDE_ORDER if n in names] + [n for n in names if n not in GUIDE_ORDER]
    return [f"guides/{n}" for n in ordered]


def _nav(files, index) -> list:
    """The site's navigation; the guides are whatever docs/guides/ holds, the spec whatever spec/ holds."""
    api = sorted(f.src_uri for f in files.documentation_pages() if f.src_uri.startswith("api/"))
    return [
        {"Home": "index.md"},
        {"Install": "install.md"},
        {"Specification": ["spec/index.md"] + [{ch.title: f"spec/{ch.slug}.md"} for ch in index.chapters]},
        {"Guides": _guides(files)},
        {"Conformance": ["conformance/vectors.md", "conformance/js-port.md"]},
        {"Reports": ["reports/arm.md", "reports/arm-report.md", "reports/lerobot.md", "reports/thirdparty.md",
                     "reports/kinetix.md", "reports/benchmarks.md"]},
        {"API reference": api},
        {"About this site": "about.md"},
    ]
