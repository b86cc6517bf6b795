"""DART-style demonstration generator for the arm sorting task (spec chapter A).

The scripted expert drives the environment through noisy joint targets, and
every visited state is labelled with the expert's clean action for that state
([A-15], [A-16]). Training on such data teaches a policy how to recover from
the drift that its own errors cause.
"""

from __future__ import annotations

import os

import numpy as np

from softrtc._files import check_out_file
from softrtc.reference._validate import check_int

from ._checks import check_number
from .env import ACTION_DIM, NUM_JOINTS, NUM_OBJECTS, OBS_DIM, ArmConfig, ArmSortEnv
from .geometry import _check_env_config
from .expert import ExpertConfig, ScriptedExpert

__all__ = ["generate_demos", "rollout_noisy_episode", "load_demos"]

# Largest seed a demo file can store (saved as int64, [A-16]).
SEED_MAX = 2**63 - 1


def rollout_noisy_episode(env: ArmSortEnv, expert: ScriptedExpert, env_seed, rng: np.random.Generator,
                          noise_std: float, perturb_prob: float = 0.0, perturb_std: float = 0.0,
                          perturb_steps: int = 10) -> dict:
    """One DART episode: execute noisy actions, record clean labels ([A-15]).

    Each step the executed joint targets are the expert's targets plus
    ``N(0, noise_std^2)`` per joint plus, while a perturbation is active, a
    constant offset drawn from ``N(0, perturb_std^2)``; a perturbation starts
    with probability ``perturb_prob`` on a step without one and lasts
    ``perturb_steps`` steps. The noisy targets are clipped to the joint limits
    (the generator's rule, [A-15]); the gripper command is never noised.
    """
    if not isinstance(env, ArmSortEnv):
        raise ValueError("env must be an ArmSortEnv")
    if not isinstance(expert, ScriptedExpert):
        raise ValueError("expert must be a ScriptedExpert")
    if not isinstance(rng, np.random.Generator):
        raise ValueError("rng must be a numpy.random.Generator")
    noise_std = check_number("noise_std", noise_std, 0.0, 1.0)
    perturb_prob = check_number("perturb_prob", perturb_prob, 0.0, 1.0)
    perturb_std = check_number("perturb_std", perturb_std, 0.0, 2.0)
    perturb_steps = check_int("perturb_steps", perturb_steps, 1, 10_000)
    env_seed = check_int("env_seed", env_seed, 0, SEED_MAX)
    obs = env.reset(env_seed)
    obs_l, lab_l, exe_l = [], [], []
    offset = np.zeros(NUM_JOINTS)
    left = 0
    info = {"success": False, "completed": [False] * NUM_OBJECTS, "success_step": None}
    while not env.done:
        label = expert.act(obs)
        # Draw every random number on every step so the stream does not depend
        # on which branch was taken.
        noise = rng.normal(0.0, 1.0, size=NUM_JOINTS) * noise_std
        start = rng.random() < perturb_prob
        new_offset = rng.normal(0.0, 1.0, size=NUM_JOINTS) * perturb_std
        if left == 0 and start:
            offset, left = new_offset, perturb_steps
        executed = label.copy()
        executed[:NUM_JOINTS] = np.clip(label[:NUM_JOINTS] + noise + (offset if left > 0 else 0.0),
                                        env.joint_low, env.joint_high)
        left = max(0, left - 1)
        obs_l.append(obs)
        lab_l.append(label)
        exe_l.append(executed)
        obs, info = env.step(executed)
    return {
        "obs": np.asarray(obs_l),
        "action": np.asarray(lab_l),
        "executed_action": np.asarray(exe_l),
        "success": bool(info["success"]),
        "success_step": -1 if info["success_step"] is None else int(info["success_step"]),
        "completed": np.asarray(info["completed"], dtype=bool),
    }


def generate_demos(num_episodes, seed, noise_std, path, perturb_prob=0.005, perturb_std=0.15,
                   perturb_steps=10, env_config: ArmConfig | None = None,
                   expert_config: ExpertConfig | None = None) -> dict:
    """Generate ``num_episodes`` DART demonstrations and save them to ``path`` ([A-15], [A-16]).

    Episode ``i`` uses the ``i``-th child of ``numpy.random.SeedSequence(seed)``
    for both its environment seed and its noise stream, so the file is a pure
    function of the arguments. ``path`` must end in ``.npz``; its parent folder
    must exist. Returns a summary dict (episodes, steps, success rate).
    """
    num_episodes = check_int("num_episodes", num_episodes, 1, None)
    seed = check_int("seed", seed, 0, SEED_MAX)
    noise_std = check_number("noise_std", noise_std, 0.0, 1.0)
    perturb_prob = check_number("perturb_prob", perturb_prob, 0.0, 1.0)
    perturb_std = check_number("perturb_std", perturb_std, 0.0, 2.0)
    perturb_steps = check_int("perturb_steps", perturb_steps, 1, 10_000)
    check_out_file("path", path, ".npz")
    env_config = _check_env_config(env_config, "env_config")
    if expert_config is not None and not isinstance(expert_config, ExpertConfig):
        raise ValueError(f"expert_config must be an ExpertConfig or None, got {type(expert_config).__name__}")
    env = ArmSortEnv(env_config)
    expert = ScriptedExpert(env.config, expert_config)
    children = np.random.SeedSequence(seed).spawn(num_episodes)
    episodes, env_seeds = [], []
    for child in children:
        env_seed = int(child.generate_state(1, dtype=np.uint32)[0])
        rng = np.random.default_rng(child)
        episodes.append(rollout_noisy_episode(env, expert, env_seed, rng, noise_std,
                                              perturb_prob, perturb_std, perturb_steps))
        env_seeds.append(env_seed)
    lengths = np.array([len(e["obs"]) for e in episodes], dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
    data = {
        "obs": np.concatenate([e["obs"] for e in episodes]).astype(np.float32),
        "action": np.concatenate([e["action"] for e in episodes]).astype(np.float32),
        "executed_action": np.concatenate([e["executed_action"] for e in episodes]).astype(np.float32),
        "episode_id": np.repeat(np.arange(num_episodes, dtype=np.int64), lengths),
        "episode_start": starts,
        "episode_length": lengths,
        "success": np.array([e["success"] for e in episodes], dtype=bool),
        "success_step": np.array([e["success_step"] for e in episodes], dtype=np.int64),
        "completed": np.stack([e["completed"] for e in episodes]),
        "env_seed": np.array(env_seeds, dtype=np.int64),
        "seed": np.array(seed, dtype=np.int64),
        "noise_std": np.array(noise_std, dtype=np.float64),
        "control_hz": np.array(env.config.control_hz, dtype=np.int64),
    }
    np.savez_compressed(path, **data)
    return {
        "path": os.fspath(path),
        "episodes": num_episodes,
        "steps": int(lengths.sum()),
        "success_rate": float(data["success"].mean()),
        "obs_dim": OBS_DIM,
        "action_dim": ACTION_DIM,
    }


def load_demos(path) -> dict:
    """Load a file written by ``generate_demos`` into a dict of arrays ([A-16])."""
    if not isinstance(path, (str, os.PathLike)) or not os.path.isfile(path):
        raise ValueError(f"path must name an existing .npz file, got {path!r}")
    try:
        f = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise ValueError(f"path {path!r} is not a readable .npz file: {exc}") from None
    if not isinstance(f, np.lib.npyio.NpzFile):  # a .npy file loads as one array, not an archive
        raise ValueError(f"path {path!r} is a single .npy array, expected the .npz archive of generate_demos")
    with f:
        return {k: f[k] for k in f.files}
