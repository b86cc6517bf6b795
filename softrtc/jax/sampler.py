"""Euler samplers in JAX: naive and training-time RTC (spec chapter S, 03-inference.md).

Twin of ``softrtc.reference.sampler``. Samplers act on a **batch**:

* ``obs [B, O]``, ``noise [B, H, A]`` (x^0 = eps), ``prior [B, H, A]``;
* ``weights [H]`` (shared by the batch) or ``[B, H]`` (per example, e.g. one
  delay per example);
* ``velocity_fn(obs [B, O], x [B, H, A], t [B, H]) -> v [B, H, A]``, batched
  like the flow policy (``policy.__call__``) or the JAX reference field
  (:class:`softrtc.jax.velocity.ReferenceVelocityField`). For one example,
  add a batch dim of 1.

Two paths compute the same chunks:

* straightforward (``naive_sample``, ``rtc_sample``): calls ``velocity_fn``
  with per-token times; this is the check;
* conditioned (``naive_sample_conditioned``, ``rtc_sample_conditioned``): for a
  ``model`` with ``time_conditioning(t)`` and ``apply_conditioned(obs, x,
  cond)`` (the flow policy, or the reference field). The blended times
  t~^k = w + (1 - w) t_k depend on the weights only ([S-3]), never on obs or
  state, so the time conditioning of all T steps is computed once, as one
  table ``model.time_conditioning(t~ [T, b, H])``, instead of once per step
  and batch element. A per-delay table (:func:`conditioning_table`) goes
  further: it is built once for every d = 0 .. H and indexed by a traced d.

Both training-time samplers take ``step`` ([S-10]): ``"algorithm1"`` (the
paper's, default) or ``"consistent"`` (window tokens blended once and moved by
(1 - w) v / T); for weights in {0, 1} the two are bitwise equal ([S-11]).

The loop over the static T is unrolled by default (faster on CPU for the
small T of RTC, e.g. T = 5); ``unroll=False`` uses ``lax.fori_loop``, whose
compile time does not grow with T.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from softrtc.reference.sampler import STEPS, check_step  # noqa: F401  ([S-10], re-exported)

from . import _validate as v

MAX_STEPS = 1 << 16


def euler_times(num_steps: int) -> jax.Array:
    """t_k = k / T, k = 0 .. T-1, float32 ([S-1])."""
    return _times(v.check_int("num_steps", num_steps, 1, MAX_STEPS))


def _times(T: int) -> jax.Array:
    """[S-1] t_k = k / T for a checked T."""
    return jnp.arange(T, dtype=jnp.float32) / T


def blend(x, prior, weights) -> jax.Array:
    """x~ = w Y + (1 - w) x token-wise ([S-3]); x, prior [..., H, A], weights [H] (shared) or [..., H].

    Other weight shapes are rejected rather than broadcast ([N-7]).
    """
    x = v.array("x", x)
    if x.ndim < 2:
        raise ValueError(f"x must have shape [..., H, A], got {list(x.shape)}")
    y = v.array("prior", prior, shape=x.shape)
    w = v.array("weights", weights, lo=0.0, hi=1.0)
    if w.shape not in (x.shape[-2:-1], x.shape[:-1]):
        raise ValueError(f"weights must have shape [{x.shape[-2]}] or {list(x.shape[:-1])}, got {list(w.shape)}")
    w = w[..., None]
    return w * y + (1.0 - w) * x


def blend_time(t, weights) -> jax.Array:
    """t~_j = w_j + (1 - w_j) t ([S-3]); t a scalar or broadcastable to weights' leading dims."""
    w = v.array("weights", weights, lo=0.0, hi=1.0)
    if w.ndim < 1:
        raise ValueError("weights must have shape [..., H] (at least one axis), got a scalar")
    t = v.array("t", t, lo=0.0, hi=1.0)
    if t.ndim and t.shape != w.shape[:-1]:
        raise ValueError(f"t must be a scalar or have the batch shape of weights {list(w.shape[:-1])}, "
                         f"got {list(t.shape)}")
    return w + (1.0 - w) * t[..., None] if t.ndim else w + (1.0 - w) * t


