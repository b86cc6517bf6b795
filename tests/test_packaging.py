"""The distribution as a user installs it ([N-13]).

The wheel and the sdist are built from this checkout; the wheel is installed
without ``-e`` into a fresh virtual environment holding NumPy alone (plus pytest
and hypothesis to run the reference's tests), away from the source tree. There
the runner must pass the reference adapter on the shipped vectors, ``softrtc
--help`` and ``import softrtc.reference`` must work, a command whose extra is
missing must say which extra in one line, and the reference's own tests, copied
out of the checkout, must pass without JAX.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(cmd, **kw):
    return subprocess.run([str(c) for c in cmd], capture_output=True, text=True, **kw)


@pytest.fixture(scope="module")
def dists(tmp_path_factory):
    """The sdist and the wheel built from it (``python -m build`` builds the wheel from the sdist, so a file
    missing from the sdist is missing from the wheel too)."""
    out = tmp_path_factory.mktemp("dist")
    build = _run([sys.executable, "-m", "build", "--no-isolation", "--outdir", out, ROOT], cwd=ROOT)
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    log = build.stdout + build.stderr
    # [N-13] Set-up prints no warnings of the project's own making.
    for marker in ("SetuptoolsDeprecationWarning", "license` as a TOML table", "Warning:"):
        assert marker not in log, f"the build printed {marker!r}:\n{log[-3000:]}"
    (wheel,) = out.glob("softrtc-*.whl")
    (sdist,) = out.glob("softrtc-*.tar.gz")
    return wheel, sdist


@pytest.mark.slow
def test_wheel_holds_the_three_packages_and_their_data(dists):
    """N-13: one distribution; the reference and the conformance suite install as softrtc.reference and
    softrtc.conformance (nothing as a top-level ``reference`` or ``conformance``), with the vectors and the
    arm and Kinetix checkpoints as package data."""
    wheel, sdist = dists
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert tops == {"softrtc"}, tops
    vectors = sorted(p.name for p in (ROOT / "conformance" / "vectors").glob("*.json"))
    for v in vectors:
        assert f"softrtc/conformance/vectors/{v}" in names
    for ck in ("base", "train_hard", "train_soft", "drift/base"):
        assert f"softrtc/arm/checkpoints/{ck}.npz" in names
    assert "softrtc/kinetix/checkpoints/m_h0_unicycle.npz" in names  # the served Kinetix base ([CR-14])
    for module in ("reference/weights.py", "conformance/runner.py", "reference_cli.py", "cli.py"):
        assert f"softrtc/{module}" in names
    assert not any(n.startswith("softrtc/reference/cli") for n in names)
    members = tarfile.open(sdist).getnames()
    for path in ("reference/weights.py", "conformance/vectors/index.json", "conformance/ports/js/protocol.js",
                 "conformance/ports/js/softrtc.js", "spec/00-overview.md",
                 "tests/reference/test_reference_weights.py", "LICENSE"):
        assert any(m.endswith(path) for m in members), path


@pytest.mark.slow
def test_numpy_only_install_runs_the_suite_and_the_reference_tests(dists, tmp_path):
    """N-13, CF-19: a non-editable install with NumPy alone runs the reference adapter through the runner and
    passes, and the reference's tests pass there without JAX."""
    wheel, _ = dists
    venv = tmp_path / "venv"
    assert _run([sys.executable, "-m", "venv", venv]).returncode == 0
    py, bin_ = venv / "bin" / "python", venv / "bin"
    pip = _run([py, "-m", "pip", "install", "--quiet", wheel, "pytest", "hypothesis"])
    assert pip.returncode == 0, pip.stderr[-3000:]
    listed = _run([py, "-m", "pip", "list", "--format=freeze"]).stdout.lower()
    for heavy in ("jax", "torch", "flax", "pymunk"):
        assert f"\n{heavy}==" not in "\n" + listed, f"{heavy} was installed with the plain wheel"

    work = tmp_path / "elsewhere"  # no source tree around: imports must come from the installed wheel
    work.mkdir()
    env = {"PATH": f"{bin_}:/usr/bin:/bin", "HOME": str(tmp_path)}
    where = _run([py, "-c", "import softrtc.reference, softrtc.conformance as c; print(softrtc.reference.__file__);"
                            "print(c.vectors_dir())"], cwd=work, env=env)
    assert where.returncode == 0, where.stderr
    assert all(str(venv) in line for line in where.stdout.split()), where.stdout

    helped = _run([bin_ / "softrtc", "--help"], cwd=work, env=env)
    assert helped.returncode == 0 and "conformance" in helped.stdout, helped.stderr
    run = _run([bin_ / "softrtc", "conformance", "run", "--impl", "reference"], cwd=work, env=env)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    assert "0 failed" in run.stdout, run.stdout[-2000:]
    missing = _run([bin_ / "softrtc", "bench", "runtime"], cwd=work, env=env)
    assert missing.returncode == 2
    assert missing.stderr.strip().splitlines() == [
        "softrtc bench: error: argument SUBCOMMAND: invalid choice: 'runtime' (choose from 'torch'); the others "
        "need the 'jax' extra (missing module jax): pip install 'softrtc[jax]'"], missing.stderr
    for command in (["arm", "train"], ["kinetix", "eval"]):
        missing = _run([bin_ / "softrtc", *command], cwd=work, env=env)
        extra = command[0]
        assert missing.returncode == 2 and missing.stderr.strip().splitlines() == [
            f"softrtc {extra}: error: needs the '{extra}' extra (missing module jax): pip install 'softrtc[{extra}]'"
        ], missing.stderr

    tests = work / "tests"
    shutil.copytree(ROOT / "tests" / "reference", tests / "reference")
    for f in ("__init__.py", "conftest.py"):
        shutil.copy(ROOT / "tests" / f, tests / f)
    ran = _run([py, "-m", "pytest", "-q", "-p", "no:cacheprovider", "tests/reference"], cwd=work,
               env=dict(env, SOFTRTC_REQUIRE_ALL="1"))
    assert ran.returncode == 0, ran.stdout[-4000:] + ran.stderr[-2000:]
    assert " passed" in ran.stdout and "skipped" not in ran.stdout, ran.stdout[-2000:]


def test_source_imports_once_under_one_name():
    """N-13: in this checkout, softrtc.reference and softrtc.conformance come from the top-level folders and
    no module is loaded twice under a second name."""
    import softrtc.conformance
    import softrtc.reference

    assert Path(softrtc.reference.__file__).parent == ROOT / "reference"
    assert Path(softrtc.conformance.__file__).parent == ROOT / "conformance"
    assert softrtc.conformance.vectors_dir() == ROOT / "conformance" / "vectors"
    assert "reference" not in sys.modules and "conformance" not in sys.modules
    assert not (ROOT / "softrtc" / "reference").exists() and not (ROOT / "softrtc" / "conformance").exists()
