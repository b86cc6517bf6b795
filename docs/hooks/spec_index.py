"""Where each requirement id of spec/ lives: its chapter, the code and tests that cite it, its vector cases.

The documentation site is generated from the repository at build time, never kept by hand: this module
reads spec/*.md, the Python sources, tests/ and conformance/vectors/*.json, and renders the Markdown of
the spec pages (every id an HTML anchor with its code, vectors and tests) and of the source pages those
links point to (every line an anchor ``L<n>``). It needs only the standard library, so the tests of the
site (tests/docs/) import it without MkDocs.
"""

from __future__ import annotations

import ast
import dataclasses
import html
import json
import re
from pathlib import Path

# The same definition pattern as tests/test_requirement_coverage.py: a list item that starts with the id.
DEF = re.compile(r"^\s*(?:[-*]|\d+\.)\s+\**\[([A-Z]{1,3}-\d+)\]", re.M)
# An id as code and tests cite it: bare (``AX-6:``) or bracketed (``[W-4]``), not inside a longer token.
CITE = re.compile(r"(?<![A-Za-z0-9_-])([A-Z]{1,3}-\d+)(?![0-9])")
# A bracketed id in spec prose, turned into a link to its definition.
REF = re.compile(r"\[([A-Z]{1,3}-\d+)\]")
# Where the code that implements the spec lives, in the order a reader looks for it.
CODE_ROOTS = ("reference", "conformance", "softrtc")
TEST_ROOT = "tests"


@dataclasses.dataclass(frozen=True)
class Chapter:
    """One spec file: its path, the slug of its page (``01-weights.md`` -> ``weights``), title and ids."""

    path: str
    slug: str
    title: str
    ids: tuple


@dataclasses.dataclass(frozen=True)
class Citation:
    """A line of a source file that names an id, and the function or class it sits in ("" at module level)."""

    path: str
    line: int
    name: str


def chapter_slug(filename: str) -> str:
    """``01-weights.md`` -> ``weights``: the number orders the files, the page keeps the name.

    >>> chapter_slug("40-conformance.md")
    'conformance'
    >>> chapter_slug("00-overview.md")
    'overview'
    """
    stem = filename[:-3] if filename.endswith(".md") else filename
    m = re.fullmatch(r"\d+-(.+)", stem)
    if not m:
        raise ValueError(f"spec file name must look like NN-name.md, got {filename!r}")
    return m.group(1)


def read_chapters(root: Path) -> list:
    """The chapters of ``root/spec`` in file order; an id defined twice is an error (ids are unique, [N-14])."""
    chapters, seen = [], {}
    files = sorted((Path(root) / "spec").glob("*.md"))
    if not files:
        raise ValueError(f"root must hold spec/*.md, found none under {root}")
    for f in files:
        text = f.read_text(encoding="utf-8")
        title = next((line[2:].strip() for line in text.splitlines() if line.startswith("# ")), f.name)
        ids = tuple(m.group(1) for m in DEF.finditer(text))
        for i in ids:
            if i in seen:
                raise ValueError(f"requirement id {i} is defined in both {seen[i]} and {f.name}")
            seen[i] = f.name
        chapters.append(Chapter(f"spec/{f.name}", chapter_slug(f.name), title, ids))
    return chapters


def _enclosing(tree: ast.AST) -> list:
    """(first line, last line, qualified name) of every function and class, outermost first."""
    spans = []

    def walk(node, prefix):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                name = f"{prefix}{child.name}"
                first = min([child.lineno] + [d.lineno for d in child.decorator_list])
                spans.append((first, child.end_lineno, name))
                walk(child, name + ".")
            else:
                walk(child, prefix)

    walk(tree, "")
    return spans


def cite_lines(path: Path, rel: str, known: set) -> list:
    """Every (line, id) of a Python file naming a known id, with the innermost function or class around it."""
    text = path.read_text(encoding="utf-8")
    spans = _enclosing(ast.parse(text, filename=rel))
    out = []
    for n, line in enumerate(text.splitlines(), start=1):
        for m in CITE.finditer(line):
            if m.group(1) not in known:
                continue
            inner = [s for s in spans if s[0] <= n <= s[1]]
            name = max(inner, key=lambda s: s[0])[2] if inner else ""
            out.append((m.group(1), Citation(rel, n, name)))
    return out


def python_files(root: Path, top: str) -> list:
    """The .py files under ``root/top``, sorted, caches left out."""
    base = Path(root) / top
    return sorted(p for p in base.rglob("*.py") if "__pycache__" not in p.parts)


def collect_citations(root: Path, tops, known: set) -> dict:
    """id -> [Citation], one per (file, function) in file and line order; the first citing line of each."""
    out: dict = {}
    for top in tops:
        for p in python_files(root, top):
            rel = p.relative_to(root).as_posix()
            for ident, c in cite_lines(p, rel, known):
                lst = out.setdefault(ident, [])
                if not any(x.path == c.path and x.name == c.name for x in lst):
                    lst.append(c)
    return out


