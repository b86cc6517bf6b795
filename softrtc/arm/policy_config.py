"""Sizes and methods of the arm policies ([A-17], [A-20], [S-6])."""

from __future__ import annotations

import dataclasses

import flax.nnx as nnx

from softrtc.jax.policy import FlowPolicy, PolicyConfig
from softrtc.reference._validate import check_int

from .env import ACTION_DIM
from .features import FEATURE_DIM

__all__ = ["TRAIN_METHODS", "STUDY_METHODS", "METHOD_LABELS", "ArmPolicyConfig", "new_model"]

# Training objective of each checkpoint ([A-20]): base = ordinary flow matching (w = 0).
TRAIN_METHODS = ("naive", "train_hard", "train_soft")
# The study's three policies and the sampler each is run with ([S-6]).
STUDY_METHODS = ("naive", "train_hard", "train_soft")
METHOD_LABELS = {"naive": "Base", "train_hard": "Train Hard RTC", "train_soft": "Train Soft RTC",
                 "inference_hard": "Inference Hard RTC", "inference_soft": "Inference Soft RTC"}


@dataclasses.dataclass(frozen=True)
class ArmPolicyConfig:
    """Horizon, execute horizon, Euler steps and network sizes of the arm policies ([A-17]).

    ``horizon`` H = 10 and ``execute_horizon`` s = 5 at 50 Hz give executable
    delays up to ``min(s, H - s) = 5`` ticks (100 ms, [X-1]).
    """

    horizon: int = 10
    execute_horizon: int = 5
    num_steps: int = 5
    channel_dim: int = 128
    channel_hidden_dim: int = 256
    token_hidden_dim: int = 32
    num_layers: int = 2

    def __post_init__(self):
        check_int("horizon", self.horizon, 2, 64)
        check_int("execute_horizon", self.execute_horizon, 1, self.horizon - 1)
        check_int("num_steps", self.num_steps, 1, 64)
        check_int("channel_dim", self.channel_dim, 2, 1024)
        if self.channel_dim % 2:
            raise ValueError(f"channel_dim must be even, got {self.channel_dim}")
        check_int("channel_hidden_dim", self.channel_hidden_dim, 1, 4096)
        check_int("token_hidden_dim", self.token_hidden_dim, 1, 1024)
        check_int("num_layers", self.num_layers, 1, 16)

    @property
    def max_delay(self) -> int:
        """Largest executable delay min(s, H - s) ([X-1])."""
        return min(self.execute_horizon, self.horizon - self.execute_horizon)

    def policy_config(self) -> PolicyConfig:
        """The ``FlowPolicy`` sizes ([P-1]) with ``action_chunk_size = horizon``."""
        return PolicyConfig(channel_dim=self.channel_dim, channel_hidden_dim=self.channel_hidden_dim,
                            token_hidden_dim=self.token_hidden_dim, num_layers=self.num_layers,
                            action_chunk_size=self.horizon)


def new_model(config: ArmPolicyConfig, seed: int) -> FlowPolicy:
    """A fresh arm flow policy with the sizes of ``config``, initialised with ``nnx.Rngs(seed)`` ([A-17])."""
    return FlowPolicy(obs_dim=FEATURE_DIM, action_dim=ACTION_DIM, config=config.policy_config(),
                      rngs=nnx.Rngs(seed))
