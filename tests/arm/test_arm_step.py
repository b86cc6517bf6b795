"""Arm rows and policies with the time-consistent solver step ([S-10], [S-11], [S-14], [AX-2])."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("jax")
import jax  # noqa: E402

from softrtc.arm import experiment as E  # noqa: E402
from softrtc.arm.env import OBS_DIM  # noqa: E402
from softrtc.arm.policies import ArmPolicy, untrained_policy  # noqa: E402
from softrtc.arm.tasks import get_task  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]


def test_row_step_keys():
    """S-10, S-11: a row's step joins its eval key only where it changes a chunk (a training-time sampler with
    window tokens); with the default step every key is the committed manifest's."""
    task = get_task("drift")
    rows = {r.name: r for r in E.rows_for(task)}
    committed = json.loads((ROOT / "results/arm/drift/manifest.json").read_text())["rows"]
    for name, r in rows.items():
        assert committed[name]["eval_key"] == E.eval_key(r, task)
    con = lambda n: dataclasses.replace(rows[n], step="consistent")  # noqa: E731
    for name in ("soft2_clip", "hard_soft_sampler", "soft2_clip_prior_noise"):
        assert E.eval_key(con(name), task) != E.eval_key(rows[name], task)
    for name in ("naive", "train_hard", "soft2_clip_hard_sampler"):  # weights in {0, 1}: bitwise the same chunks
        assert E.eval_key(con(name), task) == E.eval_key(rows[name], task)
    with pytest.raises(ValueError, match="step must be 'algorithm1' for method 'inference_soft'"):
        con("inference_soft")
    with pytest.raises(ValueError, match="step must be one of"):
        dataclasses.replace(rows["soft2_clip"], step="exact")


def test_arm_policy_step():
    """S-10, S-11, S-14: an arm policy runs its step: train_soft chunks change, train_hard ones are bitwise
    Algorithm 1's; the guided methods reject the consistent step."""
    base = untrained_policy(0, "train_soft")
    obs = np.linspace(-0.5, 0.5, OBS_DIM)
    out = {}
    for method in ("train_soft", "train_hard"):
        for step in ("algorithm1", "consistent"):
            p = ArmPolicy(base.model, base.normalizer, base.config, method, step=step)
            assert p.step == step and p.chunks.step == step
            first = p.generate(obs, None, 0, jax.random.key(0))
            out[method, step] = p.generate(obs, first + 0.05, 2, jax.random.key(1))
    assert np.abs(out["train_soft", "algorithm1"] - out["train_soft", "consistent"]).max() > 1e-6
    assert np.array_equal(out["train_hard", "algorithm1"], out["train_hard", "consistent"])
    with pytest.raises(ValueError, match="step must be 'algorithm1'"):
        ArmPolicy(base.model, base.normalizer, base.config, "inference_hard", step="consistent")
