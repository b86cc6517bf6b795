"""Conformance rollouts on a Kinetix level (spec/42-rollouts.md [CR-13]..[CR-15]): the served policy, the world
the runner steps, the closed-loop check, a mutant's diagnosis, the Kinetix rollout vectors and the level option.

The level's env programs compile once per process (and load from the compile cache of [KC-3] in later ones):
the module-scoped fixture builds the default world first and every test after it reuses the compiled programs.
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("kinetix")

from softrtc.cli import main as cli_main  # noqa: E402
from softrtc.conformance import rollout, rollout_vectors  # noqa: E402
from softrtc.conformance.rollout_loop import Settings, request_inputs  # noqa: E402

ALL = ("naive", "train_hard", "train_soft", "inference_hard", "inference_soft")
NODE = shutil.which("node")
JS = rollout_vectors.vectors_dir().parent / "ports" / "js" / "rollout.js"


@pytest.fixture(scope="module")
def kinetix():
    """(field, world) of the default Kinetix rollout: compiled once for the module."""
    return rollout.open_world("kinetix", max_steps=16)


def test_served_policy_and_world_sizes(kinetix):
    """CR-13, CR-14, K-5, KE-1, KE-11, CR-3 The default world is m_h0_unicycle padded to the benchmark's sizes;
    the served field is the shipped base checkpoint of that level (815,110 parameters, no training method),
    named by its file and both digests, with the protocol's H = 8, s = 4, T = 5 and A = 6 on 679 float32
    observation values; `init_seed` serves a fresh policy instead; the VJP agrees with central differences."""
    import flax.nnx as nnx
    import jax

    from softrtc.conformance.rollout_kinetix import checkpoints_dir, load_policy, policy_digest
    from softrtc.jax.checkpoint import load_checkpoint
    from softrtc.jax.policy import FlowPolicy, PolicyConfig
    from softrtc.kinetix import env as kenv

    field, world = kinetix
    assert (field.level, field.H, field.s, field.T, field.action_dim, field.obs_dim) == \
        ("m_h0_unicycle", 8, 4, 5, 6, 679) == ("m_h0_unicycle", 8, 4, 5, kenv.ACTION_DIM, kenv.OBS_DIM)
    path = checkpoints_dir() / "m_h0_unicycle.npz"
    shipped, meta = load_checkpoint(path)
    assert meta["level"] == "m_h0_unicycle" and "method" not in meta and field.about["role"] == "base"
    assert sum(np.size(v) for v in jax.tree_util.tree_leaves(nnx.to_pure_dict(nnx.state(shipped)))) == 815_110
    assert field.describe() == {"level": "m_h0_unicycle", "checkpoint": "kinetix/checkpoints/m_h0_unicycle.npz",
                                "checkpoint_sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
                                "init_seed": None, "policy_sha256": policy_digest(shipped)}
    fresh = FlowPolicy(obs_dim=679, action_dim=6, config=PolicyConfig(), rngs=nnx.Rngs(0))
    _, about = load_policy("m_h0_unicycle", init_seed=0)
    assert about["init_seed"] == 0 and about["checkpoint"] is None
    assert about["policy_sha256"] == policy_digest(fresh) != policy_digest(shipped)
    obs = world.reset(0)
    assert obs.shape == (679,) and np.array_equal(obs.astype(np.float32).astype(np.float64), obs)
    rng = np.random.default_rng(0)
    x, u, ct = (rng.standard_normal((8, 6)) for _ in range(3))
    t = np.linspace(0.1, 0.9, 8)
    eps = 1e-2
    fd = (field(obs, x + eps * u, t) - field(obs, x - eps * u, t)) / (2 * eps)
    assert abs(np.sum(field.vjp(obs, x, t, ct) * u) - np.sum(fd * ct)) < 2e-2 * (1 + abs(np.sum(fd * ct)))
    np.testing.assert_allclose(field.flipped()(obs, x, 1.0 - t), -field(obs, x, t), atol=1e-6)


def test_world_keys_follow_the_kinetix_evaluation(kinetix):
    """CR-13, KE-5, K-8 Episode i of seed S is keyed as `kinetix eval --seed S` keys its episode i: the same
    episode seed replays the same observations for the same actions, another episode's execution noise differs,
    and the episode's outcome is deterministic."""
    _, world = kinetix
    acts = np.tile(np.array([0.0, 0.0, 0.0, 0.0, 0.8, 0.8]), (6, 1))

    def play(seed):
        out = [world.reset(seed)]
        out += [world.step(a) for a in acts if not world.done]
        return np.array(out), dict(world.info), world.t

    a, info_a, t_a = play(3_000_001)
    b, info_b, _ = play(3_000_001)
    c, _, _ = play(3_000_002)
    assert np.array_equal(a, b) and info_a == info_b and t_a == len(a) - 1
    assert not np.array_equal(a[1:], c[1:len(a)])  # [K-8]: the execution noise comes from the episode's key


