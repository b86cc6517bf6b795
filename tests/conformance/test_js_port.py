"""The JavaScript port (conformance/ports/js/) through the child-process protocol ([CF-29], [CF-31])."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from softrtc.conformance import runner

ROOT = Path(__file__).resolve().parents[2]
PORT = ROOT / "conformance" / "ports" / "js"
NODE = shutil.which("node")
needs_node = pytest.mark.skipif(NODE is None, reason="node (Node.js 20+) not installed")

PORTED = {"endpoint", "prefix_weights", "weights", "hard_weights", "guidance_weights", "guidance_weight",
          "method_weights", "token_times", "velocity", "naive_sample", "rtc_sample", "rtc_sample_step",
          "shift_prior", "execute_chunks"}


@pytest.fixture(scope="module")
def vector_files():
    return runner.load_vectors()


@needs_node
def test_js_port_passes_every_case_it_supports(vector_files):
    """[CF-31], [CF-29], [CF-23], [E-2], [W-1], [S-3], [X-4] The port passes every case of the functions it
    has (traces included), with the others (the rollout vectors' included, [CR-10]) unsupported and none
    failed; the integer arguments written as reals (E.endpoint.reject.float-d, X.execute_chunks.reject.float-d)
    are rejected by its own parser. The README's conformance table shows these counts."""
    res = runner.run(impl_cmd=f"{NODE} {PORT / 'protocol.js'}", files=vector_files, rollouts=True)
    assert res.ok and res.counts["fail"] == 0, runner.format_summary(res)
    # protocol.js lists no rollout_chunk (rollout.js serves it): the rollout vectors are unsupported ([CR-10])
    assert res.rollouts["status"] == "unsupported" and any(c.function == "rollout_chunk" for c in res.cases)
    assert res.adapter_name == "softrtc-js"
    passed = {c.function for c in res.cases if c.status == "pass"}
    assert passed == PORTED
    assert all(c.status == "unsupported" for c in res.cases if c.function not in PORTED)
    by_id = {c.id: c for c in res.cases}
    for cid in ("E.endpoint.reject.float-d", "X.execute_chunks.reject.float-d", "E.endpoint.exact-ceil.lam1.6.d5"):
        assert by_id[cid].status == "pass"
    assert not any(c.message == runner.TRACE_NOT_PROVIDED for c in res.cases)  # traces are checked
    # The README's table states these counts; it must follow the vectors.
    readme = (ROOT / "README.md").read_text()
    n = res.counts
    assert f"| implementation | result ({len(res.cases)} cases) |" in readme
    assert f"| `conformance/ports/js` (JavaScript, `--impl-cmd`) | {n['pass']} pass, {n['unsupported']} unsupported" \
        in readme


@needs_node
@pytest.mark.parametrize("old,new,function", [
    ("(j - d + 1) / (e - d + 1)", "(j - d) / (e - d + 1)", "prefix_weights"),   # rtc positions shifted
    ("Math.min(d + rule.length, rule.h_max)", "Math.min(d + rule.length, 4096)", "endpoint"),  # cap ignored
    ("checkInt('delays[0]', delays[0], 0, 0);", "", "execute_chunks"),          # first delay not checked
    ("throw new rtc.ValueError(`${key} must be an integer", "if (0) throw new rtc.ValueError(`${key}",
     "endpoint"),                                                               # 2.0 read as the integer 2
    ("xi + (c[j] * v[j][i]) / T", "xi + v[j][i] / T", "rtc_sample_step"),       # [S-10] full step on window tokens
    ("k === 0 || again[j]", "true", "rtc_sample_step"),                         # [S-10] window re-blended
])
def test_a_broken_copy_of_the_port_fails(tmp_path, old, new, function, vector_files):
    """[CF-31], [CF-16] The runner judges the port, not the other way round: a copy with one porting
    mistake fails cases of the function it touches."""
    for f in PORT.glob("*.js"):
        shutil.copy(f, tmp_path / f.name)
    target = tmp_path / ("protocol.js" if "rtc.ValueError" in old else "softrtc.js")
    text = target.read_text()
    assert old in text
    target.write_text(text.replace(old, new))
    res = runner.run(impl_cmd=f"{NODE} {tmp_path / 'protocol.js'}", files=vector_files, only={function})
    assert not res.ok and res.counts["fail"] > 0
