"""SOFTRTC_REQUIRE_ALL=1 (set by `make test`) fails a run that skipped a test, whether the suite runs in one
process or is spread over pytest-xdist workers (`make test` runs it on two)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import SHARED_LEVELS_REASON

ROOT = Path(__file__).resolve().parents[1]

SKIPS = f'''
import pytest


def test_runs():
    assert 1 + 1 == 2


def test_levels_absent():
    pytest.skip({SHARED_LEVELS_REASON!r})


def test_package_absent():
    pytest.importorskip("softrtc_no_such_module")
'''


def _suite(tmp_path: Path, workers: list) -> subprocess.CompletedProcess:
    """Runs a three-test suite under this repository's conftest with SOFTRTC_REQUIRE_ALL=1."""
    tests = tmp_path / "tests"
    tests.mkdir(parents=True)
    for f in ("__init__.py", "conftest.py"):
        shutil.copy(ROOT / "tests" / f, tests / f)
    (tests / "test_skips.py").write_text(SKIPS)
    # The outer run's xdist and pytest variables would leak into the inner run.
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTEST_", "SOFTRTC_REQUIRE"))}
    env["SOFTRTC_REQUIRE_ALL"] = "1"
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *workers, "tests"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("workers", [[], ["-n", "2"]], ids=["one process", "two xdist workers"])
def test_a_skip_for_a_missing_package_fails_the_run(tmp_path, workers):
    """A test skipped because a package is missing fails the run (exit status 1) and is named; the one
    tolerated skip, the absent benchmark levels, is not; the passing test still passes."""
    if workers:
        pytest.importorskip("xdist")
    run = _suite(tmp_path, workers)
    assert run.returncode == 1, run.stdout[-3000:] + run.stderr[-2000:]
    assert "1 passed, 2 skipped" in run.stdout, run.stdout[-3000:]
    named = [line.split("SOFTRTC_REQUIRE_ALL: skipped ", 1)[1] for line in run.stdout.splitlines()
             if "SOFTRTC_REQUIRE_ALL: skipped " in line]
    assert len(named) == 1 and named[0].startswith("tests/test_skips.py::test_package_absent: "), run.stdout[-3000:]
