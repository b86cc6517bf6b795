"""The PyTorch arm policy: recipe, chunk generator, paired evaluation ([PT-9])."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("pymunk")
jax = pytest.importorskip("jax")

from softrtc.torch import arm  # noqa: E402
from softrtc.torch.policy import FlowPolicy  # noqa: E402

pytestmark = pytest.mark.slow  # pymunk episodes and policy training


def _normalizer():
    A = arm._arm()
    F = A["FEATURE_DIM"]
    return A["Normalizer"](np.zeros(F), np.ones(F), np.array([0.0, -1.0, 0.0, 0.5]), np.full(4, 0.3))


def _policy(method, seed=0):
    model = FlowPolicy(arm._arm()["FEATURE_DIM"], 4, arm.ARM_POLICY, generator=torch.Generator().manual_seed(seed))
    return arm.ArmTorchPolicy(model, _normalizer(), method)


def test_learning_rate_schedule_of_the_recipe():
    """[PT-9], [T-6] Linear warm-up over min(200, steps // 10) steps from 0, then cosine decay reaching 5 %
    at the last step: hand-computed values for 4000 steps (warm-up 200) and 800 steps (warm-up 80)."""
    assert arm.lr_factor(0, 4000, 0.05) == 0.0
    assert arm.lr_factor(100, 4000, 0.05) == 0.5
    assert arm.lr_factor(200, 4000, 0.05) == 1.0
    assert arm.lr_factor(2100, 4000, 0.05) == pytest.approx(0.05 + 0.95 * 0.5)
    assert arm.lr_factor(4000, 4000, 0.05) == pytest.approx(0.05)
    assert arm.lr_factor(40, 800, 0.05) == 0.5 and arm.lr_factor(80, 800, 0.05) == 1.0
    with pytest.raises(ValueError, match="steps"):
        arm.TrainRecipe(steps=0)


def test_chunk_generator_keys_bounds_and_zero_delay():
    """[PT-9], [A-19], [X-2], [S-7] generate() is a function of (obs, prior, d, key): the same key gives the same
    chunk and another key another one; chunks lie inside the action ranges; the first chunk needs d = 0; with
    d = 0 the training-time samplers give the naive chunk for the same key (zero weights)."""
    obs = np.zeros(34)
    obs[10:30] = 0.3
    base, hard, soft = (_policy(m) for m in ("naive", "train_hard", "train_soft"))
    key = jax.random.key(3)
    c1 = base.generate(obs, None, 0, key)
    assert np.array_equal(c1, base.generate(obs, None, 0, key))
    assert not np.array_equal(c1, base.generate(obs, None, 0, jax.random.key(4)))
    assert c1.shape == (10, 4) and np.all(c1 >= base.low) and np.all(c1 <= base.high)
    with pytest.raises(ValueError, match="d must be an integer in"):
        base.generate(obs, None, 1, key)
    prior = np.clip(c1 + 0.05, base.low, base.high)
    np.testing.assert_allclose(hard.generate(obs, prior, 0, key), base.generate(obs, prior, 0, key), atol=1e-6)
    np.testing.assert_allclose(soft.generate(obs, prior, 0, key), base.generate(obs, prior, 0, key), atol=1e-6)
    assert not np.allclose(soft.generate(obs, prior, 3, key), base.generate(obs, prior, 3, key), atol=1e-6)
    with pytest.raises(ValueError, match="obs"):
        base.generate(np.zeros(5), None, 0, key)


def test_training_is_a_function_of_its_seed():
    """[PT-9], [PT-4], [N-9] train_policy draws every shuffle, delay, flow time and noise from its seed: the same
    seed gives the same losses and parameters, another seed other ones; every objective lowers nothing it
    should not (the losses are finite)."""
    g = torch.Generator().manual_seed(0)
    F = arm._arm()["FEATURE_DIM"]
    obs, chunks = torch.randn(300, F, generator=g), torch.randn(300, 10, 4, generator=g)
    recipe = arm.TrainRecipe(batch_size=64)
    runs = []
    for seed in (5, 5, 6):
        m = FlowPolicy(F, 4, arm.ARM_POLICY, generator=torch.Generator().manual_seed(1))
        runs.append((arm.train_policy(m, obs, chunks, "train_soft", 6, seed, 1e-3, recipe, 5), m))
    assert np.array_equal(runs[0][0], runs[1][0]) and not np.array_equal(runs[0][0], runs[2][0])
    assert all(torch.equal(p, q) for p, q in zip(runs[0][1].parameters(), runs[1][1].parameters()))
    for method in ("naive", "train_hard"):
        m = FlowPolicy(F, 4, arm.ARM_POLICY, generator=torch.Generator().manual_seed(1))
        assert np.all(np.isfinite(arm.train_policy(m, obs, chunks, method, 3, 0, 1e-3, recipe, 5)))


def test_evaluation_is_paired():
    """[PT-9], [A-22] evaluate() runs every policy on the same env seeds with the same key per seed: two names
    for one policy give identical episodes; records carry the delay and seed; summarize() gives a mean inside
    its bootstrap interval for every metric with finite values."""
    pol = _policy("train_soft")
    rows = arm.evaluate({"a": pol, "b": pol}, (2,), 2, seed0=10_000, max_steps=30, progress=lambda m: None)
    assert [r["env_seed"] for r in rows] == [10_000, 10_000, 10_001, 10_001]
    for r, s in zip(rows[0::2], rows[1::2]):
        assert {k: v for k, v in r.items() if k != "policy"} == {k: v for k, v in s.items() if k != "policy"}
    for e in arm.summarize(rows):
        assert e["episodes"] == 2 and e["delay"] == 2
        for k in arm.METRICS:
            mean, lo, hi = e[k]
            assert math.isnan(mean) or lo - 1e-12 <= mean <= hi + 1e-12


def test_saved_policies_record_their_network(tmp_path):
    """[PT-9] A saved arm policy records its PolicyConfig: one trained with ARM_POLICY (chapter P's network
    with the JAX arm sizes) loads back with equal parameters; one of another network (time at the token
    input) is refused with a ValueError that says to retrain, so an old work folder is not evaluated as
    the chapter-P policy."""
    import dataclasses

    F = arm._arm()["FEATURE_DIM"]
    model = FlowPolicy(F, 4, arm.ARM_POLICY, generator=torch.Generator().manual_seed(2))
    arm._save(tmp_path / "base.pt", model, {"obs_dim": F})
    back, meta = arm._load(tmp_path / "base.pt")
    assert meta["policy"]["architecture"] == "adaln"
    assert all(torch.equal(p, q) for p, q in zip(model.parameters(), back.parameters()))
    other = FlowPolicy(F, 4, dataclasses.replace(arm.ARM_POLICY, architecture="token_input", time_dim=64),
                       generator=torch.Generator().manual_seed(2))
    arm._save(tmp_path / "old.pt", other, {"obs_dim": F})
    assert arm._trained_with(tmp_path / "old.pt")["architecture"] == "token_input"
    with pytest.raises(ValueError, match="retrain"):
        arm._load(tmp_path / "old.pt")


@pytest.mark.parametrize("option, message", [
    (["--work="], "argument --work: must be a directory path, got an empty string"),
    (["--max-steps", "1001"], "argument --max-steps: value must be an integer in [1, 1000], got 1001"),
])
def test_arm_torch_options_are_checked_before_training(option, message, tmp_path, capsys, monkeypatch):
    """[PT-9] [N-11] `arm torch --work ''` (the current folder) and a step limit past the scene's 1000 ticks
    end at the door with one line; the library refuses them too, before anything is trained."""
    from softrtc.cli import main

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(arm, "train_arm_policies", lambda *a, **k: pytest.fail("trained before the check"))
    try:
        rc = main(["arm", "torch", "--out", str(tmp_path / "a.json")] + option)
    except SystemExit as exc:
        rc = exc.code
    assert rc == 2 and capsys.readouterr().err.splitlines()[-1] == f"softrtc arm torch: error: {message}"
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match=r"^max_steps must be an integer in \[1, 1000\], got 1001$"):
        arm.Protocol(max_steps=1001)
    with pytest.raises(ValueError, match="^work must be a non-empty"):
        arm.run_experiment(tmp_path / "a.json", "")