def check_batch(obs, noise, prior=None, weights=None, num_steps=None, model=None):
    """Validate sampler inputs ([N-7]); returns (obs, noise, prior, weights, T) as float32 arrays.

    With ``model`` (the velocity function or conditioned model), ``noise`` and
    ``obs`` are also checked against the sizes it declares (``horizon`` or
    ``action_chunk_size``, ``action_dim``, ``obs_dim``), so that a mismatch
    names the sampler's argument rather than the model's internal ``x``.
    """
    x = v.array("noise", noise, ndim=3)
    B, H, _ = x.shape
    if B < 1:
        raise ValueError("noise must have batch size B >= 1, got 0")
    obs = v.array("obs", obs, ndim=2)
    if obs.shape[0] != B:
        raise ValueError(f"obs must have shape [B={B}, O], got {list(obs.shape)}")
    if model is not None:
        mH, mA, mO = model_horizon(model), _declared(model, "action_dim"), _declared(model, "obs_dim")
        if (mH is not None and H != mH) or (mA is not None and x.shape[2] != mA):
            raise ValueError(f"noise must have the model's shape [B, H={'*' if mH is None else mH}, "
                             f"A={'*' if mA is None else mA}], got {list(x.shape)}")
        if mO is not None and obs.shape[1] != mO:
            raise ValueError(f"obs must have the model's shape [B, O={mO}], got {list(obs.shape)}")
    y = None if prior is None else v.array("prior", prior, shape=x.shape)
    w = None
    if weights is not None:
        w = v.array("weights", weights, lo=0.0, hi=1.0)
        if w.shape not in ((H,), (B, H)):
            raise ValueError(f"weights must have shape [H={H}] or [B={B}, H={H}], got {list(w.shape)}")
    T = None if num_steps is None else v.check_int("num_steps", num_steps, 1, MAX_STEPS)
    return obs, x, y, w, T


def require(name: str, value, what: str):
    """An argument the function needs: None is a ValueError naming it, not a TypeError later ([N-7])."""
    if value is None:
        raise ValueError(f"{name} must be {what}, got None")
    return value


def check_unroll(unroll) -> bool:
    """The samplers' ``unroll`` flag: True or False, no truthy stand-ins ([N-7])."""
    return v.check_bool("unroll", unroll)


def _declared(model, attr: str) -> int | None:
    """An integer size attribute of ``model``, or None where it declares none."""
    value = getattr(model, attr, None)
    return int(value) if isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_)) else None


def model_horizon(model) -> int | None:
    """The chunk length H of a conditioned ``model``: its ``horizon`` (the reference field) or
    ``action_chunk_size`` (the flow policy); None when it declares neither."""
    for attr in ("horizon", "action_chunk_size"):
        H = _declared(model, attr)
        if H is not None:
            return H
    return None


def _check_fn(name, fn):
    if not callable(fn):
        raise ValueError(f"{name} must be callable as {name}(obs [B, O], x [B, H, A], t [B, H]) -> v [B, H, A]")


def _check_model(model):
    if not (callable(getattr(model, "time_conditioning", None))
            and callable(getattr(model, "apply_conditioned", None))):
        raise ValueError("model must provide time_conditioning(t) and apply_conditioned(obs, x, cond)")


def _check_model_h(name: str, w, model) -> None:
    """Weights [..., H] must have the model's H as their last axis: a last axis of 1 would be read by
    ``time_conditioning`` as one time shared by all tokens ([S-3], [N-7])."""
    H = model_horizon(model)
    if H is not None and w.shape[-1] != H:
        raise ValueError(f"{name} must have shape [..., H] with the model's H={H} as last axis, "
                         f"got {list(w.shape)}")


def _stepper(wb, T: int, step: str):
    """The training-time step for weights ``wb`` [B, H] ([S-4], [S-10]): ``advance(k, x, y, v_of) -> x^{k+1}``
    with ``v_of(xb)`` the field at the blended state. ``step`` and T are static, the weights may be traced."""
    wx = wb[..., None]
    if step == "algorithm1":
        def advance(k, x, y, v_of):
            xb = wx * y + (1.0 - wx) * x  # [S-3]
            return xb + v_of(xb) / T  # [S-4]
        return advance
    c = jnp.where(wx < 1.0, 1.0 - wx, 1.0)  # [S-10] c = 1 - w; [S-11] c = 1 at w = 1
    again = (wx == 0.0) | (wx == 1.0)  # [S-10] window tokens are blended at k = 0 only

    def advance(k, x, y, v_of):
        xb = wx * y + (1.0 - wx) * x  # [S-3]
        xb = jnp.where(jnp.logical_or(k == 0, again), xb, x)
        return xb + (c * v_of(xb)) / T  # [S-10]; c = 1 gives v / T bit for bit ([S-11])
    return advance


def _loop(step, x, T, unroll):
    """x <- step(k, x) for k = 0 .. T-1; Python-unrolled or a fori_loop."""
    if unroll:
        for k in range(T):
            x = step(k, x)
        return x
    return jax.lax.fori_loop(0, T, step, x)


