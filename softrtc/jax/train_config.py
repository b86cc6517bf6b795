"""The training configuration of chapter T and its optimiser ([T-1]..[T-6], ``spec/31-training-jax.md``)."""

from __future__ import annotations

import dataclasses
import types
from typing import Any, Mapping

import jax
import jax.numpy as jnp
import optax

from softrtc.reference import endpoints as _ref_ep
from softrtc.reference import weights as _ref_w
from softrtc.reference._validate import check_choice, check_int, check_real

from . import weights as _jw
from .delays import MAX_DELAY

__all__ = ["METHODS", "TrainConfig", "make_optimizer"]

METHODS = ("none", "hard", "soft")

# Large enough for any run, small enough to stay an int32 step counter.
MAX_STEPS = 2**31 - 1
MAX_BATCH = 2**24


# --------------------------------------------------------------------------- config


def _to_reference_window(window: Any) -> _ref_w.SoftWindow:
    """A reference (host-side, hashable, JSON-able) window from either window type ([W-7])."""
    if isinstance(window, _ref_w.SoftWindow):
        return window
    if not isinstance(window, _jw.SoftWindow):
        raise ValueError(f"window must be a SoftWindow (reference or JAX), got {type(window).__name__}")
    r = window.rule
    if any(isinstance(a, jax.core.Tracer) for a in (r.lam, r.h_max, r.length)):
        raise ValueError("window must have concrete rule parameters (not traced) in a TrainConfig")
    _jw.from_reference(window)  # kind and parameter ranges ([E-1]) before the conversion
    if r.kind == "delay_scaled":
        rule = _ref_ep.delay_scaled(float(r.lam), int(r.h_max))
    elif r.kind == "offset":
        rule = _ref_ep.offset(int(r.length), int(r.h_max))
    elif r.kind == "fixed":
        rule = _ref_ep.fixed(int(r.length))
    else:
        rule = _ref_ep.hard()
    return _ref_w.SoftWindow(rule, window.schedule, window.parametrization, window.overflow)


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """All hyper-parameters of behaviour-cloning training ([T-1]).

    Method ([T-3]): ``method`` in {"none", "hard", "soft"}; ``window`` is the soft
    window of [W-7] (reference or JAX ``SoftWindow``, stored as the reference
    type; used by ``soft`` only); ``execute_horizon`` is ``s`` (needed by
    ``soft`` with ``overflow="clip"``, [W-6], [D-4]; ``None`` otherwise allowed).

    Delays ([D-1]..[D-4]): ``delay_dist`` in {"uniform", "exponential"} on
    ``d_min .. d_max`` with ``delay_decay`` (exponential only). Ignored by ``none``.

    Optimiser ([T-6]): AdamW (``learning_rate``, ``weight_decay``, ``adam_b1``,
    ``adam_b2``, ``adam_eps``) after global-norm clipping at ``grad_clip_norm``;
    linear warm-up over ``warmup_steps``, then constant, or cosine decay to
    ``final_lr_ratio * learning_rate`` at step ``decay_steps`` when given.

    ``batch_size`` is used by :func:`train` when it samples batches from arrays.
    Every field is validated; a bad value raises ``ValueError`` naming the field
    and its allowed range.
    """

    method: str = "soft"
    window: Any = dataclasses.field(default_factory=_ref_w.SoftWindow)
    execute_horizon: int | None = 4
    delay_dist: str = "uniform"
    d_min: int = 0
    d_max: int = 4
    delay_decay: float = 1.0
    batch_size: int = 256
    learning_rate: float = 3e-4
    weight_decay: float = 1e-2
    adam_b1: float = 0.9
    adam_b2: float = 0.999
    adam_eps: float = 1e-8
    grad_clip_norm: float = 1.0
    warmup_steps: int = 0
    decay_steps: int | None = None
    final_lr_ratio: float = 0.0

    def __post_init__(self) -> None:
        check_choice("method", self.method, METHODS)
        # Stored as the reference window: plain Python values keep the config hashable and JSON-able.
        object.__setattr__(self, "window", _to_reference_window(self.window))
        if self.execute_horizon is not None:
            check_int("execute_horizon", self.execute_horizon, 1, MAX_DELAY)
        elif self.method == "soft" and self.window.overflow == "clip":
            raise ValueError("execute_horizon must be an integer in [1, H] for method='soft' with "
                             "overflow='clip' (the clipped window needs s, [W-6], [D-4]), got None")
        check_choice("delay_dist", self.delay_dist, ("uniform", "exponential"))
        check_int("d_min", self.d_min, 0, MAX_DELAY)
        check_int("d_max", self.d_max, self.d_min, MAX_DELAY)
        check_real("delay_decay", self.delay_decay, 0.0, 64.0)
        check_int("batch_size", self.batch_size, 1, MAX_BATCH)
        check_real("learning_rate", self.learning_rate, 0.0, 10.0, lo_open=True)
        check_real("weight_decay", self.weight_decay, 0.0, 10.0)
        check_real("adam_b1", self.adam_b1, 0.0, 1.0, hi_open=True)
        check_real("adam_b2", self.adam_b2, 0.0, 1.0, hi_open=True)
        check_real("adam_eps", self.adam_eps, 0.0, 1.0, lo_open=True)
        check_real("grad_clip_norm", self.grad_clip_norm, 0.0, 1e12, lo_open=True)
        check_int("warmup_steps", self.warmup_steps, 0, MAX_STEPS)
        if self.decay_steps is not None:
            check_int("decay_steps", self.decay_steps, self.warmup_steps + 1, MAX_STEPS)
        check_real("final_lr_ratio", self.final_lr_ratio, 0.0, 1.0)

    def to_dict(self) -> dict:
        """JSON-able dict (e.g. for checkpoint metadata); inverse of :meth:`from_dict`."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        out["window"] = self.window.to_dict()
        return out

    @classmethod
    def from_dict(cls, data: Mapping) -> "TrainConfig":
        """Rebuilds a config written by :meth:`to_dict` (validated like the constructor)."""
        if not isinstance(data, Mapping):
            raise ValueError(f"data must be a mapping as written by TrainConfig.to_dict, got {type(data).__name__}")
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f"data has unknown TrainConfig fields {unknown}")
        kw = dict(data)
        if "window" in kw:
            w = kw["window"]
            if not isinstance(w, Mapping) or not isinstance(w.get("rule"), Mapping):
                raise ValueError("data['window'] must be a mapping with a 'rule' mapping (SoftWindow.to_dict)")
            try:
                rule = _ref_ep.EndpointRule(**w["rule"])
                kw["window"] = _ref_w.SoftWindow(rule, **{k: x for k, x in w.items() if k != "rule"})
            except TypeError as exc:
                raise ValueError(f"data['window'] is not a SoftWindow dict: {exc}") from exc
        return cls(**kw)


# --------------------------------------------------------------------------- optimiser


def _decay_mask(params: Any) -> Any:
    # Decay matrices (kernels) only: decaying biases and gains only shrinks offsets, a common AdamW choice.
    return jax.tree.map(lambda p: jnp.ndim(p) >= 2, params)


_OPTIMIZER_FIELDS = ("learning_rate", "weight_decay", "adam_b1", "adam_b2", "adam_eps", "grad_clip_norm",
                     "warmup_steps", "decay_steps", "final_lr_ratio")


def make_optimizer(config: TrainConfig) -> tuple[optax.GradientTransformation, optax.Schedule]:
    """``(optax transformation, learning-rate schedule)`` of ``config`` ([T-6]).

    Global-norm clipping at ``grad_clip_norm`` followed by AdamW; weight decay
    applies to parameters with ``ndim >= 2`` (kernels), not to biases.
    """
    if not isinstance(config, TrainConfig):
        raise ValueError(f"config must be a TrainConfig, got {type(config).__name__}")
    return _optimizer(_optimizer_key(config))


def _optimizer_key(config: TrainConfig) -> tuple:
    return tuple((f, getattr(config, f)) for f in _OPTIMIZER_FIELDS)


def _optimizer(key: tuple) -> tuple[optax.GradientTransformation, optax.Schedule]:
    config = types.SimpleNamespace(**dict(key))
    lr = config.learning_rate
    if config.decay_steps is not None:
        schedule = optax.warmup_cosine_decay_schedule(
            init_value=0.0 if config.warmup_steps else lr, peak_value=lr,
            warmup_steps=config.warmup_steps, decay_steps=config.decay_steps,
            end_value=lr * config.final_lr_ratio)
    elif config.warmup_steps:
        schedule = optax.join_schedules(
            [optax.linear_schedule(0.0, lr, config.warmup_steps), optax.constant_schedule(lr)],
            [config.warmup_steps])
    else:
        schedule = optax.constant_schedule(lr)
    # The same transformation as chain(clip_by_global_norm, adamw(mask=kernels)). Clipping and the Adam
    # moments run on one flattened vector: a few large ops instead of a few per parameter leaf, which
    # compiles several times faster and fuses better.
    tx = optax.chain(
        optax.flatten(optax.chain(
            optax.clip_by_global_norm(config.grad_clip_norm),
            optax.scale_by_adam(b1=config.adam_b1, b2=config.adam_b2, eps=config.adam_eps),
        )),
        optax.add_decayed_weights(config.weight_decay, mask=_decay_mask),
        optax.scale_by_learning_rate(schedule),
    )
    return tx, schedule

