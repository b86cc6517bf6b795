"""What the JAX benchmarks vary, and their policy and inputs (spec chapter B, ``spec/32-runtime-bench.md``, [B-1]..[B-9])."""

from __future__ import annotations

import dataclasses

import flax.nnx as nnx
import jax
import jax.numpy as jnp
import numpy as np

from softrtc.reference._validate import check_choice, check_int

from .policy import FlowPolicy, PolicyConfig

__all__ = ["ARCHS", "CHUNK_ROWS", "ROW_STEPS", "TRAIN_ROWS", "REFERENCE_ROWS", "PUBLIC_ROWS", "TRAIN_METHODS",
           "BenchConfig", "make_policy"]

# [B-2] Benchmark architecture (spec chapter P defaults) and a tiny one for smoke runs and tests.
ARCHS = {
    "benchmark": dict(obs_dim=679, action_dim=6, config=PolicyConfig()),
    "tiny": dict(obs_dim=7, action_dim=3,
                 config=PolicyConfig(channel_dim=16, channel_hidden_dim=24, token_hidden_dim=6, num_layers=1,
                                     action_chunk_size=8)),
}

# [B-1] Chunk-generation rows: name -> (method of [S-6], soft window or None, label).
CHUNK_ROWS = {
    "naive": ("naive", None, "naive (base policy)"),
    "inference_hard": ("inference_hard", None, "inference hard RTC"),
    "inference_soft": ("inference_soft", None, "inference soft RTC"),
    "train_hard": ("train_hard", None, "train hard RTC"),
    "train_soft_lam1": ("train_soft", (1.0, 5), "train soft RTC (lam=1)"),
    "train_soft_lam2": ("train_soft", (2.0, 5), "train soft RTC (lam=2)"),
    "train_soft_lam2_consistent": ("train_soft", (2.0, 5), "train soft RTC (lam=2, consistent step)"),
}
# [B-1], [S-10] The solver step of a training-time row; rows not named run Algorithm 1's.
ROW_STEPS = {"train_soft_lam2_consistent": "consistent"}
# [B-9] The training-time rows held to TRAIN_SAMPLER_LIMIT (those a result has: older results lack the
# consistent-step row).
TRAIN_ROWS = ("train_hard", "train_soft_lam1", "train_soft_lam2", "train_soft_lam2_consistent")
# [B-4] Straightforward reference rows measured next to the fast path.
REFERENCE_ROWS = ("naive", "train_soft_lam2")
# [B-14] Rows also measured as the public release's guided sampler runs them, next to the fast path.
PUBLIC_ROWS = ("inference_soft",)
TRAIN_METHODS = ("none", "hard", "soft")

# [B-5] Fast and straightforward chunks agree within this float32 tolerance: |a - b| <= ATOL + RTOL |b|.
ATOL = RTOL = 1e-4

# [B-9] Targets (limits on ratios of medians).
TRAIN_SAMPLER_LIMIT = 1.05
NAIVE_VS_STRAIGHTFORWARD_LIMIT = 0.9
SOFT_STEP_LIMIT = 1.03
# Fast guided rows over the public-style guided sampler ([B-14]) at every batch size.
GUIDED_VS_PUBLIC_LIMIT = 0.9



# --------------------------------------------------------------------------- config


@dataclasses.dataclass(frozen=True)
class BenchConfig:
    """Everything the benchmark varies ([B-2], [B-6], [B-8]); every field is validated.

    ``delay`` is ``None`` to rotate d over 0 .. min(s, H - s) across calls
    (default), or one fixed delay. ``path`` selects the implementation of the
    six method rows ("fast" or "straightforward", [B-3], [B-4]).
    """

    calls: int = 200
    warmup: int = 5
    batch_sizes: tuple = (1, 32)
    delay: int | None = None
    seed: int = 0
    num_steps: int = 5
    execute_horizon: int = 4
    path: str = "fast"
    train_batch: int = 32
    train_calls: int = 50
    arch: str = "benchmark"

    def __post_init__(self) -> None:
        check_int("calls", self.calls, 1, 10**7)
        check_int("warmup", self.warmup, 1, 10**6)
        if not isinstance(self.batch_sizes, tuple) or not self.batch_sizes:
            raise ValueError(f"batch_sizes must be a non-empty tuple of integers >= 1, got {self.batch_sizes!r}")
        for b in self.batch_sizes:
            check_int("batch_sizes entry", b, 1, 1 << 16)
        if len(set(self.batch_sizes)) != len(self.batch_sizes):
            raise ValueError(f"batch_sizes must not repeat a size, got {self.batch_sizes!r}")
        check_choice("arch", self.arch, tuple(ARCHS))
        H = ARCHS[self.arch]["config"].action_chunk_size
        check_int("execute_horizon", self.execute_horizon, 1, H)
        if self.delay is not None:
            check_int("delay", self.delay, 0, self.max_delay)
        check_int("seed", self.seed, 0, 2**31 - 1)
        check_int("num_steps", self.num_steps, 1, 1000)
        check_choice("path", self.path, ("fast", "straightforward"))
        check_int("train_batch", self.train_batch, 1, 1 << 16)
        check_int("train_calls", self.train_calls, 0, 10**7)

    @property
    def horizon(self) -> int:
        return ARCHS[self.arch]["config"].action_chunk_size

    @property
    def max_delay(self) -> int:
        """Largest executable delay min(s, H - s) ([X-1])."""
        return min(self.execute_horizon, self.horizon - self.execute_horizon)

    @property
    def delays(self) -> tuple:
        """Delays used call by call: rotating 0 .. max_delay, or the fixed one ([B-2])."""
        return tuple(range(self.max_delay + 1)) if self.delay is None else (self.delay,)


# --------------------------------------------------------------------------- policy and inputs


def make_policy(config: BenchConfig) -> FlowPolicy:
    """The benchmark policy ([B-2]): seed-initialised, adaLN kernels redrawn so that time matters.

    adaLN-zero initialisation ([P-6]) makes a fresh network independent of
    time, which would make the path-agreement check of [B-5] vacuous.
    """
    if not isinstance(config, BenchConfig):
        raise ValueError(f"config must be a BenchConfig, got {type(config).__name__}")
    arch = ARCHS[config.arch]
    policy = FlowPolicy(obs_dim=arch["obs_dim"], action_dim=arch["action_dim"], config=arch["config"],
                        rngs=nnx.Rngs(config.seed))
    rng = np.random.default_rng(config.seed)
    for block in policy.mlp_stack:
        for lin in (block.adaln_1, block.adaln_2):
            lin.kernel[...] = jnp.asarray(0.02 * rng.standard_normal(lin.kernel.shape), jnp.float32)
    policy.final_adaln.kernel[...] = jnp.asarray(0.02 * rng.standard_normal(policy.final_adaln.kernel.shape),
                                                 jnp.float32)
    return policy


def inputs(config: BenchConfig, policy: FlowPolicy, batch: int, count: int) -> list[tuple]:
    """``count`` input sets (obs, noise, prior) on the device, drawn once so no call times a draw."""
    rng = np.random.default_rng([config.seed, batch])
    H, A, O = policy.action_chunk_size, policy.action_dim, policy.obs_dim
    out = []
    for _ in range(count):
        out.append(tuple(jax.device_put(np.asarray(a, np.float32)) for a in (
            rng.standard_normal((batch, O)), rng.standard_normal((batch, H, A)), rng.standard_normal((batch, H, A)))))
    return out
