"""The implementation in a child process: hangs, exits, crashes and tampering are failed cases, never a
verdict of the implementation's own ([CF-29], [CF-30], [CF-31]).

Each adapter below misbehaves on one case only (E.endpoint.hard.d3) and is the reference everywhere else,
so every test checks that exactly that case fails, the others pass and the run goes on with a summary.
Time limits are tiny: the hanging case waits on an event nobody sets, for --case-timeout seconds only.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from softrtc.conformance import runner
from softrtc.conformance.adapter import AdapterError
from softrtc.conformance.protocol import ImplementationError

ROOT = Path(__file__).resolve().parents[2]
BAD_CASE = "E.endpoint.hard.d3"

_HEAD = """from softrtc.conformance.adapters.reference import ReferenceAdapter
name = "misbehaving"
_ref = ReferenceAdapter()

def endpoint(rule, d):
    if rule.get("kind") == "hard" and d == 3 and not isinstance(d, bool):
{action}
    return _ref.endpoint(rule, d)
"""

ACTIONS = {
    "hang": "        import threading\n        threading.Event().wait()",
    "exit": "        import os\n        os._exit(0)",
    "crash": "        import os, signal\n        os.kill(os.getpid(), signal.SIGKILL)",
}


def _cli(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "softrtc.conformance", "run", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)


def _adapter(tmp_path, kind: str) -> Path:
    f = tmp_path / f"{kind}_adapter.py"
    f.write_text(_HEAD.format(action=ACTIONS[kind]))
    return f


@pytest.mark.parametrize("kind,needle", [
    ("hang", "no answer within the case time limit"),
    ("exit", "the implementation's process exited with status 0 while running this case"),
    ("crash", "the implementation's process was killed by signal 9 (SIGKILL) while running this case"),
])
def test_misbehaving_case_fails_and_the_run_goes_on(tmp_path, kind, needle):
    """[CF-30], [CF-16], [CF-14] A case that hangs (past --case-timeout), calls os._exit(0) or kills its own
    process (SIGKILL) fails with one line naming it; the run goes on in a fresh child, every other endpoint case
    passes, and the run ends with a summary and exit status 1 (never 0, never a traceback)."""
    rep = tmp_path / "r.json"
    r = _cli("--impl", str(_adapter(tmp_path, kind)), "--only", "endpoint", "--case-timeout", "1",
             "--report", str(rep))
    assert r.returncode == 1, r.stdout + r.stderr
    assert "Traceback" not in r.stdout + r.stderr
    assert f"FAIL {BAD_CASE}: {needle}" in r.stdout, r.stdout
    data = json.loads(rep.read_text())
    failed = [c["id"] for c in data["cases"] if c["status"] == "fail"]
    assert failed == [BAD_CASE]
    assert data["counts"]["pass"] == len(data["cases"]) - 1 > 300 and data["isolation"] == "child process"
    assert r.stdout.splitlines()[-1].startswith(f"FAIL: {len(data['cases'])} cases: {len(data['cases']) - 1} passed, "
                                                "1 failed")


def test_a_function_that_kills_every_child_stops_being_run(tmp_path):
    """[CF-30] After MAX_LOST_IN_A_ROW cases of one function in a row lose their child, the function's
    remaining cases fail as not run (no child per case for ever); other functions still run and pass."""
    f = tmp_path / "always_exits.py"
    f.write_text("import os\nfrom softrtc.conformance.adapters.reference import ReferenceAdapter\n"
                 "name = 'exits'\nhard_weights = ReferenceAdapter().hard_weights\n\n"
                 "def endpoint(rule, d):\n    os._exit(3)\n")
    res = runner.run(str(f), only={"endpoint", "hard_weights"})
    ep = [c for c in res.cases if c.function == "endpoint"]
    assert all(c.status == "fail" for c in ep)
    lost = [c for c in ep if "exited with status 3" in c.message]
    assert len(lost) == runner.MAX_LOST_IN_A_ROW
    assert all(c.message.startswith("not run: the implementation's process was lost on 3 cases of endpoint")
               for c in ep if c not in lost)
    assert all(c.status == "pass" for c in res.cases if c.function == "hard_weights")


TAMPER = """import numpy as np
import softrtc.conformance.runner as r
import softrtc.conformance.results as res
r.compare = lambda *a, **k: 0.0
r.check_outputs = lambda *a, **k: (0.0, "")
res.RunResult.ok = property(lambda self: True)
name = "tamperer"

