"""The files a run reads and writes: which vectors ran (and whether they are the shipped set), vector files
that are no regular files or are too large, and output paths that clash or are special files ([CF-15],
[CF-39], [CF-40])."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from softrtc.conformance import runner
from softrtc.conformance.adapters.reference import ReferenceAdapter
from softrtc.conformance.vectors_io import MAX_VECTOR_FILE_BYTES, VectorError, load_vectors

ROOT = Path(__file__).resolve().parents[2]
VECTORS = ROOT / "conformance" / "vectors"

def _cli(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "softrtc.conformance", "run", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)


def _shipped_digest() -> str:
    index = json.loads((VECTORS / "index.json").read_text())
    lines = "".join(f"{e['sha256']}  {n}\n" for n, e in sorted(index["files"].items()))
    return hashlib.sha256(lines.encode()).hexdigest()


def _copy_without_errors(tmp_path, with_index: bool) -> Path:
    """A copy of the shipped vectors with every error case removed and index.json regenerated (or removed)."""
    d = tmp_path / "trimmed"
    shutil.copytree(VECTORS, d)
    index = json.loads((d / "index.json").read_text())
    for p in sorted(d.glob("*.json")):
        if p.name == "index.json":
            continue
        data = json.loads(p.read_text())
        data["cases"] = [c for c in data["cases"] if "error" not in c["expected"]]
        raw = json.dumps(data).encode()
        p.write_bytes(raw)
        index["files"][p.name].update(sha256=hashlib.sha256(raw).hexdigest(), cases=len(data["cases"]))
    if with_index:
        (d / "index.json").write_text(json.dumps(index))
    else:
        (d / "index.json").unlink()
    return d


# ---------------------------------------------------------------- which vectors ran ([CF-39])

def test_a_run_names_its_vectors_and_says_they_are_the_shipped_set(tmp_path):
    """[CF-39], [CF-14], [CF-15] A run on the shipped vectors (or on a byte-identical copy elsewhere) says so on
    its second line, with the set's digest (SHA-256 of the sorted "sha256  name" lines of its files,
    computed here from index.json); the JSON report and the JUnit XML carry the folder, every file's SHA-256,
    the digest and shipped = true."""
    rep, junit = tmp_path / "r.json", tmp_path / "j.xml"
    r = _cli("--impl", "reference", "--only", "endpoint", "--report", str(rep), "--junit", str(junit))
    assert r.returncode == 0, r.stdout + r.stderr
    digest = _shipped_digest()
    line = r.stdout.splitlines()[1]
    assert line.startswith("vectors: the shipped set") and digest[:16] in line, line
    data = json.loads(rep.read_text())["vectors"]
    index = json.loads((VECTORS / "index.json").read_text())
    assert data["shipped"] is True and data["digest"] == digest and Path(data["folder"]) == VECTORS.resolve()
    assert data["files"] == {n: e["sha256"] for n, e in index["files"].items()}
    props = {p.get("name"): p.get("value") for p in ET.parse(junit).getroot().iter("property")}
    assert props["vectors_digest"] == digest and props["vectors_shipped"] == "true"
    copy = tmp_path / "copy"
    shutil.copytree(VECTORS, copy)
    res = runner.run(ReferenceAdapter(), copy, only={"endpoint"})
    assert res.vectors["shipped"] is True and res.vectors["digest"] == digest
    assert Path(res.vectors["folder"]) == copy.resolve()


@pytest.mark.parametrize("with_index", [True, False])
def test_a_run_on_other_vectors_says_so_in_its_summary_line(tmp_path, with_index):
    """[CF-39] A vector folder with its error cases removed (index.json regenerated, or no index at all) passes
    an implementation that would accept invalid input (none is left to reject), but the run's last line says
    the vectors are not the shipped set and names the folder, and the report says shipped = false with the
    other digest."""
    d = _copy_without_errors(tmp_path, with_index)
    f = tmp_path / "lax.py"
    f.write_text("from softrtc.conformance.adapters.reference import ReferenceAdapter\nname = 'lax'\n"
                 "hard_weights = ReferenceAdapter().hard_weights\n")
    rep = tmp_path / "r.json"
    r = _cli("--impl", str(f), "--vectors", str(d), "--report", str(rep))
    assert r.returncode == 0, r.stdout + r.stderr
    last = r.stdout.splitlines()[-1]
    assert last.startswith("PASS:") and "NOT the shipped vectors" in last and str(d) in last, last
    assert r.stdout.splitlines()[1].startswith("vectors: NOT the shipped set")
    data = json.loads(rep.read_text())["vectors"]
    assert data["shipped"] is False and data["digest"] != _shipped_digest() and data["index"] is with_index


# ---------------------------------------------------------------- vector files that are no regular files

def _mkfifo_or_skip(path: Path) -> None:
    if not hasattr(os, "mkfifo"):
        pytest.skip("no FIFOs on this platform")
    os.mkfifo(path)


@pytest.mark.parametrize("name", ["metrics.json", "index.json"])
@pytest.mark.parametrize("kind", ["fifo", "zero", "large", "folder"])
def test_a_vector_file_that_is_no_regular_file_is_refused_without_hanging(tmp_path, name, kind):
    """[CF-40], [CF-16] A vector file or index.json that is a FIFO, a symbolic link to /dev/zero, a folder, or
    larger than MAX_VECTOR_FILE_BYTES is refused with one error line naming it before anything is read from
    it: exit 2, within the time limit (a FIFO nobody writes to would block a plain read for ever)."""
    d = tmp_path / "v"
    shutil.copytree(VECTORS, d)
    target = d / name
    target.unlink()
    if kind == "fifo":
        _mkfifo_or_skip(target)
    elif kind == "zero":
        if not os.path.exists("/dev/zero"):
            pytest.skip("no /dev/zero")
        target.symlink_to("/dev/zero")
    elif kind == "folder":
        target.mkdir()
    else:
        with open(target, "wb") as fh:  # sparse: no disk used
            fh.truncate(MAX_VECTOR_FILE_BYTES + 1)
    with pytest.raises(VectorError, match=name.replace(".", r"\.")) as info:
        load_vectors(d)
    assert ("not a regular file" in str(info.value)) == (kind != "large"), str(info.value)
    r = _cli("--impl", "reference", "--vectors", str(d), timeout=60)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and r.stdout == "" and len(lines) == 1 and name in lines[0], r.stderr


# ---------------------------------------------------------------- output paths ([CF-15], [CF-40])

def test_report_and_junit_on_the_same_path_are_refused(tmp_path):
    """[CF-15], [N-11] --report and --junit naming one file (also spelt differently, or a hard link to it) is a
    usage error before any case runs: exit 2, one line naming both options, nothing written."""
    out = tmp_path / "out.xml"
    for other in (str(out), str(tmp_path / "." / "out.xml")):
        r = _cli("--impl", "reference", "--only", "endpoint", "--report", str(out), "--junit", other)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and r.stdout == "" and len(lines) == 1, r.stdout + r.stderr
        assert "--report" in lines[0] and "--junit" in lines[0] and "same file" in lines[0]
        assert not out.exists() and list(tmp_path.iterdir()) == []
    out.write_text("old")
    os.link(out, tmp_path / "hard.xml")
    r = _cli("--impl", "reference", "--only", "endpoint", "--report", str(out), "--junit", str(tmp_path / "hard.xml"))
    assert r.returncode == 2 and "same file" in r.stderr and out.read_text() == "old", r.stderr


@pytest.mark.parametrize("kind", ["symlink", "dangling", "fifo", "device"])
@pytest.mark.parametrize("option", ["--report", "--junit"])
def test_an_output_path_that_is_a_special_file_is_refused(tmp_path, kind, option):
    """[CF-15], [N-11] An output path that is a symbolic link (to a file, or dangling), a FIFO or a device is
    refused before any case runs: exit 2, one line naming the option and the path; the entry is left as it
    was (a plain rename would replace the link or the FIFO with a regular file)."""
    out = tmp_path / "out.json"
    if kind == "symlink":
        (tmp_path / "real.json").write_text("keep")
        out.symlink_to(tmp_path / "real.json")
    elif kind == "dangling":
        out.symlink_to(tmp_path / "nowhere.json")
    elif kind == "fifo":
        _mkfifo_or_skip(out)
    else:
        if not os.path.exists("/dev/null"):
            pytest.skip("no /dev/null")
        out = Path("/dev/null")
    before = os.lstat(out)
    r = _cli("--impl", "reference", "--only", "endpoint", option, str(out), timeout=60)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and r.stdout == "" and len(lines) == 1, r.stdout + r.stderr
    assert option in lines[0] and str(out) in lines[0], lines[0]
    after = os.lstat(out)
    assert (after.st_mode, after.st_ino) == (before.st_mode, before.st_ino)
    if kind == "symlink":
        assert (tmp_path / "real.json").read_text() == "keep"


def test_reports_are_written_through_a_temporary_file(tmp_path, monkeypatch):
    """[CF-15] The JSON report goes through a temporary file in the same folder and a rename: a failure of the
    rename leaves the old report as it was and no temporary file behind."""
    res = runner.run(ReferenceAdapter(), only={"endpoint"})
    rep = tmp_path / "r.json"
    rep.write_text("old")

    def fail(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(OSError):
        runner.write_report(res, rep)
    assert rep.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["r.json"]
    monkeypatch.undo()
    runner.write_report(res, rep)
    assert json.loads(rep.read_text())["counts"]["pass"] == len(res.cases)


def test_the_compatibility_report_refuses_special_output_paths(tmp_path):
    """[CF-15], [TP-1] `conformance report --out` is checked the same way before the implementation runs: a
    symbolic link as the Markdown file, or a FIFO where its JSON goes, is one error line, exit 2."""
    (tmp_path / "real.md").write_text("keep")
    (tmp_path / "link.md").symlink_to(tmp_path / "real.md")
    r = subprocess.run([sys.executable, "-m", "softrtc.conformance", "report", "--impl", "lerobot", "--out",
                        str(tmp_path / "link.md")], cwd=ROOT, capture_output=True, text=True, timeout=60)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "--out" in lines[0] and "symbolic link" in lines[0], r.stderr
    assert (tmp_path / "real.md").read_text() == "keep"
    _mkfifo_or_skip(tmp_path / "plain.json")
    r = subprocess.run([sys.executable, "-m", "softrtc.conformance", "report", "--impl", "lerobot", "--out",
                        str(tmp_path / "plain.md")], cwd=ROOT, capture_output=True, text=True, timeout=60)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "FIFO" in lines[0], r.stderr
