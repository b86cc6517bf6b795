"""Every requirement id defined in spec/ is named by at least one test that checks it (spec/00-overview.md).

A test *counts* for the ids its docstring names when both hold ([N-14]):

* it checks something: an ``assert``, a ``pytest.raises``, an ``assert_*``
  call (``np.testing.assert_allclose``, ...), or a call of a helper of its own
  module that does one of these;
* its expectation is not the reference's own output: it does not run only
  the reference through the conformance runner (``run("reference", ...)``, a
  ``Reference...`` adapter, ``--impl reference``), since the shipped vectors
  are what the reference generated, so such a run compares the reference
  with itself. A test that also runs a mutant, another implementation or a
  hand-made adapter counts.

Tests that check the JAX, PyTorch or another implementation against the
vectors count: the code under test did not produce them.
"""

import ast
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
    """N-14: requirement ids are unique across the spec (ids are stable, so a later rule may sit in an earlier
    section)."""
    seen = {}
    for f in sorted((ROOT / "spec").glob("*.md")):
        for m in DEF.finditer(f.read_text()):
            assert m.group(1) not in seen, f"{m.group(1)} defined in {seen.get(m.group(1))} and {f.name}"
            seen[m.group(1)] = f.name
    assert len(seen) > 50


# ----------------------------------------------------------------------------- what a test checks


def _call_name(call: ast.Call) -> str:
    f = call.func
    return f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""


def _own_checks(fn: ast.AST) -> bool:
    """An assert, a pytest.raises or an assert_* call directly in ``fn``."""
    for node in ast.walk(fn):
        if isinstance(node, ast.Assert):
            return True
        if isinstance(node, ast.Call) and (_call_name(node) == "raises" or _call_name(node).startswith("assert")):
            return True
    return False


def _names_reference(node: ast.AST) -> bool:
    """The reference implementation as an adapter: "reference", REF, ReferenceAdapter(), reference.ADAPTER..."""
    if isinstance(node, ast.Constant):
        return node.value == "reference"
    if isinstance(node, ast.Call):
        return _names_reference(node.func)
    name = node.attr if isinstance(node, ast.Attribute) else node.id if isinstance(node, ast.Name) else ""
    return name in ("REF", "reference", "ref_adapter") or name.startswith("Reference")


def _runner_runs(fn: ast.AST) -> tuple:
    """(runs the reference, runs another implementation) through the conformance runner, in Python or on the
    command line (``--impl NAME``)."""
    ref = other = False
    for node in ast.walk(fn):
        if isinstance(node, ast.Call) and _call_name(node) == "run" and node.args:
            if _names_reference(node.args[0]):
                ref = True
            else:
                other = True
        if isinstance(node, (ast.List, ast.Tuple)):
            words = [e.value for e in node.elts if isinstance(e, ast.Constant)]
            for a, b in zip(words, words[1:]):
                if a == "--impl":
                    ref, other = ref or b == "reference", other or b != "reference"
    return ref, other


def classify(source: str) -> dict:
    """``{test name: (docstring, checks, self_referential)}`` for the test functions of a module's source."""
    tree = ast.parse(source)
    funcs = {n.name: n for n in tree.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))}
    classes = [n for n in tree.body if isinstance(n, ast.ClassDef)]

    def called(fn):
        return {_call_name(c) for c in ast.walk(fn) if isinstance(c, ast.Call)} & set(funcs)

    # Helpers of the module that check, that run the reference and that run another implementation through the
    # runner (to a fixed point).
    checks = {n for n, f in funcs.items() if _own_checks(f)}
    runs_ref = {n for n, f in funcs.items() if _runner_runs(f)[0]}
    runs_other = {n for n, f in funcs.items() if _runner_runs(f)[1]}
    changed = True
    while changed:
        changed = False
        for n, f in funcs.items():
            for target in (checks, runs_ref, runs_other):
                if n not in target and called(f) & target:
                    target.add(n)
                    changed = True
    out = {}
    tests = [(n, f) for n, f in funcs.items() if n.startswith("test")]
    for c in classes:
        if c.name.startswith("Test"):
            tests += [(f"{c.name}.{f.name}", f) for f in c.body
                      if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef)) and f.name.startswith("test")]
    for name, f in tests:
        own = name.split(".")[-1]
        ref, other = _runner_runs(f)
        ref = own in runs_ref or ref or bool(called(f) & runs_ref)
        other = own in runs_other or other or bool(called(f) & runs_other)
        # Running a mutant, another implementation or a hand-made adapter as well is a check the reference's
        # own output cannot pass by construction.
        out[name] = (ast.get_docstring(f) or "", own in checks or _own_checks(f) or bool(called(f) & checks),
                     ref and not other)
    return out


def _all_tests() -> dict:
    """Every test function of ``tests/**/test_*.py`` but this file, by ``path::name``."""
    out = {}
    for p in sorted((ROOT / "tests").rglob("test_*.py")):
        if p.name == Path(__file__).name:
            continue
        rel = p.relative_to(ROOT).as_posix()
        for name, info in classify(p.read_text()).items():
            out[f"{rel}::{name}"] = info
    return out


