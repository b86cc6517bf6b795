"""Where Soft RTC's executed window tokens go: pull toward the prior, per delay and solver step ([AX-5]).

For every request ``c >= 1`` of a closed-loop episode the soft sampler's chunk
``a`` is compared, token by token, with the fresh plan ``f``: the chunk the
same checkpoint makes from the same observation and the same noise with the
naive sampler (the prior ignored). ``y`` is the prior ([X-3]). For an executed
window token (``d <= j < s`` and ``0 < w_j < 1``), in normalized action units:

    pull      = <a - f, y - f> / |y - f|^2     how far a moved from f toward y (0: not at all, 1: onto y)
    closer    = |a - y| < |f - y|              whether a ended nearer the prior than the fresh plan
    unrelated = |(a - f) - pull (y - f)|       the movement orthogonal to the direction of the prior

The weights ask for a pull of ``w_j``: the training corruption puts a window
token at ``w_j A + (1 - w_j) eps`` at flow time ``w_j``, and a time-consistent
step keeps the prior's share ``w_j`` up to the end ([S-10], [S-13]).

>>> import numpy as np
>>> token_pull(np.array([1.0, 1.0]), np.array([0.0, 0.0]), np.array([2.0, 0.0]))   # pull 0.5, closer, 1 aside
(0.5, True, 1.0)
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from softrtc._files import write_json
from softrtc.reference import weights as rw
from softrtc.reference._validate import check_int

from .tasks import get_task

__all__ = ["token_pull", "measure_pull", "STEPS"]

STEPS = ("algorithm1", "consistent")


def token_pull(a, f, y) -> tuple:
    """``(pull, closer, unrelated)`` of one token: chunk ``a``, fresh plan ``f``, prior ``y`` (vectors)."""
    a, f, y = (np.asarray(v, np.float64) for v in (a, f, y))
    if not (a.shape == f.shape == y.shape and a.ndim == 1 and np.all(np.isfinite(np.stack([a, f, y])))):
        raise ValueError("a, f and y must be finite vectors of one shape")
    g = y - f
    gg = float(g @ g)
    if gg == 0.0:
        raise ValueError("the prior equals the fresh plan: the pull is undefined")
    p = float((a - f) @ g) / gg
    closer = bool(np.linalg.norm(a - y) < np.linalg.norm(f - y))
    return p, closer, float(np.linalg.norm((a - f) - p * g))


class _Probe:
    """A policy for :func:`run_simulated_episode` that also records, per request, the fresh plan."""

    def __init__(self, policy, fresh):
        self.policy, self.fresh = policy, fresh
        self.H, self.s, self.method = policy.H, policy.s, policy.method
        self.records = []

    def generate(self, obs, prior, d, key):
        a = self.policy.generate(obs, prior, d, key)
        if prior is not None:
            f = self.fresh.generate(obs, prior, d, key)
            self.records.append((np.asarray(prior, np.float64), int(d), np.asarray(a, np.float64), np.asarray(f)))
        return a


def measure_pull(checkpoint, task_name: str = "drift", delays=(1, 2, 3, 4, 5), episodes: int = 20,
                 seed0: int = 10_000, key_seed: int = 0, max_steps: int = 1000, window=None) -> dict:
    """Pull statistics of a ``train_soft`` sampler on ``checkpoint`` under each solver step, per delay ([AX-5]).

    Episodes pair across steps (env seeds ``seed0 + i``, keys
    ``fold_in(key(key_seed), i)``, as the experiment's cells). Returns
    ``{"steps": {step: {d: {"tokens", "intended", "pull_median", "pull_q25",
    "pull_q75", "closer_share", "unrelated_median", "moved_median",
    "success"}}}, ...}``; ``intended`` is the mean weight of the tokens.
    """
    import jax

    from .checkpoints import load_arm_checkpoint
    from .executor import run_simulated_episode
    from .experiment import _arm_policy

    task = get_task(task_name)
    path = Path(checkpoint)
    if not path.is_file():
        raise ValueError(f"checkpoint must be an arm checkpoint file, got {str(checkpoint)!r}")
    delays = [check_int("delays[i]", d, 1, task.max_delay) for d in delays]
    if not delays or len(set(delays)) != len(delays):
        raise ValueError(f"delays must be distinct integers in [1, {task.max_delay}], got {list(delays)}")
    episodes = check_int("episodes", episodes, 1, 10_000)
    max_steps = check_int("max_steps", max_steps, 1, task.env_config.max_steps)
    window = rw.SoftWindow() if window is None else window
    ck = load_arm_checkpoint(path)
    std = np.asarray(ck.normalizer.act_std, np.float64)
    H, s = 10, task.execute_horizon
    fresh = _arm_policy(ck.model, ck.normalizer, task, "naive", None)
    out = {"checkpoint_sha256_16": hashlib.sha256(path.read_bytes()).hexdigest()[:16], "task": task.name,
           "window": window.to_dict(), "episodes": episodes, "seed0": seed0, "key_seed": key_seed,
           "max_steps": max_steps, "steps": {}}
    for step in STEPS:
        pol = _arm_policy(ck.model, ck.normalizer, task, "train_soft", window, step)
        per = {}
        for d in delays:
            w = rw.soft_weights(H, d, window, s)
            toks = [j for j in range(d, s) if 0 < w[j] < 1]
            pulls, closer, unrel, moved, wins = [], [], [], [], 0
            for i in range(episodes):
                probe = _Probe(pol, fresh)
                rec = run_simulated_episode(probe, seed0 + i, d, jax.random.fold_in(jax.random.key(key_seed), i),
                                            max_steps=max_steps, env_config=task.env_config)
                wins += int(rec.success)
                for (y, dd, a, f) in probe.records:
                    for j in toks:
                        if np.array_equal(y[j], f[j]):
                            continue
                        p, c, u = token_pull(a[j] / std, f[j] / std, y[j] / std)
                        pulls.append(p)
                        closer.append(c)
                        unrel.append(u)
                        moved.append(float(np.linalg.norm((a[j] - f[j]) / std)))
            per[str(d)] = {
                "tokens": len(pulls), "intended": float(np.mean([w[j] for j in toks])) if toks else None,
                "window_tokens": toks, "success": wins / episodes,
                **({"pull_median": float(np.median(pulls)), "pull_q25": float(np.percentile(pulls, 25)),
                    "pull_q75": float(np.percentile(pulls, 75)), "closer_share": float(np.mean(closer)),
                    "unrelated_median": float(np.median(unrel)), "moved_median": float(np.median(moved))}
                   if pulls else {})}
        out["steps"][step] = per
    return out


def write_pull(result: dict, path) -> None:
    """The measurement as JSON, written atomically."""
    write_json(Path(path), result)
