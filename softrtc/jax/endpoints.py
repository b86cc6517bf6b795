"""Endpoint rules e(d) in JAX (spec chapter E, 01-weights.md); twin of ``softrtc.reference.endpoints``.

A rule is a pytree: its ``kind`` is static (part of the tree structure), its
parameters ``lam`` (float32), ``h_max`` and ``length`` (int32) are leaves, so
one compiled function serves every delay *and* every parameter value of a
rule kind ([E-1]). The delay ``d`` may be traced as well.

>>> import jax.numpy as jnp
>>> [int(endpoint(delay_scaled(2.0, 5), d)) for d in range(6)]
[0, 2, 4, 5, 5, 5]

The delay-scaled ceiling ([E-2]) is ``ceil(lam * d - 1e-4)`` in float32. It
equals the reference's exact one for every ``lam`` with at most three decimal
places while ``lam * d <= 256``: the float32 rounding error of ``lam * d`` stays
below 5e-5, and the exact ``lam * d`` is an integer or at least 1e-3 above one.

>>> [int(endpoint(delay_scaled(1.6, 16), d)) for d in range(6)]
[0, 2, 4, 5, 7, 8]
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from softrtc.reference import endpoints as _ref

from . import _validate as v

RULES = _ref.RULES
MAX_WINDOW = _ref.MAX_WINDOW
DELAY_SCALED_DELTA = float(_ref.DELAY_SCALED_DELTA)  # [E-2]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class EndpointRule:
    """An endpoint rule ([E-1]) as a pytree: static ``kind``, traced parameters.

    Unused parameters are 0, so every rule of a kind has the same tree
    structure (and the same compiled code). Build with :func:`delay_scaled`,
    :func:`offset`, :func:`fixed`, :func:`hard` or :func:`from_reference`.
    """

    lam: jax.Array
    h_max: jax.Array
    length: jax.Array
    kind: str = dataclasses.field(metadata=dict(static=True), default="hard")

    def bound(self):
        """Largest endpoint over all d: h_max, h, or None for ``hard`` (bounded by d)."""
        if self.kind in ("delay_scaled", "offset"):
            return self.h_max
        if self.kind == "fixed":
            return self.length
        return None


def _rule(kind, lam=0.0, h_max=0, length=0) -> EndpointRule:
    # Concrete parameters stay NumPy scalars (jit takes them as it takes arrays); traced ones stay traced.
    xp = jnp if v.is_traced((lam, h_max, length)) else np
    return EndpointRule(lam=xp.asarray(lam, xp.float32), h_max=xp.asarray(h_max, xp.int32),
                        length=xp.asarray(length, xp.int32), kind=kind)


def delay_scaled(lam, h_max) -> EndpointRule:
    """[E-2] e(d) = min(ceil(lam d - 1e-4), h_max); lam in [0, 4096], h_max integer in [0, 4096] ([E-1])."""
    return _rule("delay_scaled", lam=v.real_value("lam", lam, 0.0, float(MAX_WINDOW)),
                 h_max=v.int_value("h_max", h_max, 0, MAX_WINDOW))


def offset(length, h_max) -> EndpointRule:
    """[E-3] e(d) = min(d + L, h_max) for d > 0; L, h_max integers in [0, 4096] ([E-1])."""
    return _rule("offset", length=v.int_value("length", length, 0, MAX_WINDOW),
                 h_max=v.int_value("h_max", h_max, 0, MAX_WINDOW))


def fixed(h) -> EndpointRule:
    """[E-4] e(d) = h for d > 0; h integer in [0, 4096] ([E-1])."""
    return _rule("fixed", length=v.int_value("h", h, 0, MAX_WINDOW))


def hard() -> EndpointRule:
    """[E-5] e(d) = d (Hard training-time RTC)."""
    return _rule("hard")


def _checked(rule: EndpointRule) -> EndpointRule:
    """A rule built directly (not by a constructor) gets the constructors' checks ([E-1], [N-7]).

    The kind always; the parameters when concrete (inside ``jit`` they are
    traced and only their shape and dtype can be checked).
    """
    if rule.kind not in RULES:
        raise ValueError(f"rule.kind must be one of {RULES}, got {rule.kind!r}")
    specs = (("lam", rule.lam, jnp.floating), ("h_max", rule.h_max, jnp.integer), ("length", rule.length, jnp.integer))
    for name, value, kind in specs:
        _check_scalar(f"rule.{name}", value, kind)
    if not v.is_traced(rule):
        v.real_value("rule.lam", float(rule.lam), 0.0, float(MAX_WINDOW))
        v.int_value("rule.h_max", rule.h_max, 0, MAX_WINDOW)
        v.int_value("rule.length", rule.length, 0, MAX_WINDOW)
        for name in ("lam", "h_max", "length"):
            if name not in _ref.RULE_PARAMETERS[rule.kind] and float(getattr(rule, name)) != 0:
                raise ValueError(f"rule.{name} is not a parameter of the {rule.kind!r} rule and must be 0, "
                                 f"got {getattr(rule, name)}")
    return rule


def _check_scalar(name: str, value, kind) -> None:
    """A rule parameter (or code) is a scalar of the given dtype kind; shape and dtype only ([N-7], [N-10])."""
    want = "float" if kind is jnp.floating else "integer"
    # A string, None or an object has no numeric dtype (jnp.result_type(None) is float32, so None is explicit).
    ok = value is not None and not isinstance(value, (str, bytes))
    if ok:
        try:
            dt = jnp.result_type(value)
        except (TypeError, ValueError):
            ok = False
    if not ok or jnp.ndim(value) != 0 or not jnp.issubdtype(dt, kind):
        got = f"{dt} of shape {list(jnp.shape(value))}" if ok else repr(value)
        raise ValueError(f"{name} must be a scalar of {want} dtype, got {got}")


def from_reference(rule: _ref.EndpointRule) -> EndpointRule:
    """The JAX rule with the parameters of a (validated) reference rule ([E-1])."""
    if isinstance(rule, EndpointRule):
        return _checked(rule)
    if not isinstance(rule, _ref.EndpointRule):
        raise ValueError(f"rule must be an EndpointRule, got {type(rule).__name__}")
    return _rule(rule.kind, lam=rule.lam or 0.0, h_max=rule.h_max or 0, length=rule.length or 0)


def endpoint(rule: EndpointRule, d) -> jax.Array:
    """Raw endpoint e(d) as an int32 scalar ([E-1]..[E-6]); ``d`` may be traced.

    [E-6] every rule gives e(0) = 0. ``d`` must be an integer in [0, 4096]
    (checked when concrete; traced values outside give undefined results).
    The delay-scaled ceiling agrees with the reference's for lam with at most three decimals (module doc).
    Works under ``vmap`` over ``d`` and over the rule's parameters.
    """
    rule = from_reference(rule)
    d = v.int_value("d", d, 0, MAX_WINDOW)
    return endpoint_by_code(RULES.index(rule.kind), rule.lam, rule.h_max, rule.length, d)


def endpoint_by_code(kind, lam, h_max, length, d) -> jax.Array:
    """e(d) for the rule ``RULES[kind]`` ([E-1]..[E-6]); the kind code may be traced.

    A Python int ``kind`` evaluates only its own rule; a traced one evaluates
    all four and selects, so one compiled function serves every rule kind
    (used by the weight tables, [W-7]). Arguments are checked like the rule's
    ([E-1], [N-7]): ``kind`` an integer code in [0, 3] (an index into
    ``RULES``), ``lam`` a real in [0, 4096], ``h_max``, ``length`` and ``d``
    integers in [0, 4096], and, for a concrete Python ``kind``, a parameter
    the rule does not have must be 0. Concrete values are range-checked;
    traced ones are checked for shape and dtype only ([N-10]).
    """
    if isinstance(kind, (str, bool, np.bool_)) or kind is None:
        raise ValueError(f"kind must be an integer code in [0, {len(RULES) - 1}] (the index of the rule in "
                         f"{RULES}), got {kind!r}")
    if isinstance(kind, (int, np.integer)):
        kind = v.check_int("kind", kind, 0, len(RULES) - 1)
    else:
        _check_scalar("kind", kind, jnp.integer)
        kind = v.int_value("kind", kind, 0, len(RULES) - 1)
    if v.is_traced(lam):
        v.real_dtype("lam", lam, "be a real scalar")
    lam = v.real_value("lam", lam, 0.0, float(MAX_WINDOW))
    params = {"h_max": v.int_value("h_max", h_max, 0, MAX_WINDOW),
              "length": v.int_value("length", length, 0, MAX_WINDOW)}
    if isinstance(kind, int):
        name = RULES[kind]
        for pname, value in (("lam", lam), *params.items()):
            if pname not in _ref.RULE_PARAMETERS[name] and not v.is_traced(value) and float(value) != 0:
                raise ValueError(f"{pname} is not a parameter of the {name!r} rule and must be 0, got {value}")
    h_max, length = params["h_max"], params["length"]
    d = v.int_value("d", d, 0, MAX_WINDOW)
    rules = {
        # ceil(0 - 1e-4) = 0 already gives [E-6]; 1e-4 is [E-2]'s delta.
        "delay_scaled": lambda: jnp.minimum(
            jnp.ceil(lam * d.astype(jnp.float32) - DELAY_SCALED_DELTA).astype(jnp.int32), h_max),
        "fixed": lambda: jnp.where(d == 0, 0, length).astype(jnp.int32),
        "offset": lambda: jnp.where(d == 0, 0, jnp.minimum(d + length, h_max)).astype(jnp.int32),
        "hard": lambda: d,
    }
    return v.select_by_code(kind, [rules[name] for name in RULES])
