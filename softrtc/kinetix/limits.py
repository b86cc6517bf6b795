"""Ranges shared by the Kinetix library and ``softrtc kinetix`` ([KE-1], [KE-9], [KE-12], [N-11]).

One constant per bound, read by the library's validation and by the
command line's option types, so an option accepts exactly the values the call
it feeds accepts. NumPy and JAX are not imported: the CLI builds its parser
from these without loading either.

>>> EPISODES_MAX, REPEATS_MAX, EPISODE_STEPS_MIN
(65536, 100, 1)
"""

from __future__ import annotations

__all__ = ["BATCH_MAX", "EPISODES_MAX", "EPISODE_STEPS_MIN", "EPISODE_STEPS_MAX", "NUM_ENVS_MAX", "NUM_STEPS_MAX", "REPEATS_MAX"]

# [KE-1] episodes per (level, delay, method): EvalConfig.episodes and ``eval --episodes``.
EPISODES_MAX = 1 << 16
# [KE-1] control steps per episode: EvalConfig.episode_steps and make_rollout's episode_steps.
EPISODE_STEPS_MIN = 1
EPISODE_STEPS_MAX = 1 << 16
# [KE-9] bench_harness num_envs / repeats and ``bench --num-envs`` / ``--repeats``.
NUM_ENVS_MAX = 1 << 16
REPEATS_MAX = 100
# [K-12], [N-12] environments per batched call (reset_batch, random_actions, make_random_rollout):
# the harness's own bound on make_rollout's num_envs.
BATCH_MAX = 1 << 20
# [K-13] steps per bare-env benchmark scan (bench_bare_env, make_random_rollout).
NUM_STEPS_MAX = 1 << 20