def vector_counts(root: Path) -> tuple:
    """(id -> {vector file: cases naming it}, {file: total cases}) from conformance/vectors/**/*.json.

    A file must be a JSON object with a list ``cases`` whose entries carry a list ``requirements``
    ([CF-1]); anything else is an error naming the file, not a silently smaller count.
    """
    per_id: dict = {}
    totals: dict = {}
    vdir = Path(root) / "conformance" / "vectors"
    # Sub-folders (the rollout vectors) hold files of the same form, named by their path from vectors/.
    for f in sorted(vdir.rglob("*.json")):
        if f.name == "index.json":
            continue
        name = f.relative_to(vdir).as_posix()
        doc = json.loads(f.read_text(encoding="utf-8"))
        cases = doc.get("cases") if isinstance(doc, dict) else None
        if not isinstance(cases, list):
            raise ValueError(f"vector file {name} must hold a list 'cases'")
        totals[name] = len(cases)
        for case in cases:
            reqs = case.get("requirements") if isinstance(case, dict) else None
            if not isinstance(reqs, list):
                raise ValueError(f"every case of {name} must carry a list 'requirements'")
            for r in set(reqs):
                per_id.setdefault(r, {}).setdefault(name, 0)
                per_id[r][name] += 1
    return per_id, totals


@dataclasses.dataclass(frozen=True)
class SpecIndex:
    """Everything the spec pages link: chapters, id -> chapter slug, code and test citations, vector counts."""

    chapters: list
    where: dict
    code: dict
    tests: dict
    vectors: dict
    vector_totals: dict

    @property
    def cited_files(self) -> list:
        """The source files a spec page links to, sorted: each gets a page of its own."""
        files = {c.path for cites in (*self.code.values(), *self.tests.values()) for c in cites}
        return sorted(files)


def build_index(root) -> SpecIndex:
    """Read the repository at ``root`` (a folder holding spec/, reference/, conformance/, softrtc/, tests/)."""
    root = Path(root)
    chapters = read_chapters(root)
    where = {i: ch.slug for ch in chapters for i in ch.ids}
    known = set(where)
    code = collect_citations(root, CODE_ROOTS, known)
    tests = collect_citations(root, (TEST_ROOT,), known)
    vectors, totals = vector_counts(root)
    return SpecIndex(chapters, where, code, tests, vectors, totals)


# --------------------------------------------------------------------------- rendering


def code_page_uri(path: str) -> str:
    """The site page of a source file: ``reference/weights.py`` -> ``code/reference/weights.py.md``."""
    return f"code/{path}.md"


def _link_refs(text: str, index: SpecIndex, slug, prefix: str = "") -> str:
    """Bracketed ids outside inline code become links to their definition (same page: ``#W-4``)."""
    parts = re.split(r"(`+[^`]*`+)", text)
    for k in range(0, len(parts), 2):  # even parts lie outside code spans

        def repl(m):
            ident = m.group(1)
            if ident not in index.where:
                return m.group(0)
            target = "" if index.where[ident] == slug else f"{prefix}{index.where[ident]}.md"
            return f"[\\[{ident}\\]]({target}#{ident})"

        parts[k] = REF.sub(repl, parts[k])
    return "".join(parts)


def _grouped(cites) -> str:
    """Citations grouped by file: ``path``: [name](page#Ln), ... (a module-level line shows as ``line n``)."""
    groups: dict = {}
    for c in cites:
        groups.setdefault(c.path, []).append(c)
    parts = []
    for path, lst in groups.items():
        links = ", ".join(f"[{c.name or f'line {c.line}'}](../{code_page_uri(c.path)}#L{c.line})" for c in lst)
        parts.append(f"`{path}`: {links}")
    return "; ".join(parts)


def link_ids(markdown: str, index: SpecIndex, spec_prefix: str) -> str:
    """Every bracketed id outside code (fenced blocks, inline spans) as a link to its rule's address.

    ``spec_prefix`` is the path from the page to the spec pages (``../spec/`` from ``guides/x.md``); used
    on the guides and reports, whose sources keep plain ``[W-4]`` so that they read well as files too.
    """
    out, fence = [], False
    for line in markdown.split("\n"):
        if line.lstrip().startswith("```"):
            fence = not fence
        out.append(line if fence or line.lstrip().startswith("```") else
                   _link_refs(line, index, None, spec_prefix))
    return "\n".join(out)


def _where_lines(ident: str, index: SpecIndex) -> list:
    """The code, vector files (with case counts) and tests of one id, as a small block of three lines."""
    code = index.code.get(ident, [])
    tests = index.tests.get(ident, [])
    vecs = index.vectors.get(ident, {})
    vec = ", ".join(f"[{name}](../conformance/vectors/{name}) ({n} cases)" for name, n in sorted(vecs.items()))
    return ['<div class="req-where" markdown>',
            f"**Code:** {_grouped(code) if code else 'none cites this id'}<br>",
            f"**Vectors:** {vec if vecs else 'no vector case names this id'}<br>",
            f"**Tests:** {_grouped(tests) if tests else 'none names this id'}",
            "</div>"]


