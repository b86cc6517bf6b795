"""JAX implementation of softrtc; module names mirror softrtc.reference (see spec/00-overview.md).

The names users call are importable from here; each loads its module on
first access, so ``import softrtc.jax`` costs nothing until one is used::

    from softrtc.jax import FastChunks, FlowPolicy, PolicyConfig, shift_prior
"""

from __future__ import annotations

import importlib

# name -> module that defines it
_EXPORTS = {
    # the policy network ([P-1]) and its parameter files ([P-8], [T-11])
    "FlowPolicy": "policy", "PolicyConfig": "policy",
    "state_pure_dict": "params", "load_pure_dict": "params",
    "save_checkpoint": "checkpoint", "load_checkpoint": "checkpoint",
    # what the samplers call ([S-2], [P-11])
    "VelocityField": "protocols", "ConditionedModel": "protocols",
    # chunk generation ([S-6]) and its fast path ([B-3])
    "FastChunks": "fast_chunks", "METHODS": "methods", "generate_chunk": "methods", "method_weights": "methods",
    "naive_sample": "sampler", "rtc_sample": "sampler", "guided_sample": "guidance",
    "SoftWindow": "weights", "soft_weights": "weights", "hard_weights": "weights",
    # execution ([X-1]..[X-8])
    "shift_prior": "executor", "segment": "executor", "execute_chunks": "executor", "closed_loop": "executor",
    "check_delays": "executor",
    # training ([T-1]..[T-9])
    "TrainConfig": "training", "train": "training", "make_train_step": "training",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))
