"""Planar pymunk arm sorting environment, scripted expert and demo generator.

Spec chapter A (``spec/10-arm.md``).
"""

from .env import ACTION_DIM, OBS_DIM, OBS_SLICES, ArmConfig, ArmSortEnv, forward_kinematics, inverse_kinematics
from .expert import ExpertConfig, ScriptedExpert, expert_success_rate, run_expert_episode
from .demos import generate_demos, load_demos, rollout_noisy_episode

__all__ = [
    "ACTION_DIM", "OBS_DIM", "OBS_SLICES", "ArmConfig", "ArmSortEnv", "forward_kinematics",
    "inverse_kinematics", "ExpertConfig", "ScriptedExpert", "expert_success_rate",
    "run_expert_episode", "generate_demos", "load_demos", "rollout_noisy_episode",
]