def _runtime(*arrays):
    """Hide values from XLA's constant folding.

    Times and weights are usually compile-time constants; XLA then folds or
    rewrites the ops that consume them (e.g. a dot with a broadcast operand),
    with a different rounding than the same ops on runtime values. Passing
    them through an optimization barrier makes every sampler evaluate the
    velocity field on runtime arrays, so that the bitwise identities [S-7]
    and [G-6] hold between separately compiled samplers.
    """
    return jax.lax.optimization_barrier(arrays)


def _at(tree, k):
    return jax.tree_util.tree_map(lambda a: a[k], tree)


def check_tree(name: str, tree, min_ndim: int = 1) -> list:
    """A conditioning tree: a non-empty tree of real arrays with at least ``min_ndim`` axes ([N-7]).

    Returns its leaves. Only shapes and dtypes are read (traced leaves included).
    """
    leaves = jax.tree_util.tree_leaves(tree)
    if not leaves:
        raise ValueError(f"{name} must be a conditioning tree of arrays, got {type(tree).__name__}")
    for leaf in leaves:
        if not hasattr(leaf, "shape") or not hasattr(leaf, "dtype"):
            raise ValueError(f"{name} must be a conditioning tree of arrays, got a leaf of type "
                             f"{type(leaf).__name__}")
        v.real_dtype(name, leaf, "be a conditioning tree of real arrays")
        if leaf.ndim < min_ndim:
            raise ValueError(f"{name} must be a conditioning tree of arrays with at least {min_ndim} axes, "
                             f"got a leaf of shape {list(leaf.shape)}")
    return leaves


def check_leading(name: str, tree, lead: tuple) -> None:
    """Every leaf of a conditioning tree starts with the axes ``lead`` (e.g. (T,) or (D, T)) ([N-7]).

    A table built for another number of steps or delays would otherwise be
    indexed out of range, which JAX clamps instead of raising.
    """
    leaves = check_tree(name, tree)
    for leaf in leaves:
        if tuple(jnp.shape(leaf)[:len(lead)]) != tuple(lead):
            raise ValueError(f"{name} must have leading axes {list(lead)} (built for these steps/delays), "
                             f"got a leaf of shape {list(jnp.shape(leaf))}")


def field_output(name: str, value, x) -> jax.Array:
    """A velocity returned by ``name`` must be a real array of the state's shape ([N-7]).

    Checked at trace time (shapes and dtypes are static, so it costs nothing
    per call); XLA would otherwise broadcast a [A] or [B, H, 1] velocity
    silently, and promote the state to complex. Values cannot be checked
    inside a compiled call; the reference also rejects NaN.
    """
    v.real_dtype(name, value, "return a real numeric array (integer or float)")
    if tuple(jnp.shape(value)) != tuple(x.shape):
        raise ValueError(f"{name} must return an array of the state's shape {list(x.shape)}, "
                         f"got {list(jnp.shape(value))}")
    return value


# ----------------------------------------------------------------------- straightforward path


def naive_sample(velocity_fn, obs, noise, num_steps: int, *, unroll: bool = True) -> jax.Array:
    """Naive Euler sampler ([S-1], [S-2]): x += v(obs, x, t_k 1) / T; returns x^T [B, H, A]."""
    _check_fn("velocity_fn", velocity_fn)
    obs, x, _, _, T = check_batch(obs, noise, num_steps=num_steps, model=velocity_fn)
    return _naive(velocity_fn, obs, x, T, check_unroll(unroll))


def _naive(velocity_fn, obs, x, T: int, unroll: bool) -> jax.Array:
    """[S-1], [S-2] x += v(obs, x, t_k 1) / T on checked arguments (``x`` the noise)."""
    # t_k 1 is computed as the blended time of zero weights, 0 + (1 - 0) t_k (exactly t_k),
    # so that the RTC sampler with w = 0 runs the same arithmetic ([S-7]).
    times, w0 = _runtime(_times(T), jnp.zeros(x.shape[:2], jnp.float32))

    def step(k, x):
        return x + field_output("velocity_fn", velocity_fn(obs, x, w0 + (1.0 - w0) * times[k]), x) / T

    return _loop(step, x, T, unroll)


def rtc_sample(velocity_fn, obs, noise, prior, weights, num_steps: int, *, unroll: bool = True,
               step: str = "algorithm1") -> jax.Array:
    """Training-time RTC sampler ([S-3], [S-4], [S-5]); returns x^T without a final blend.

    ``step``: "algorithm1" (the paper's, default) or "consistent" ([S-10]).
    With w = 0 (e.g. d = 0) it is bitwise :func:`naive_sample` under either step ([S-7], [S-11]).
    """
    step = check_step(step)
    _check_fn("velocity_fn", velocity_fn)
    require("prior", prior, "an array [B, H, A] (the previous chunk in this chunk's frame, [X-3])")
    require("weights", weights, "an array [H] or [B, H] in [0, 1]")
    obs, x, y, w, T = check_batch(obs, noise, prior, weights, num_steps, model=velocity_fn)
    return _rtc(velocity_fn, obs, x, y, w, T, check_unroll(unroll), step)


