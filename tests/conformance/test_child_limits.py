"""Hostile children of the protocol: deeply nested JSON, grandchildren, endless stderr, runaway memory and
integer outputs that are not integers ([CF-18], [CF-29], [CF-30], [CF-35], [CF-36], [CF-37]).

Each fake implementation below is a few lines of plain Python speaking the protocol for ``standard_error``
(and ``sample_delay`` for integer outputs); it misbehaves the way its mode says and answers correctly
otherwise, so every test can check that exactly the misbehaving cases fail and the run goes on.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import pytest

from softrtc.conformance import protocol, runner
from softrtc.conformance.protocol import ImplementationError

ROOT = Path(__file__).resolve().parents[2]

FAKE = r"""
import json, os, subprocess, sys, time
mode, state = sys.argv[1], sys.argv[2]
hello = {"protocol": "softrtc-conformance", "version": 1, "name": "fake",
         "functions": ["standard_error"]}
if mode == "deep-hello":
    sys.stdout.write("[" * 100000 + "\n")
    sys.stdout.flush()
    sys.stdin.read()
    sys.exit(0)
if mode == "grandchild-idle":
    # a helper process that outlives this one unless the runner ends the whole process group
    p = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
    open(state, "a").write(f"{p.pid}\n")
print(json.dumps(hello), flush=True)
first = not os.path.exists(state + ".done")
open(state + ".done", "a").close()

def reply(rid, **kw):
    print(json.dumps(dict(id=rid, **kw)), flush=True)

for line in sys.stdin:
    req = json.loads(line)
    if first and mode == "deep-reply":
        first = False
        sys.stdout.write("[" * 100000 + "\n")
        sys.stdout.flush()
        continue
    if first and mode == "grandchild-exit":
        p = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
        open(state, "a").write(f"{p.pid}\n")
        os._exit(0)
    if first and mode == "stderr-flood":
        block = ("x" * 1023 + "\n").encode()
        for _ in range(int(sys.argv[3]) * 1024):
            os.write(2, block)
        os.write(2, b"last words before exiting\n")
        os._exit(3)
    if first and mode == "allocate-and-die":
        hog = bytearray(int(sys.argv[3]) * 1024 * 1024)  # no except: the MemoryError ends the process
    if first and mode == "allocate":
        first = False
        try:
            hog = bytearray(int(sys.argv[3]) * 1024 * 1024)
        except MemoryError:
            reply(req["id"], error={"kind": "exception", "type": "MemoryError", "message": ""})
            continue
    first = False
    v = req["args"]["values"]
    if not isinstance(v, list) or len(v) < 2 or any(isinstance(x, list) for x in v):
        reply(req["id"], error={"kind": "invalid_input", "type": "ValueError", "message": "bad"})
        continue
    m = sum(v) / len(v)
    reply(req["id"], result={"value": (sum((x - m) ** 2 for x in v) / (len(v) - 1) / len(v)) ** 0.5})
"""


def _fake(tmp_path, mode: str, *extra) -> str:
    f = tmp_path / "fake.py"
    f.write_text(FAKE)
    return " ".join([sys.executable, str(f), mode, str(tmp_path / "state"), *map(str, extra)])


def _cli(*args, timeout=180, **kw):
    return subprocess.run([sys.executable, "-m", "softrtc.conformance", "run", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout, **kw)


def _alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie waiting for its parent to reap it does not)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return False
    return stat.rsplit(")", 1)[1].split()[0] not in ("Z", "X")


# ---------------------------------------------------------------- deeply nested JSON on the pipe

def test_a_deeply_nested_reply_fails_its_case_with_one_line(tmp_path):
    """[CF-29], [CF-18] A reply nested far deeper than Python's parser follows fails the case in flight as a
    protocol error (no RecursionError escapes the runner); the run goes on in a fresh child and every other
    case passes."""
    res = runner.run(impl_cmd=_fake(tmp_path, "deep-reply"), only={"standard_error"}, case_timeout=20)
    failed = [c for c in res.cases if c.status == "fail"]
    assert len(failed) == 1 and "protocol error" in failed[0].message and "nested" in failed[0].message, \
        [c.message for c in failed]
    assert res.counts["pass"] == len(res.cases) - 1 > 3


def test_a_deeply_nested_hello_ends_the_run_with_one_line(tmp_path):
    """[CF-29], [CF-30], [CF-16] A hello line nested too deeply ends the run: ImplementationError from run(),
    and from the command line exit 2 with one error line and no traceback."""
    with pytest.raises(ImplementationError, match="hello line"):
        runner.run(impl_cmd=_fake(tmp_path, "deep-hello"), only={"standard_error"}, start_timeout=20)
    r = _cli("--impl-cmd", _fake(tmp_path, "deep-hello"), "--only", "standard_error")
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and r.stdout == "" and len(lines) == 1, r.stderr
    assert "hello line" in lines[0] and "Traceback" not in r.stderr


# ---------------------------------------------------------------- the child's process group

def test_grandchildren_never_outlive_the_run(tmp_path):
    """[CF-35] A child that starts a helper process and then serves normally: when the run ends (stdin
    closed, the child exits at once) the helper, in the child's process group, is killed too."""
    res = runner.run(impl_cmd=_fake(tmp_path, "grandchild-idle"), only={"standard_error"}, case_timeout=20)
    assert res.ok
    pids = [int(p) for p in (tmp_path / "state").read_text().split()]
    assert pids and _all_gone(pids), pids