def test_reference_passes_a_short_closed_loop_check(kinetix):
    """CR-1, CR-2, CR-5, CR-7, CR-12, CR-13 The reference makes every chunk of one short episode (at most 16
    ticks, the scope of the tests) per method: every
    request passes, each episode makes ceil(steps / s) requests, the implementation sees the level's observation
    and chunk sizes, and its paired outcomes against the reference's own episodes (the same keys, noise and
    delays) differ by exactly 0."""
    seen = []

    class Spy:
        name = "spy"

        def rollout_chunk(self, field, **args):
            from softrtc.conformance.rollout_impls import ReferenceRollout

            seen.append((args["obs"].shape, args["noise"].shape, args["s"], args["T"], args["d"], args["arrival"]))
            return ReferenceRollout().rollout_chunk(field, **args)

    from softrtc.conformance import rollout_impls

    rollout_impls.BUILTIN["spy-kinetix"] = Spy
    try:
        out = rollout.run("spy-kinetix", env="kinetix", settings=Settings(ALL, 1, (1, 2, 3, 4, 5), 16),
                          in_process=True)
    finally:
        del rollout_impls.BUILTIN["spy-kinetix"]
    res = out["result"]
    assert res.ok and res.counts["fail"] == 0, rollout.summary_text(out)
    assert out["metrics"] == ("return", "solved", "delta", "jerk")
    for ep in out["episodes"]:
        assert 1 <= ep.steps <= 16 and ep.requests == math.ceil(ep.steps / 4) and ep.error is None
    assert {(o, n, s, T) for o, n, s, T, _, _ in seen} == {((679,), (8, 6), 4, 5)}
    assert max(d for *_, d, _ in seen) == 4  # delays 5 capped at min(s, H - s) = 4 ([CR-5])
    for method, p in out["paired"].items():
        assert all(p[m]["diff"] in (0.0, None) for m in out["metrics"]), (method, p)
    assert out["policy"]["level"] == "m_h0_unicycle" and res.cases[0].id.startswith("CR.kinetix.")


def test_mutant_fails_with_its_diagnosis(kinetix):
    """CR-9, CR-11, X-3, CR-13 The prior-shift mutant fails the chunk of every blended request of a Kinetix
    episode, each diagnosed [X-3]; an executed case that fails is blamed on its chunk (executed as [X-4] says
    from the wrong chunk); its first (naive) request passes."""
    out = rollout.run("mutant-prior-shift", env="kinetix", settings=Settings(("train_hard",), 1, (1, 2, 3), 16),
                      in_process=True)
    res = out["result"]
    failed = [c for c in res.cases if c.status == "fail"]
    chunks = [c for c in failed if c.id.endswith(".chunk")]
    assert not res.ok and chunks and all(c.requirements == ["CR-2", "X-3"] and "diagnosis [X-3]" in c.message
                                         for c in chunks)
    assert {c.id for c in chunks} == {f"CR.kinetix.train_hard.ep000.r{c:03d}.chunk"
                                      for c in range(1, out["episodes"][0].requests)}
    for c in failed:
        if c.id.endswith(".executed"):
            assert c.id.replace(".executed", ".chunk") in {k.id for k in chunks}
            assert c.requirements == ["CR-2", "X-3"] and "the chunk is what differs" in c.message


def test_kinetix_vectors_content(kinetix):
    """CR-15, CR-10, CF-25 The shipped Kinetix vectors name their env, level and policy (the shipped checkpoint,
    its file's and the served policy's SHA-256), hold the first 16 requests of 2 episodes of each method (fewer where the level
    ends first), every array of the level's sizes and the noise, delays and arrivals of [CR-5] for seed 7, in
    under 1 MB; the index lists both files."""
    field, _ = kinetix
    header, cases = rollout_vectors.load(env="kinetix")
    assert header["checkpoint_sha256"] == field.describe()["checkpoint_sha256"]
    assert {k: header[k] for k in ("env", "level", "init_seed", "checkpoint", "policy_sha256", "H", "s", "T",
                                   "obs_dim", "action_dim", "seed")} == \
        {"env": "kinetix", "level": "m_h0_unicycle", "init_seed": None,
         "checkpoint": "kinetix/checkpoints/m_h0_unicycle.npz", "policy_sha256": field.describe()["policy_sha256"], "H": 8, "s": 4, "T": 5, "obs_dim": 679,
         "action_dim": 6, "seed": 7}
    assert rollout_vectors.listed_envs() == ("arm", "kinetix")
    folder = rollout_vectors.rollouts_dir()
    assert (folder / "rollouts_kinetix.json").stat().st_size < 1_000_000
    per = {}
    for case in cases:
        _, env, method, ep, r = case["id"].split(".")
        assert env == "kinetix" and case["requirements"][:2] == ["CR-10", "CR-15"]
        per.setdefault((method, ep), []).append(int(r[1:]))
        a = case["args"]
        assert len(a["obs"]) == 679 and np.shape(a["noise"]) == (8, 6) and np.shape(case["expected"]["executed"]) \
            == (4, 6)
        noise, d, arrival = request_inputs(Settings(ALL, 2, (0, 1, 2, 3, 4, 5), 64, seed=7), int(ep[2:]),
                                           int(r[1:]), 8, 6, 4)
        assert np.array_equal(np.asarray(a["noise"]), noise) and (a["d"], a["arrival"]) == (d, arrival)
    assert set(per) == {(m, f"ep{i:03d}") for m in ALL for i in range(2)}
    assert all(v == list(range(len(v))) and 1 <= len(v) <= 16 for v in per.values())
    assert sum(len(v) for v in per.values()) == len(cases) == 108  # every episode ends with the level ([CR-15])
    readme = " ".join((Path(__file__).resolve().parents[2] / "README.md").read_text().split())
    assert f"{len(cases)} recorded requests" in readme


