"""Token weights and schedules in JAX (spec chapter W, 01-weights.md); twin of ``softrtc.reference.weights``.

Shapes are static (the horizon ``H``); the delay ``d``, the endpoint ``e``,
the execute horizon ``s`` and the window's rule parameters may be traced, so
one compiled function serves every delay and every window of a given
horizon ``H``, whatever the rule kind, schedule, parametrization and
overflow ([W-7]): inside, the names travel as traced integer codes. In the
public API they are Python strings (static fields of :class:`SoftWindow`).

Instead of slicing (which needs static bounds) every function computes all
``H`` tokens and selects the committed prefix / window / tail with masks.

>>> [round(float(x), 3) for x in prefix_weights(10, 2, 6, "linear")]  # float32 values, rounded
[1.0, 1.0, 0.8, 0.6, 0.4, 0.2, 0.0, 0.0, 0.0, 0.0]
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from softrtc.reference import weights as _ref

from . import _validate as v
from . import endpoints as _ep
from .endpoints import EndpointRule, delay_scaled

SCHEDULES = _ref.SCHEDULES
PARAMETRIZATIONS = _ref.PARAMETRIZATIONS
OVERFLOWS = _ref.OVERFLOWS


def _schedule(code, x):
    u = 1.0 - x
    by_name = {
        "zeros": lambda: jnp.zeros_like(x),
        "ones": lambda: jnp.ones_like(x),
        "linear": lambda: u,
        # expm1(1) rather than e - 1 so that g(0) is exactly 1 ([W-3]); XLA may turn the division into a
        # product with the reciprocal (0.99999994 in float32 at u = 1), so u = 1 is pinned to 1.
        "exp": lambda: jnp.where(u == 1.0, 1.0, u * jnp.expm1(u) / jnp.expm1(jnp.ones((), u.dtype))),
    }
    return v.select_by_code(code, [by_name[n] for n in SCHEDULES])


def schedule_value(schedule: str, x) -> jax.Array:
    """Window schedule g(x) for x in [0, 1], any shape ([W-3]).

    zeros: 0; ones: 1; linear: 1 - x; exp: u expm1(u) / expm1(1), u = 1 - x.
    Concrete ``x`` outside [0, 1] is rejected.
    """
    v.check_choice("schedule", schedule, SCHEDULES)
    x = v.array("x", x, lo=0.0, hi=1.0)
    return _schedule(SCHEDULES.index(schedule), x)


def window_positions(H: int, d, e, parametrization: str = "rtc") -> jax.Array:
    """Relative positions x_j for all tokens j = 0 .. H-1 ([W-4], [W-5]).

    rtc: (j - d + 1) / (e - d + 1); paper: (j - d) / (e - d). Unlike the
    reference (which returns only the window tokens d .. e-1), the result has
    the static shape [H]; entries outside the window are clipped to [0, 1]
    and carry no meaning.
    """
    H = v.check_horizon(H)
    v.check_choice("parametrization", parametrization, PARAMETRIZATIONS)
    d = v.int_value("d", d, 0, H)
    e = v.int_value("e", e, 0, H)
    if not v.is_traced(d) and not v.is_traced(e) and int(e) < int(d):
        raise ValueError(f"e must be an integer in [d={int(d)}, {H}], got {int(e)}")
    return _positions(H, d, e, PARAMETRIZATIONS.index(parametrization))


# The private helpers below take the schedule, parametrization, overflow and
# rule kind as integer codes (indices into SCHEDULES, ...). A Python int code
# evaluates only its own variant; a traced code selects among all of them, so
# the jitted entry points compile once per horizon H for every variant.

def _positions(H, d, e, pcode):
    j = jnp.arange(H, dtype=jnp.float32)
    df, ef = jnp.asarray(d).astype(jnp.float32), jnp.asarray(e).astype(jnp.float32)
    by_name = {
        "rtc": lambda: (j - df + 1.0) / (ef - df + 1.0),
        # An empty window (e = d) has no tokens; the max only avoids 0/0 in masked lanes.
        "paper": lambda: (j - df) / jnp.maximum(ef - df, 1.0),
    }
    return jnp.clip(v.select_by_code(pcode, [by_name[n] for n in PARAMETRIZATIONS]), 0.0, 1.0)


def _prefix(H, d, e, scode, pcode):
    j = jnp.arange(H)
    g = _schedule(scode, _positions(H, d, e, pcode))
    return jnp.where(j < d, 1.0, jnp.where(j < e, g, 0.0)).astype(jnp.float32)


@functools.partial(jax.jit, static_argnums=(0,))
def _prefix_jit(H, d, e, scode, pcode):
    return _prefix(H, d, e, scode, pcode)


def prefix_weights(H: int, d, e, schedule: str = "linear", parametrization: str = "rtc") -> jax.Array:
    """Weights [H]: 1 for j < d, g(x_j) for d <= j < e, 0 for j >= e ([W-1], [W-4], [W-5]).

    Requires 0 <= d <= e <= H (checked when concrete; traced ``d``/``e``
    outside this range give undefined results). ``H`` and the names are static;
    one compilation per ``H`` serves every delay, endpoint and variant.
    """
    H = v.check_horizon(H)
    v.check_choice("schedule", schedule, SCHEDULES)
    v.check_choice("parametrization", parametrization, PARAMETRIZATIONS)
    d = v.int_value("d", d, 0, H)
    e = v.int_value("e", e, 0, H)
    if not v.is_traced((d, e)) and int(e) < int(d):
        raise ValueError(f"e must be an integer in [{int(d)}, {H}] (e >= d), got {int(e)}")
    return _prefix_jit(H, d, e, np.int32(SCHEDULES.index(schedule)),
                       np.int32(PARAMETRIZATIONS.index(parametrization)))


def effective_endpoint(H: int, d, e, s=None, overflow: str = "clip") -> jax.Array:
    """Effective endpoint e* ([W-2], [W-6]).

    [W-2] e* = max(e, d): the committed prefix is always clamped.
    [W-6] overflow="clip" also caps at the overlap: e* = max(d, min(e*, H - s)).
    ``d``, ``e`` in [0, H] and ``s`` in [1, H] may be traced (checked when concrete); a given
    ``s`` is checked under either overflow, as in the reference.
    """
    H = v.check_horizon(H)
    v.check_choice("overflow", overflow, OVERFLOWS)
    d = v.int_value("d", d, 0, H)
    e = v.int_value("e", e, 0, H)
    if s is not None:
        s = v.int_value("s", s, 1, H)  # checked when given, even where overflow="zeros" leaves it unused
    if overflow == "clip" and s is None:
        raise ValueError("s (execute horizon, 1 <= s <= H) is required when overflow='clip'")
    return _effective(H, d, e, s, OVERFLOWS.index(overflow))


def _effective(H, d, e, s, ocode):
    e_star = jnp.maximum(e, d)
    by_name = {
        "clip": lambda: jnp.maximum(d, jnp.minimum(e_star, H - s)),
        "zeros": lambda: e_star,
    }
    return v.select_by_code(ocode, [by_name[n] for n in OVERFLOWS])


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SoftWindow:
    """Soft RTC window ([W-7]) as a pytree: traced rule parameters, static names.

    Default ([W-7]): the paper's main rule and schedule, delay-scaled lam = 2, h_max = 5,
    linear, "rtc", "clip". Convert a reference window with :func:`from_reference`.
    """

    rule: EndpointRule = dataclasses.field(default_factory=lambda: delay_scaled(2.0, 5))
    schedule: str = dataclasses.field(metadata=dict(static=True), default="linear")
    parametrization: str = dataclasses.field(metadata=dict(static=True), default="rtc")
    overflow: str = dataclasses.field(metadata=dict(static=True), default="clip")

    def __post_init__(self):
        if not isinstance(self.rule, EndpointRule):
            raise ValueError(f"rule must be an EndpointRule, got {type(self.rule).__name__}")
        v.check_choice("schedule", self.schedule, SCHEDULES)
        v.check_choice("parametrization", self.parametrization, PARAMETRIZATIONS)
        v.check_choice("overflow", self.overflow, OVERFLOWS)


def from_reference(window) -> SoftWindow:
    """The JAX window of a reference :class:`softrtc.reference.weights.SoftWindow` ([W-7])."""
    if isinstance(window, SoftWindow):
        _ep.from_reference(window.rule)  # a rule built field by field is checked like a constructed one
        return window
    if not isinstance(window, _ref.SoftWindow):
        raise ValueError(f"window must be a SoftWindow, got {type(window).__name__}")
    return SoftWindow(_ep.from_reference(window.rule), window.schedule, window.parametrization,
                      window.overflow)


def check_window(H: int, window) -> SoftWindow:
    """Host-side check that a window fits the horizon: h_max (or h) <= H ([E-1]).

    Called by :func:`soft_weights` when the rule's parameters are concrete.
    """
    H = v.check_horizon(H)
    window = from_reference(window)
    bound = window.rule.bound()
    if bound is not None and not v.is_traced(bound) and int(bound) > H:
        raise ValueError(f"window endpoint bound (h_max or h) must be <= H={H}, got {int(bound)}")
    return window


def _codes(window):
    """(rule kind, schedule, parametrization, overflow) codes of a window."""
    return (_ep.RULES.index(window.rule.kind), SCHEDULES.index(window.schedule),
            PARAMETRIZATIONS.index(window.parametrization), OVERFLOWS.index(window.overflow))


def _check_s(H, window, s):
    if s is None:
        if window.overflow == "clip":
            raise ValueError("s (execute horizon, 1 <= s <= H) is required when overflow='clip'")
        return np.int32(H)  # unused by overflow="zeros"
    return v.int_value("s", s, 1, H)


def _soft(H, d, kind, lam, h_max, length, scode, pcode, ocode, s):
    e = _ep.endpoint_by_code(kind, lam, h_max, length, d)
    # The hard rule's endpoint is d itself; every other rule is bounded by h_max <= H.
    e = jnp.where(kind == _ep.RULES.index("hard"), jnp.minimum(e, H), e)
    e_star = _effective(H, d, e, s, ocode)
    return _prefix(H, d, e_star, scode, pcode)


@functools.partial(jax.jit, static_argnums=(0,))
def _soft_jit(H, d, kind, lam, h_max, length, scode, pcode, ocode, s):
    return _soft(H, d, kind, lam, h_max, length, scode, pcode, ocode, s)


def soft_weights(H: int, d, window=None, s=None) -> jax.Array:
    """Soft RTC weights for delay d ([W-7]): prefix_weights(H, d, e*, g, parametrization).

    ``d`` in [0, H], ``s`` in [1, H] and the window's rule parameters may be
    traced; one compilation per ``H`` serves every window. Traced values
    outside their ranges give undefined results; concrete ones are checked ([N-7]).

    >>> soft_weights(8, 3, SoftWindow(), s=4).round(3).tolist()
    [1.0, 1.0, 1.0, 0.5, 0.0, 0.0, 0.0, 0.0]
    """
    H = v.check_horizon(H)
    window = check_window(H, SoftWindow() if window is None else window)
    d = v.int_value("d", d, 0, H)
    return _soft_weights(H, d, window, _check_s(H, window, s))


def _soft_weights(H: int, d, window: SoftWindow, s) -> jax.Array:
    """:func:`soft_weights` of checked arguments (``d``, ``s`` int32)."""
    kind, scode, pcode, ocode = (np.int32(c) for c in _codes(window))
    r = window.rule
    return _soft_jit(H, d, kind, r.lam, r.h_max, r.length, scode, pcode, ocode, s)  # [W-7]


def hard_weights(H: int, d) -> jax.Array:
    """Hard RTC weights 1[j < d] ([W-8]); ``d`` in [0, H] may be traced."""
    H = v.check_horizon(H)
    return _hard(H, v.int_value("d", d, 0, H))


def _hard(H: int, d) -> jax.Array:
    return (jnp.arange(H) < d).astype(jnp.float32)  # [W-8] w_j = 1[j < d]


def weight_table(H: int, window=None, s=None) -> jax.Array:
    """Soft weights for every delay d = 0 .. H as a table [H + 1, H] ([W-7]).

    Index it with a traced delay (``table[d]``) inside a jitted sampler; the
    table itself depends only on the window and ``s``. One compilation per
    ``H`` serves every window and ``s``.
    """
    H = v.check_horizon(H)
    window = check_window(H, SoftWindow() if window is None else window)
    s = _check_s(H, window, s)
    kind, scode, pcode, ocode = (np.int32(c) for c in _codes(window))
    r = window.rule
    return _weight_table(H, kind, r.lam, r.h_max, r.length, scode, pcode, ocode, s)


@functools.partial(jax.jit, static_argnums=(0,))
def _weight_table(H, kind, lam, h_max, length, scode, pcode, ocode, s):
    return jax.vmap(lambda d: _soft(H, d, kind, lam, h_max, length, scode, pcode, ocode, s))(
        jnp.arange(H + 1, dtype=jnp.int32))


def check_weights(name: str, w, H: int) -> jax.Array:
    """A weight vector [..., H] with values in [0, 1] (range checked when concrete) ([W-1])."""
    H = v.check_horizon(H)
    w = v.array(name, w, lo=0.0, hi=1.0)
    if w.ndim < 1 or w.shape[-1] != H:
        raise ValueError(f"{name} must have shape [..., {H}], got {list(w.shape)}")
    return w