def _all_gone(pids, within: float = 5.0) -> bool:
    """Whether every process of ``pids`` has ended within ``within`` seconds: SIGKILL to a group is delivered
    asynchronously, so on a loaded machine a member may still be scheduled for a moment after killpg returns."""
    deadline = time.monotonic() + within
    while any(_alive(p) for p in pids):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def test_a_child_that_exits_at_once_is_reported_as_exited_not_timed_out(tmp_path):
    """[CF-30], [CF-35] A child that starts a helper (which keeps its stdout open) and exits with status 0
    fails its case as "exited with status 0" at once, not as a time-out after --case-timeout, and the
    helper does not survive the run."""
    res = runner.run(impl_cmd=_fake(tmp_path, "grandchild-exit"), only={"standard_error"}, case_timeout=60)
    failed = [c for c in res.cases if c.status == "fail"]
    assert len(failed) == 1 and "exited with status 0" in failed[0].message, [c.message for c in failed]
    assert failed[0].seconds < 30 and res.counts["pass"] == len(res.cases) - 1
    pids = [int(p) for p in (tmp_path / "state").read_text().split()]
    assert pids and _all_gone(pids), pids


# ---------------------------------------------------------------- the child's stderr

def test_an_endless_stderr_keeps_a_bounded_tail(tmp_path):
    """[CF-36] A child that writes 256 MiB to stderr before exiting: the runner keeps only the tail. No file
    grows with it (the run is limited to 8 MiB per written file, which an unbounded capture of the child's
    stderr in a file breaks), the runner's peak resident memory stays far below what was written, and the
    failure still names the child's last stderr line."""
    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (8 << 20, 8 << 20))

    # A fresh process runs the runner, so its RUSAGE_CHILDREN peak is the runner's (or its small child's).
    measure = ("import resource, subprocess, sys; r = subprocess.run(sys.argv[1:]); "
               "print('maxrss', resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, file=sys.stderr); "
               "sys.exit(r.returncode)")
    p = subprocess.run([sys.executable, "-c", measure, sys.executable, "-m", "softrtc.conformance", "run",
                        "--impl-cmd", _fake(tmp_path, "stderr-flood", 256), "--only", "standard_error"], cwd=ROOT,
                       capture_output=True, text=True, preexec_fn=limit, timeout=300)
    assert p.returncode == 1, p.stdout + p.stderr
    assert "exited with status 3 (last stderr line: last words before exiting)" in p.stdout, p.stdout
    maxrss_kib = int(p.stderr.strip().splitlines()[-1].split()[-1])
    assert maxrss_kib < 192 * 1024, maxrss_kib  # the runner held no copy of the 256 MiB


def test_stderr_tail_is_bounded_in_memory():
    """[CF-36] The tail kept of a stream is at most STDERR_TAIL bytes, and it is the stream's end."""
    tail = protocol.Tail(limit=1000)
    for i in range(5000):
        tail.add(f"line {i}\n".encode())
    kept = tail.bytes()
    assert len(kept) <= 1000 and kept.endswith(b"line 4999\n") and b"line 4000\n" not in kept
    assert protocol.STDERR_TAIL <= 1 << 20


# ---------------------------------------------------------------- the child's memory