def hard_weights(H, d):
    return np.full(H, 0.5)
"""


def test_tampering_with_the_runner_has_no_effect_in_a_child(tmp_path):
    """[CF-29], [CF-16] An adapter that replaces the runner's comparison functions and its verdict fools a
    run in the same process (which is why that mode is for debugging only), but in the default child mode
    it changes only its own copy: every non-reject case of its wrong hard_weights fails, exit 1."""
    f = tmp_path / "tamper.py"
    f.write_text(TAMPER)
    r = _cli("--impl", str(f), "--only", "hard_weights")
    assert r.returncode == 1, r.stdout + r.stderr
    assert "FAIL W.hard_weights.H4.d0: weights[0]: got 0.5, expected 0.0" in r.stdout
    r = _cli("--impl", str(f), "--only", "hard_weights", "--in-process")
    assert r.returncode == 0, r.stdout + r.stderr  # fooled: the adapter rewrote this process's verdict


def test_a_child_that_never_answers_is_status_2(tmp_path):
    """[CF-30], [CF-16] A command that never writes its hello line, or exits before it, ends the run with
    exit 2 and one error line naming the command; nothing is reported as passed."""
    silent = f"{sys.executable} -c \"import sys; sys.stdin.read()\""
    r = _cli("--impl-cmd", silent, "--start-timeout", "1")
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and r.stdout == "" and len(lines) == 1, r.stdout + r.stderr
    assert "wrote no hello line within 1 s" in lines[0]
    r = _cli("--impl-cmd", f"{sys.executable} -c \"import sys; print('boom', file=sys.stderr)\"")
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "exited with status 0 (last stderr line: boom)" in lines[0]
    with pytest.raises(ImplementationError, match="no such file|cannot start"):
        runner.run(impl_cmd=str(tmp_path / "no-such-program"))


def test_adapter_load_errors_in_the_child_are_status_2(tmp_path):
    """[CF-18], [CF-16], [CF-29] An adapter that fails to import in the child gives the same one-line error
    and exit 2 as in process (the child reports it in its hello line)."""
    bad = tmp_path / "bad_import.py"
    bad.write_text("import softrtc_not_a_module\n")
    with pytest.raises(AdapterError, match="cannot import adapter module") as info:
        runner.run(str(bad), only={"endpoint"})
    assert not isinstance(info.value, ImplementationError)


FAKE = r"""
import json, sys
mode = sys.argv[1]
print(json.dumps({"protocol": "softrtc-conformance", "version": 1, "name": "fake",
                  "functions": ["standard_error"]}), flush=True)
for line in sys.stdin:
    req = json.loads(line)
    if mode == "wrong-id":
        req["id"] += 1000
    if mode == "garbage":
        print("hello there", flush=True)
        continue
    if mode == "nan":
        print(json.dumps({"id": req["id"], "result": {"value": "NaN"}}), flush=True)
        continue
    if mode == "unsupported":
        print(json.dumps({"id": req["id"], "error": {"kind": "unsupported", "type": "NotImplementedError",
                                                     "message": "not here"}}), flush=True)
        continue
    v = req["args"]["values"]
    if len(v) < 2:
        print(json.dumps({"id": req["id"], "error": {"kind": "invalid_input", "type": "ValueError",
                                                     "message": "n < 2"}}), flush=True)
        continue
    m = sum(v) / len(v)
    se = (sum((x - m) ** 2 for x in v) / (len(v) - 1) / len(v)) ** 0.5
    print(json.dumps({"id": req["id"], "result": {"value": se}}), flush=True)