def _rtc(velocity_fn, obs, x, y, w, T: int, unroll: bool, step: str = "algorithm1") -> jax.Array:
    """[S-3], [S-4] ([S-10] for ``step`` "consistent") Euler steps from the blend x~ = w y + (1 - w) x at
    times t~ = w + (1 - w) t_k, on checked arguments (``x`` the noise, ``y`` the prior, ``w`` weights [H]
    or [B, H], ``step`` a checked name)."""
    times, wb = _runtime(_times(T), jnp.broadcast_to(w, x.shape[:2]))
    advance = _stepper(wb, T, step)

    def body(k, x):
        tb = wb + (1.0 - wb) * times[k]
        return advance(k, x, y, lambda xb: field_output("velocity_fn", velocity_fn(obs, xb, tb), x))

    return _loop(body, x, T, unroll)


# ----------------------------------------------------------------------- conditioned fast path


def rtc_time_table(weights, num_steps: int) -> jax.Array:
    """Blended times t~^k = w + (1 - w) t_k for all steps ([S-3]): weights [..., H] -> [T, ..., H]."""
    w = v.array("weights", weights, lo=0.0, hi=1.0)
    if w.ndim < 1:
        raise ValueError("weights must have shape [..., H] (at least one axis), got a scalar")
    return _time_table(w, v.check_int("num_steps", num_steps, 1, MAX_STEPS))


def _time_table(w, T: int) -> jax.Array:
    """[S-3] t~^k = w + (1 - w) t_k, [T, ..., H], for checked weights and T."""
    t = _times(T).reshape((-1,) + (1,) * w.ndim)
    return w + (1.0 - w) * t


def naive_conditioning(model, num_steps: int):
    """Time conditioning of the naive sampler: ``model.time_conditioning(t_k)`` for t [T, 1, 1] ([S-2])."""
    _check_model(model)
    return _naive_cond(model, v.check_int("num_steps", num_steps, 1, MAX_STEPS))


def _naive_cond(model, T: int):
    """[S-2] ``model.time_conditioning(t_k)``, t [T, 1, 1], for a checked model and T."""
    return model.time_conditioning(_times(T)[:, None, None])


def rtc_conditioning(model, weights, num_steps: int):
    """Time conditioning of every RTC step, ``model.time_conditioning(t~ [T, b, H])`` ([S-3]).

    ``weights [H]`` gives b = 1 (shared by the batch), ``[B, H]`` gives b = B. The last axis
    must be the model's H (``model.horizon`` or ``model.action_chunk_size`` where the model
    declares one): ``time_conditioning`` would read a last axis of 1 as one shared time.
    """
    _check_model(model)
    w = v.array("weights", weights, lo=0.0, hi=1.0)
    if w.ndim not in (1, 2):
        raise ValueError(f"weights must have shape [H] or [B, H], got {list(w.shape)}")
    _check_model_h("weights", w, model)
    return _rtc_cond(model, w, v.check_int("num_steps", num_steps, 1, MAX_STEPS))


def _rtc_cond(model, w, T: int):
    """[S-3] ``model.time_conditioning(t~ [T, b, H])`` for checked weights [H] (b = 1) or [B, H] and T."""
    return model.time_conditioning(_time_table(w[None] if w.ndim == 1 else w, T))


def conditioning_table(model, weight_table, num_steps: int):
    """Per-delay conditioning table: leaves [D, T, 1, ...] for a weight table [D, H] ([S-3], [W-7]).

    Build it once (e.g. from ``weights.weight_table`` or ``methods.method_weight_table``)
    and pick a delay with :func:`select_conditioning`; it depends on the model's
    parameters and the weights only. The table's last axis must be the model's H
    (as for :func:`rtc_conditioning`).
    """
    _check_model(model)
    wt = v.array("weight_table", weight_table, ndim=2, lo=0.0, hi=1.0)
    _check_model_h("weight_table", wt, model)
    return _cond_table(model, wt, v.check_int("num_steps", num_steps, 1, MAX_STEPS))


