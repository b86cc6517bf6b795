"""Under pytest-xdist the files holding a test marked ``slow`` run first (tests/conftest.py); one process keeps
pytest's order."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

FAST = "def test_a1():\n    pass\n\n\ndef test_a2():\n    pass\n"
SLOW = "import pytest\n\n\ndef test_b0():\n    pass\n\n\n@pytest.mark.slow\ndef test_b1():\n    pass\n"


@pytest.mark.parametrize("workers", [[], ["-n", "1", "--dist", "loadfile", "--no-loadscope-reorder"]],
                         ids=["one process", "one xdist worker"])
def test_files_with_slow_tests_start_first_under_xdist(tmp_path, workers):
    """The run order of four tests in two files: the file with the slow test first under xdist, each file's
    tests in their written order; collection order in one process."""
    if workers:
        pytest.importorskip("xdist")
    tests = tmp_path / "tests"
    tests.mkdir()
    for f in ("__init__.py", "conftest.py"):
        shutil.copy(ROOT / "tests" / f, tests / f)
    (tests / "test_a.py").write_text(FAST)
    (tests / "test_b.py").write_text(SLOW)
    (tmp_path / "pytest.ini").write_text("[pytest]\nmarkers =\n    slow: a long test\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTEST_", "SOFTRTC_REQUIRE"))}
    run = subprocess.run([sys.executable, "-m", "pytest", "-v", "-p", "no:cacheprovider", *workers, "tests"],
                         cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    order = [word.split("::")[1] for line in run.stdout.splitlines() if "PASSED" in line
             for word in line.split() if word.startswith("tests/test_")]
    expected = ["test_b0", "test_b1", "test_a1", "test_a2"] if workers else ["test_a1", "test_a2", "test_b0", "test_b1"]
    assert order == expected, run.stdout[-3000:]
