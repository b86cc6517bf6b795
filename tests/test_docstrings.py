"""The worked examples in the docstrings of the softrtc modules are run, so none can drift from the code.

Only modules whose source holds an example (``>>>`` in a docstring) are
collected, and each run must attempt at least one: a doctest run over a
module without examples passes whatever the module does, and checks nothing.
"""

import ast
import doctest
import importlib
import importlib.util
import pkgutil

import pytest

import softrtc
import softrtc.conformance
import softrtc.reference

# softrtc.reference and softrtc.conformance live in their own folders (package-dir), so they are walked too.
MODULES = sorted({m.name for pkg in (softrtc, softrtc.reference, softrtc.conformance)
                  for m in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + ".")
                  if not m.name.endswith("__main__")})


def docstring_examples(source: str) -> int:
    """How many ``>>>`` lines the docstrings of a module's source hold (module, classes, functions)."""
    tree = ast.parse(source)
    nodes = [tree] + [n for n in ast.walk(tree)
                      if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))]
    docs = [ast.get_docstring(n, clean=False) or "" for n in nodes]
    return sum(line.lstrip().startswith(">>>") for d in docs for line in d.splitlines())


def _source(name: str) -> str:
    with open(importlib.util.find_spec(name).origin, encoding="utf-8") as f:
        return f.read()


WITH_EXAMPLES = [n for n in MODULES if docstring_examples(_source(n))]


@pytest.mark.parametrize("name", WITH_EXAMPLES)
def test_docstring_examples(name):
    """N-14: every example of the module's docstrings runs and gives the output written under it."""
    mod = importlib.import_module(name)
    res = doctest.testmod(mod, report=False, optionflags=doctest.ELLIPSIS)
    assert res.attempted >= 1, f"doctest found none of the examples of {name}"
    assert res.failed == 0, f"{res.failed} of {res.attempted} docstring examples of {name} fail (python -m doctest)"


def test_every_chapter_module_of_the_reference_holds_examples():
    """N-14: each public module of the reference (one per spec chapter) has a worked example, so that the
    docstring test above runs it; the collection counts examples as doctest does."""
    chapters = [n for n in MODULES if n.startswith("softrtc.reference.") and not n.rsplit(".", 1)[1].startswith("_")]
    assert len(chapters) >= 12, chapters
    missing = [n for n in chapters if n not in WITH_EXAMPLES]
    assert not missing, f"reference modules without a worked example: {missing}"
    src = '"""Top.\n\n>>> 1 + 1\n2\n"""\n\ndef f():\n    """None here."""\n\nclass C:\n    def g(self):\n' \
          '        """\n        >>> 3\n        3\n        >>> 4\n        4\n        """\n'
    assert docstring_examples(src) == 3 and docstring_examples('"""No examples."""\n') == 0
