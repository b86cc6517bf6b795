"""What the samplers call: a velocity field, or a model with precomputed time conditioning ([S-2], [P-11], [P-12]).

Any callable of the :class:`VelocityField` shape serves the straightforward
samplers (``naive_sample``, ``rtc_sample``, ``guided_sample``,
``generate_chunk``); any object of the :class:`ConditionedModel` shape serves
the conditioned ones (``*_sample_conditioned``, ``generate_chunk_conditioned``,
``generate_chunk_from_row``). :class:`~softrtc.jax.policy.FlowPolicy` is both.

>>> import flax.nnx as nnx
>>> from softrtc.jax.policy import FlowPolicy, PolicyConfig
>>> cfg = PolicyConfig(channel_dim=8, channel_hidden_dim=8, token_hidden_dim=4, num_layers=1, action_chunk_size=4)
>>> pol = FlowPolicy(obs_dim=3, action_dim=2, config=cfg, rngs=nnx.Rngs(0))
>>> isinstance(pol, VelocityField), isinstance(pol, ConditionedModel)
(True, True)
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import jax

__all__ = ["VelocityField", "ConditionedModel"]


@runtime_checkable
class VelocityField(Protocol):
    """``v(obs [B, O], x [B, H, A], t [B, H]) -> [B, H, A]``: the flow's velocity, one time per token ([S-2])."""

    def __call__(self, obs: jax.Array, x: jax.Array, t: jax.Array) -> jax.Array: ...


@runtime_checkable
class ConditionedModel(Protocol):
    """A velocity field split at its time path ([P-11], [P-12]).

    ``time_conditioning(t)`` returns every tensor that depends on the flow
    time ``t [..., H]`` (or ``[..., 1]``) alone; ``apply_conditioned(obs, x,
    cond)`` is the field given such a ``cond``, whose leading axes of size 1
    broadcast over the batch. ``apply_conditioned(obs, x,
    time_conditioning(t))`` equals ``v(obs, x, t)``.
    """

    def time_conditioning(self, t: jax.Array) -> Any: ...

    def apply_conditioned(self, obs: jax.Array, x: jax.Array, cond: Any) -> jax.Array: ...