def _named(i: str, doc: str) -> bool:
    return re.search(rf"(?<![A-Z-]){re.escape(i)}(?!\d)", doc) is not None


def test_the_coverage_rule_on_hand_made_tests():
    """N-14: the rule above, on a module written for it: a test without a check, one that runs only the reference
    on the vectors (directly, through a helper, or on the command line), one that runs a mutant too, and one whose
    helper asserts."""
    src = '''
def _same(a, b):
    assert a == b

def _ref_run(files):
    return runner.run("reference", files=files)

def test_no_check():
    """W-1"""
    weights.hard_weights(4, 1)

def test_reference_on_its_vectors(files):
    """W-2"""
    res = runner.run("reference", files=files)
    assert res.failed == 0

def test_reference_adapter_on_its_vectors(files):
    """W-3"""
    assert runner.run(ReferenceAdapter(), files=files).failed == 0

def test_through_a_helper(files):
    """W-4"""
    assert _ref_run(files).failed == 0

def test_command_line():
    """W-5"""
    assert main(["conformance", "run", "--impl", "reference"]) == 0

def test_jax_on_the_vectors(files):
    """W-6"""
    assert runner.run("jax", files=files).failed == 0

def test_mutant_and_reference(files):
    """W-10"""
    assert not runner.run(Mutant(), files=files).ok
    assert runner.run("reference", files=files).ok

def test_by_hand():
    """W-7"""
    _same(weights.hard_weights(2, 1).tolist(), [1.0, 0.0])

def test_raises():
    """W-8"""
    with pytest.raises(ValueError, match="^d must"):
        weights.hard_weights(2, 5)

class TestGroup:
    def test_in_a_class(self):
        """W-9"""
        np.testing.assert_allclose(weights.hard_weights(1, 1), [1.0])
'''
    got = {name: (checks, selfref) for name, (_, checks, selfref) in classify(src).items()}
    assert got == {"test_no_check": (False, False), "test_reference_on_its_vectors": (True, True),
                   "test_reference_adapter_on_its_vectors": (True, True), "test_through_a_helper": (True, True),
                   "test_command_line": (True, True), "test_jax_on_the_vectors": (True, False),
                   "test_mutant_and_reference": (True, False), "test_by_hand": (True, False),
                   "test_raises": (True, False),
                   "TestGroup.test_in_a_class": (True, False)}


def test_every_requirement_id_is_named_by_a_test_that_checks_it():
    """N-14: every requirement id in spec/ is named in the docstring of a test that counts by the rule above.

    Only docstrings of test functions count: an id in a comment, a helper or
    conftest.py does not make a rule tested.
    """
    tests = _all_tests()
    assert len(tests) > 300, len(tests)  # every test folder was read
    counting = "\n".join(doc for doc, checks, selfref in tests.values() if checks and not selfref)
    missing = {}
    for i in spec_ids():
        if not _named(i, counting):
            missing[i] = [t for t, (doc, _, _) in tests.items() if _named(i, doc)]
    assert not missing, ("requirement ids no counting test names (with the tests that name them but do not count): "
                         f"{missing}")


def test_no_test_compares_an_expression_with_itself():
    """N-14: no assert compares an expression with the same expression (``assert x == x``,
    ``assert_allclose(a, a)``): such a check passes whatever the code does."""
    same = []
    for p in sorted((ROOT / "tests").rglob("test_*.py")):
        for node in ast.walk(ast.parse(p.read_text())):
            pairs = []
            if isinstance(node, ast.Compare) and len(node.ops) == 1:
                pairs.append((node.left, node.comparators[0]))
            if isinstance(node, ast.Call) and _call_name(node).startswith("assert") and len(node.args) >= 2:
                pairs.append((node.args[0], node.args[1]))
            for a, b in pairs:
                # The same call twice is a determinism check ([N-9]); the same name or constant is not a check.
                if ast.dump(a) == ast.dump(b) and not isinstance(a, ast.Call) and not (
                        isinstance(a, ast.Attribute) and isinstance(a.value, ast.Call)):
                    same.append(f"{p.relative_to(ROOT)}:{node.lineno}: {ast.unparse(node)[:100]}")
    assert not same, same


def test_only_the_missing_levels_skip_is_tolerated():
    """With SOFTRTC_REQUIRE_ALL=1 a skip fails the run unless its reason is exactly the missing
    benchmark levels; a missing package, or a reason that merely mentions ../shared, is not tolerated."""
    from tests.conftest import SHARED_LEVELS_REASON, tolerated_skip

    assert tolerated_skip(("f.py", 3, f"Skipped: {SHARED_LEVELS_REASON}"))
    assert not tolerated_skip(("f.py", 3, "Skipped: needs kinetix-env"))
    assert not tolerated_skip(("f.py", 3, "Skipped: needs kinetix-env and ../shared/kinetix-levels"))
    assert not tolerated_skip(("f.py", 3, "Skipped: could not import 'kinetix': No module named 'kinetix'"))