"""


@pytest.mark.parametrize("mode,status,needle", [
    ("ok", "pass", ""),
    ("wrong-id", "fail", "protocol error: reply id"),
    ("garbage", "fail", "protocol error: the child wrote b'hello there"),
    ("nan", "fail", "non-finite value"),
    ("unsupported", "unsupported", "unsupported case: standard_error raised NotImplementedError: not here"),
])
def test_protocol_from_a_program_of_its_own(tmp_path, mode, status, needle):
    """[CF-29], [CF-31], [CF-26] A program speaking the protocol (here a few lines of plain Python that
    import nothing of softrtc) is run with impl_cmd: correct replies pass, a reply with the wrong id or a
    line that is no reply fails the case as a protocol error, the string "NaN" is a non-finite value, and an
    "unsupported" error makes the case unsupported."""
    f = tmp_path / "fake.py"
    f.write_text(FAKE)
    res = runner.run(impl_cmd=f"{sys.executable} {f} {mode}", only={"standard_error"}, case_timeout=20)
    assert res.adapter_name == "fake" and res.isolation == "child process"
    valid = [c for c in res.cases if ".reject." not in c.id]
    if mode in ("wrong-id", "garbage"):  # each loses its child; after three in a row the rest is not run
        lost = [c for c in res.cases if needle in c.message]
        assert len(lost) == runner.MAX_LOST_IN_A_ROW and all(c.status == "fail" for c in res.cases)
        assert all(c.message.startswith("not run:") for c in res.cases if c not in lost)
        return
    assert valid and all(c.status == status and needle in c.message for c in valid), valid[0].message
    if mode == "ok":
        assert res.ok and res.counts["pass"] == len(res.cases)


def test_run_arguments_are_checked():
    """[CF-29], [N-7] run() takes exactly one of impl and impl_cmd, a positive case_timeout, and runs an
    adapter object only in process."""
    with pytest.raises(ValueError, match="exactly one"):
        runner.run()
    with pytest.raises(ValueError, match="case_timeout"):
        runner.run("reference", case_timeout=0)
    with pytest.raises(ValueError, match="adapter object"):
        runner.run(object(), in_process=False)
    r = _cli("--impl-cmd", "x", "--in-process")
    assert r.returncode == 2 and "--in-process" in r.stderr


FLIPPED = """import numpy as np
from softrtc.conformance.adapters.reference import ReferenceAdapter
name, time_convention = "flipped-reference", "noise_at_1"
_ref = ReferenceAdapter()

def token_times(w, t):
    return 1.0 - _ref.token_times(w, 1.0 - t)

def corrupt(actions, noise, w, tau):
    x, times = _ref.corrupt(actions, noise, w, 1.0 - tau)
    return x, 1.0 - times

def velocity(field, obs, x, t):
    return -_ref.velocity(field, obs, x, 1.0 - np.asarray(t))

def loss(pred, actions, noise, w):
    return _ref.loss(-np.asarray(pred), actions, noise, w)
"""


def test_flipped_convention_through_the_protocol(tmp_path):
    """[CF-10], [CF-29], [V-1] A noise_at_1 implementation in a child gets t' = 1 - t and u = -v in its
    requests and has its times and velocities mapped back: a correct flipped adapter passes, the same
    adapter declaring data_at_1 fails every time-carrying case."""
    f = tmp_path / "flipped.py"
    f.write_text(FLIPPED)
    only = {"token_times", "corrupt", "velocity", "loss"}
    res = runner.run(str(f), only=only)
    assert res.ok and res.counts["pass"] == len(res.cases) and res.time_convention == "noise_at_1"
    f.write_text(FLIPPED.replace('"noise_at_1"', '"data_at_1"'))
    res = runner.run(str(f), only=only)
    failed = {c.function for c in res.cases if c.status == "fail"}
    assert failed == only