def test_a_case_over_the_memory_limit_fails_with_one_line(tmp_path):
    """[CF-37] With --case-memory-mb 512 a case that allocates 2 GiB fails, its message saying it ran out of
    the memory limit; the other cases pass in the same child (exit 1, a summary, no traceback)."""
    r = _cli("--impl-cmd", _fake(tmp_path, "allocate", 2048), "--only", "standard_error",
             "--case-memory-mb", "512")
    assert r.returncode == 1 and "Traceback" not in r.stdout + r.stderr, r.stdout + r.stderr
    fails = [ln for ln in r.stdout.splitlines() if ln.startswith("  FAIL M.")]
    assert len(fails) == 1 and "memory limit of 512 MB (--case-memory-mb)" in fails[0], r.stdout


def test_a_child_that_dies_of_the_memory_limit_is_named_so(tmp_path):
    """[CF-37], [CF-30] A child that dies of the limit (an uncaught MemoryError; Python exits with status 1)
    fails its case as a lost child whose message names the memory limit; the run goes on in a fresh child."""
    res = runner.run(impl_cmd=_fake(tmp_path, "allocate-and-die", 2048), only={"standard_error"},
                     case_memory_mb=512, case_timeout=60)
    failed = [c for c in res.cases if c.status == "fail"]
    assert len(failed) == 1 and "exited with status 1" in failed[0].message, [c.message for c in failed]
    assert "MemoryError" in failed[0].message and "memory limit of 512 MB (--case-memory-mb)" in failed[0].message
    assert res.counts["pass"] == len(res.cases) - 1


def test_the_memory_limit_is_checked_at_the_door(tmp_path):
    """[CF-37], [N-7] --case-memory-mb takes an integer number of megabytes in [256, 1048576]; anything else
    is a usage error (exit 2, one line naming the option), and run() raises ValueError naming it."""
    for bad in ("0", "100", "4096.5", "1e9", "abc", "2000000"):
        r = _cli("--impl", "reference", "--case-memory-mb", bad)
        assert r.returncode == 2 and "--case-memory-mb" in r.stderr and r.stdout == "", (bad, r.stderr)
    for bad in (0, 255, 4096.0, True, 1 << 21):
        with pytest.raises(ValueError, match="case_memory_mb"):
            runner.run("reference", case_memory_mb=bad)


def test_the_default_memory_limit_lets_the_built_in_adapters_run():
    """[CF-37] The default limit is generous: the reference's child runs its sampler cases under it."""
    assert runner.DEFAULT_CASE_MEMORY_MB >= 4096
    res = runner.run("reference", only={"naive_sample", "guided_sample"})
    assert res.ok


# ---------------------------------------------------------------- integer outputs

RETURNS = """import numpy as np
from softrtc.conformance.adapters.reference import ReferenceAdapter
name = "returns"
_ref = ReferenceAdapter()

def endpoint(rule, d):
    return CONV(_ref.endpoint(rule, d))

def sample_delay(probs, d_min, u):
    return CONV(_ref.sample_delay(probs, d_min, u))
"""


@pytest.mark.parametrize("conv,ok", [
    ("float", False), ("np.float64", False), ("lambda v: np.array(v, dtype=np.float32)", False),
    ("lambda v: np.bool_(v % 2)", False),
    ("int", True), ("np.int64", True), ("np.int32", True), ("lambda v: np.array(v, dtype=np.int16)", True),
])
@pytest.mark.parametrize("in_process", [False, True])
def test_integer_outputs_must_be_integers(tmp_path, conv, ok, in_process):
    """[CF-5], [CF-29] An integer output (endpoint's e, sample_delay's d) returned as a float (4.0 on the
    protocol), as a boolean (true/false on the protocol) or as a list fails every valid case, even where its
    value equals the expected integer, in a child and in process; NumPy or Python integers pass."""
    f = tmp_path / "returns.py"
    f.write_text(RETURNS.replace("CONV(", f"({conv})("))
    res = runner.run(str(f), only={"endpoint", "sample_delay"}, in_process=in_process)
    if ok:
        assert res.ok, [c.message for c in res.cases if c.status == "fail"][:3]
        return
    valid = [c for c in res.cases if ".reject." not in c.id]
    assert valid and all(c.status == "fail" for c in valid), \
        [c.message for c in valid if c.status != "fail"][:3]
    assert all("integer" in c.message for c in valid), valid[0].message