def render_chapter(chapter: Chapter, index: SpecIndex, root, header: str = "") -> str:
    """The Markdown of a chapter's page: the spec text, every id an anchor, a where-paragraph after each rule.

    The definition ``- **[W-4]** ...`` becomes ``- <span id="W-4"></span>**[[W-4]](#W-4)** ...`` so that
    ``spec/weights/#W-4`` addresses it; the paragraph after the rule is indented as part of its list item.
    """
    lines = (Path(root) / chapter.path).read_text(encoding="utf-8").splitlines()
    out, fence, pending = [], False, None

    def flush():
        nonlocal pending
        if pending is not None:
            while out and not out[-1].strip():
                out.pop()
            out.extend([""] + ["    " + x for x in _where_lines(pending, index)] + [""])
            pending = None

    for n, line in enumerate(lines):
        if line.lstrip().startswith("```"):
            fence = not fence
            out.append(line)
            continue
        if fence:
            out.append(line)
            continue
        m = DEF.match(line)
        starts_block = bool(line.strip()) and not line.startswith((" ", "\t"))
        if pending is not None and (m or starts_block):
            flush()
        if m:
            ident = m.group(1)
            head, tail = line[:m.end()], line[m.end():]
            # `- **[W-4]**` -> the anchor, then the id as a link to itself (a citable address).
            lead = head[:head.index("[")]
            bold = lead.endswith("**")
            lead = lead[:-2] if bold else lead
            tail = tail[2:] if bold and tail.startswith("**") else tail
            anchor = f'<span class="req-id" id="{ident}"></span>'
            idlink = f"[\\[{ident}\\]](#{ident})"
            idtext = f"**{idlink}**" if bold else idlink
            out.append(f"{lead}{anchor}{idtext}{_link_refs(tail, index, chapter.slug)}")
            pending = ident
            continue
        out.append(_link_refs(line, index, chapter.slug))
        if n == 0 and header and line.startswith("# "):
            out.extend(["", header])
    flush()
    return "\n".join(out) + "\n"


def render_spec_index(index: SpecIndex, header: str = "") -> str:
    """The spec's front page: its chapters, and every id with its chapter, code, vector and test counts."""
    out = ["# Specification", ""]
    if header:
        out += [header, ""]
    out += ["Every requirement id is an anchor: cite a rule as `spec/<chapter>/#<id>` (for example "
            "[weights/#W-4](weights.md#W-4)). Each rule's page lists the code that cites it, the conformance "
            "vector files with their case counts, and the tests that name it; this page and those lists are "
            "generated from the repository when the site is built.", "",
            "| chapter | page | ids |", "|---|---|---|"]
    for ch in index.chapters:
        out.append(f"| [{ch.title}]({ch.slug}.md) | `spec/{ch.slug}/` | {len(ch.ids)} |")
    out += ["", "## Every id", "", "| id | chapter | code | vector cases | tests |", "|---|---|---|---|---|"]
    for ch in index.chapters:
        for i in ch.ids:
            out.append(f"| [{i}]({ch.slug}.md#{i}) | {ch.slug} | {len(index.code.get(i, []))} | "
                       f"{sum(index.vectors.get(i, {}).values())} | {len(index.tests.get(i, []))} |")
    return "\n".join(out) + "\n"


def render_code_page(root, path: str) -> str:
    """A source file as a page whose every line carries the anchor ``L<n>`` (raw HTML, so nothing is parsed)."""
    text = (Path(root) / path).read_text(encoding="utf-8")
    rows = [f'<span class="ln" id="L{n}">{n:>4}</span> {html.escape(line)}'
            for n, line in enumerate(text.splitlines(), start=1)]
    return (f"# {path}\n\n<div class=\"softrtc-code\"><pre><code>" + "\n".join(rows) + "</code></pre></div>\n")


def render_vectors_page(index: SpecIndex, header: str = "") -> str:
    """The conformance vector files with their case counts, each downloadable from the site."""
    out = ["# Conformance vectors", ""]
    if header:
        out += [header, ""]
    out += ["The files the conformance runner checks an implementation against (`softrtc conformance run`); "
            "each case names the requirement ids it checks, and each rule on the spec pages links the files "
            "whose cases name it.", "", "| file | cases |", "|---|---|"]
    for name, n in sorted(index.vector_totals.items()):
        out.append(f"| [{name}](vectors/{name}) | {n} |")
    out += ["", f"All {sum(index.vector_totals.values())} cases; `index.json` holds the SHA-256 and case count "
            "of every file ([\\[CF-25\\]](../spec/conformance.md#CF-25)).", ""]
    return "\n".join(out)
