"""The worked examples in the docstrings of every softrtc module are run, so none can drift from the code."""

import doctest
import importlib
import pkgutil

import pytest

import softrtc

MODULES = sorted(m.name for m in pkgutil.walk_packages(softrtc.__path__, "softrtc.")
                 if not m.name.endswith("__main__"))


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    mod = importlib.import_module(name)
    res = doctest.testmod(mod, report=False, optionflags=doctest.ELLIPSIS)
    assert res.failed == 0, f"{res.failed} of {res.attempted} docstring examples of {name} fail (python -m doctest)"


def test_the_docstrings_hold_examples():
    """The reference's worked examples exist: a doctest run that finds none checks nothing."""
    attempted = sum(doctest.testmod(importlib.import_module(n), report=False).attempted
                    for n in MODULES if n.startswith("softrtc.reference."))
    assert attempted >= 15