def test_vectors_replay_for_the_reference_and_the_js_port(kinetix, tmp_path):
    """CR-15, CR-10, CR-4 The reference, in process, and the JavaScript port, asking the runner for the Kinetix
    field over the protocol, answer every recorded Kinetix request within the tolerance; a vector file whose
    header names another policy is refused before any request runs."""
    n = len(rollout_vectors.load(env="kinetix")[1])
    res = rollout_vectors.replay("reference", env="kinetix", in_process=True)["result"]
    assert res.ok and res.counts["pass"] == n and all(c.file == "rollouts_kinetix.json" for c in res.cases)
    if NODE is not None:
        js = rollout_vectors.replay(impl_cmd=f"{NODE} {JS}", env="kinetix")["result"]
        assert js.ok and js.counts["pass"] == n and max(c.worst for c in js.cases) < 1e-6
    bad = tmp_path / "rollouts"
    bad.mkdir()
    text = (rollout_vectors.rollouts_dir() / "rollouts_kinetix.json").read_text()
    # the header names a fresh policy (init seed 1) instead of the shipped checkpoint
    text = text.replace('"checkpoint":"kinetix/checkpoints/m_h0_unicycle.npz"', '"checkpoint":null', 1)
    text = text.replace('"init_seed":null', '"init_seed":1', 1)
    (bad / "rollouts_kinetix.json").write_text(text)
    index = {"format_version": "1.0", "files": {"rollouts_kinetix.json": {
        "cases": n, "env": "kinetix", "sha256": hashlib.sha256(text.encode()).hexdigest()}}}
    (bad / "index.json").write_text(json.dumps(index))
    with pytest.raises(ValueError, match="SHA-256"):
        rollout_vectors.replay("reference", vectors_dir=bad, env=None, in_process=True)


def test_checkpoint_is_served_and_checked(kinetix, tmp_path):
    """CR-14, KE-11 A `<level>.npz` checkpoint is served (the report names it and its digests); a checkpoint of
    another level, or a file not named `<level>.npz`, is refused naming the argument."""
    import flax.nnx as nnx

    from softrtc.conformance.rollout_kinetix import KinetixField, policy_digest
    from softrtc.jax.checkpoint import save_checkpoint
    from softrtc.jax.policy import FlowPolicy, PolicyConfig

    pol = FlowPolicy(obs_dim=679, action_dim=6, config=PolicyConfig(), rngs=nnx.Rngs(5))
    path = tmp_path / "s_h4_thrust_aim.npz"
    save_checkpoint(path, pol, {"level": "s_h4_thrust_aim"})
    field = KinetixField("s_h4_thrust_aim", checkpoint=path)
    d = field.describe()
    assert d["policy_sha256"] == policy_digest(pol) != kinetix[0].describe()["policy_sha256"]
    assert d["checkpoint_sha256"] == hashlib.sha256(path.read_bytes()).hexdigest() and d["init_seed"] is None
    (tmp_path / "other").mkdir()
    wrong = tmp_path / "other" / "m_h5_angry_birds.npz"
    save_checkpoint(wrong, pol, {"level": "s_h4_thrust_aim"})
    with pytest.raises(ValueError, match="level"):
        KinetixField("m_h5_angry_birds", checkpoint=wrong)
    with pytest.raises(ValueError, match="checkpoint must name"):
        KinetixField("s_h4_thrust_aim", checkpoint=wrong)


def test_bad_level_is_one_clear_error(capsys):
    """CR-13, K-20, N-11 An unknown --level is one error line naming the option, the valid forms and
    `softrtc kinetix levels`, exit status 2, before anything is compiled; --level with the arm is refused."""
    code = cli_main(["conformance", "rollout", "--impl", "reference", "--in-process", "--env", "kinetix",
                     "--level", "no_such_level"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert err[0].startswith("softrtc conformance rollout: error: --level must be one of the benchmark's levels")
    assert "softrtc kinetix levels" in err[0] and "'no_such_level'" in err[0]
    with pytest.raises(ValueError, match="level must be one of"):
        rollout.run("reference", env="kinetix", level="m_h5", in_process=True)
    code = cli_main(["conformance", "rollout", "--impl", "reference", "--in-process", "--level", "m_h5_angry_birds"])
    assert code == 2 and "level is for env 'kinetix' only" in capsys.readouterr().err