def _cond_table(model, wt, T: int):
    """[S-3] the per-delay conditioning table [D, T, 1, ...] of a checked weight table [D, H] and T."""
    # _time_table puts the step axis first: [T, D, 1, H] -> [D, T, 1, H].
    return model.time_conditioning(jnp.swapaxes(_time_table(wt[:, None, :], T), 0, 1))


def select_conditioning(table, d):
    """Rows of a :func:`conditioning_table` for delay ``d``: a scalar gives leaves [T, 1, ...],
    per-example delays [B] give [T, B, ...]. Traced ``d`` must lie in [0, D-1]."""
    if not jax.tree_util.tree_leaves(table):
        raise ValueError(f"table must be a conditioning_table (a tree of [D, T, ...] arrays), got {table!r}")
    leaves = check_tree("table", table, min_ndim=2)
    D = int(leaves[0].shape[0])
    check_leading("table", table, (D,))
    if d is None or isinstance(d, str) or jnp.ndim(d) > 1:
        raise ValueError(f"d must be an integer scalar or a non-empty vector [B], got {d!r}")
    d = v.int_value("d", d, 0, D - 1) if jnp.ndim(d) == 0 else v.int_array("d", d, shape=(None,), lo=0, hi=D - 1)
    if d.ndim and d.shape[0] == 0:
        raise ValueError("d must be an integer scalar or a non-empty vector [B], got an empty vector ([N-12])")
    return _select(table, d)


def _select(table, d):
    """Rows of a checked per-delay table for a checked delay: scalar d -> [T, 1, ...], d [B] -> [T, B, ...]."""
    if jnp.ndim(d) == 0:
        return _at(table, d)
    return jax.tree_util.tree_map(lambda a: jnp.moveaxis(a[d][:, :, 0], 0, 1), table)


def naive_sample_conditioned(model, obs, noise, num_steps: int, *, cond=None,
                             unroll: bool = True) -> jax.Array:
    """:func:`naive_sample` through ``model.apply_conditioned`` ([S-2]).

    ``cond`` (optional) is :func:`naive_conditioning`; computed here if omitted.
    """
    _check_model(model)
    obs, x, _, _, T = check_batch(obs, noise, num_steps=num_steps, model=model)
    unroll = check_unroll(unroll)
    if cond is not None:
        check_leading("cond", cond, (T,))
    return _naive_conditioned(model, obs, x, T, cond, unroll)


def _naive_conditioned(model, obs, x, T: int, cond, unroll: bool) -> jax.Array:
    """[S-2] the naive sampler through ``model.apply_conditioned`` on checked arguments; ``cond`` a checked
    naive conditioning [T, ...], or None to compute it here."""
    cond = _naive_cond(model, T) if cond is None else cond

    def step(k, x):
        return x + field_output("model.apply_conditioned", model.apply_conditioned(obs, x, _at(cond, k)), x) / T

    return _loop(step, x, T, unroll)


def rtc_sample_conditioned(model, obs, noise, prior, weights, num_steps: int, *, cond=None,
                           unroll: bool = True, step: str = "algorithm1") -> jax.Array:
    """:func:`rtc_sample` through ``model.apply_conditioned`` ([S-3]..[S-5]; ``step`` [S-10]).

    ``cond`` (optional) is the conditioning of these weights' blended times:
    :func:`rtc_conditioning` or a :func:`select_conditioning` row of a
    per-delay table; computed here from ``weights`` if omitted. The caller
    guarantees that ``cond`` belongs to ``weights``.
    """
    _check_model(model)
    step = check_step(step)
    require("prior", prior, "an array [B, H, A] (the previous chunk in this chunk's frame, [X-3])")
    require("weights", weights, "an array [H] or [B, H] in [0, 1]")
    obs, x, y, w, T = check_batch(obs, noise, prior, weights, num_steps, model=model)
    unroll = check_unroll(unroll)
    if cond is not None:
        check_leading("cond", cond, (T,))
    return _rtc_conditioned(model, obs, x, y, w, T, cond, unroll, step)


def _rtc_conditioned(model, obs, x, y, w, T: int, cond, unroll: bool, step: str = "algorithm1") -> jax.Array:
    """[S-3]..[S-5] ([S-10] for ``step`` "consistent") the RTC sampler through ``model.apply_conditioned`` on
    checked arguments; ``cond`` the checked conditioning of ``w``'s blended times [T, ...], or None to
    compute it here."""
    cond = _rtc_cond(model, w, T) if cond is None else cond
    advance = _stepper(jnp.broadcast_to(w, x.shape[:2]), T, step)

    def body(k, x):
        return advance(k, x, y, lambda xb: field_output("model.apply_conditioned",
                                                        model.apply_conditioned(obs, xb, _at(cond, k)), x))

    return _loop(body, x, T, unroll)
