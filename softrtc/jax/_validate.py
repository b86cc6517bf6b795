"""Validation helpers of the JAX twin ([N-7]).

Static arguments (H, A, T, schedule names, ...) are always checked. Array and
scalar arguments are checked for shape at trace time and, when their values
are concrete (not JAX tracers), for range and finiteness too. Traced values
cannot be inspected inside ``jit``; the functions that accept them document
the valid range and provide host-side ``check_*`` helpers instead. Nothing is
clamped to make an out-of-range traced value valid.
"""

from __future__ import annotations

import numbers

import jax
import jax.numpy as jnp
import numpy as np

from softrtc.reference import _validate as _ref

check_choice = _ref.check_choice
check_int = _ref.check_int
check_real = _ref.check_real
check_horizon = _ref.check_horizon
check_bool = _ref.check_bool
MAX_HORIZON = _ref.MAX_HORIZON


def is_traced(value) -> bool:
    """True when ``value`` (or any leaf of it) is a JAX tracer, i.e. not concrete."""
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(value))


INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1


def int_value(name: str, value, lo: int | None = None, hi: int | None = None, *,
              dtype=jnp.int32) -> jax.Array | np.ndarray:
    """A scalar integer argument that may be traced ([N-7]); a concrete one comes back as a NumPy scalar array.

    Concrete values must be integers in ``[lo, hi]`` (Python ints, NumPy or JAX
    integer scalars; floats and booleans are rejected). Traced values must have
    an integer dtype and scalar shape; their range is the caller's duty.
    """
    if is_traced(value):
        if jnp.ndim(value) != 0 or not jnp.issubdtype(jnp.result_type(value), jnp.integer):
            raise ValueError(f"{name} must be a scalar integer, got {jnp.result_type(value)} "
                             f"of shape {jnp.shape(value)}")
        return jnp.asarray(value, dtype)
    if isinstance(value, (jax.Array, np.ndarray)):
        if value.ndim != 0 or not np.issubdtype(value.dtype, np.integer):
            raise ValueError(f"{name} must be a scalar integer{_ref._range(lo, hi)}, got {value!r}")
        value = int(value)
    # The value becomes int32: a bound the caller left open is int32's own, so nothing wraps.
    lo = INT32_MIN if lo is None else lo
    hi = INT32_MAX if hi is None else hi
    # A concrete value stays on the host (a NumPy scalar): jit and jnp take it as they take an array,
    # and no device buffer is made for each checked scalar.
    return np.asarray(check_int(name, value, lo, hi), dtype)


def real_value(name: str, value, lo: float | None = None, hi: float | None = None,
               lo_open: bool = False, hi_open: bool = False) -> jax.Array | np.ndarray:
    """A scalar real argument that may be traced; concrete values are range-checked and come back as a
    float32 NumPy scalar array ([N-7])."""
    if is_traced(value):
        if jnp.ndim(value) != 0:
            raise ValueError(f"{name} must be a scalar, got shape {jnp.shape(value)}")
        return jnp.asarray(value, jnp.float32)
    if isinstance(value, (jax.Array, np.ndarray)):
        if value.ndim != 0 or value.dtype == bool:
            raise ValueError(f"{name} must be a finite real scalar, got {value!r}")
        value = value.item()
    if not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be a finite real number, got {value!r}")
    with np.errstate(over="ignore"):  # beyond float32 becomes inf, rejected below (NumPy: no tracer under jit)
        f32 = np.float32(check_real(name, value, lo, hi, lo_open, hi_open))
    if not np.isfinite(f32):
        raise ValueError(f"{name} must be a finite real number within float32 range, got {value!r}")
    return np.asarray(f32)


def real_dtype(name: str, value, what: str = "be a real numeric array (integer or float)"):
    """The dtype of an array argument, concrete or traced, if it is real: integer or float ([N-7]).

    Booleans, complex numbers, strings, None and objects without a dtype are
    rejected. Only the dtype is read, so this costs nothing inside ``jit``.
    """
    if value is None or isinstance(value, (str, bytes)):
        raise ValueError(f"{name} must {what}, got {type(value).__name__}")
    try:
        dt = jnp.result_type(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must {what}, got {type(value).__name__}") from exc
    if not (jnp.issubdtype(dt, jnp.integer) or jnp.issubdtype(dt, jnp.floating)):
        raise ValueError(f"{name} must {what}, got dtype {dt}")
    return dt


def array(name: str, value, shape: tuple | None = None, ndim: int | None = None,
          lo: float | None = None, hi: float | None = None, dtype=jnp.float32,
          allow_empty: bool = False, hi_open: bool = False) -> jax.Array:
    """A float array argument ([N-7], [N-8]).

    ``shape`` may contain ``None`` for a free dimension. The shape is checked
    always (an axis of length 0 is rejected unless ``allow_empty``, [N-1]);
    finiteness and the range ``[lo, hi]`` (``[lo, hi)`` with ``hi_open``)
    only when the value is concrete. The range is checked on the caller's
    values before they are rounded to ``dtype``: rounding must neither pull
    an out-of-range 1.000000001 into [0, 1] nor push a valid 1 - 1e-12 onto
    an open bound.
    """
    raw = None
    if not is_traced(value):
        if isinstance(value, (bool, np.bool_)) or (hasattr(value, "dtype") and value.dtype == bool):
            raise ValueError(f"{name} must be a numeric array, got a boolean")
        try:
            kind = np.asarray(value).dtype.kind
        except (TypeError, ValueError, OverflowError) as exc:
            raise ValueError(f"{name} must be a numeric array, got a ragged or non-numeric "
                             f"{type(value).__name__}") from exc
        if kind not in "iuf":  # booleans, complex numbers, strings and objects are not real arrays
            raise ValueError(f"{name} must be a real numeric array, got dtype {np.asarray(value).dtype}")
        raw = np.asarray(value)
        try:
            with np.errstate(over="ignore"):  # a value beyond float32 becomes inf, rejected below
                value = jnp.asarray(value, dtype)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{name} must be a numeric array, got {type(value).__name__}") from exc
    else:
        real_dtype(name, value)  # [N-10] a traced array is checked for shape and dtype
        value = jnp.asarray(value, dtype)
    if ndim is not None and value.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimensions, got shape {list(value.shape)}")
    _check_shape(name, value, shape)
    if not allow_empty and 0 in value.shape:
        raise ValueError(f"{name} must have at least one entry along every axis, got shape {list(value.shape)}")
    if raw is not None and value.size:
        with np.errstate(over="ignore"):  # NumPy's rounding, as value may be a tracer inside a jit
            rounded = raw.astype(np.dtype(dtype))
        if not (np.all(np.isfinite(raw)) and np.all(np.isfinite(rounded))):
            raise ValueError(f"{name} must contain only finite values (no NaN or inf, none beyond float32 range)")
        where = f"[{lo}, {hi}{')' if hi_open else ']'}"
        if lo is not None and raw.min() < lo:
            raise ValueError(f"{name} values must lie in {where}, got min {raw.min().item()!r}")
        if hi is not None and (raw.max() >= hi if hi_open else raw.max() > hi):
            raise ValueError(f"{name} values must lie in {where}, got max {raw.max().item()!r}")
    return value


def int_array(name: str, value, shape: tuple | None = None, lo: int | None = None,
              hi: int | None = None) -> jax.Array:
    """An integer array argument (e.g. per-example delays); range-checked when concrete ([N-7])."""
    if not is_traced(value):
        if _holds_bool(value):  # np.asarray would read True among integers as 1
            raise ValueError(f"{name} must be an integer array, got a boolean entry")
        try:
            v = np.asarray(value)
        except (TypeError, ValueError, OverflowError) as exc:
            raise ValueError(f"{name} must be an integer array, got a ragged or non-numeric "
                             f"{type(value).__name__}") from exc
        if v.dtype == bool or not np.issubdtype(v.dtype, np.integer):
            raise ValueError(f"{name} must be an integer array, got dtype {v.dtype}")
        # The values become int32: open bounds are int32's own, so nothing wraps.
        lo = INT32_MIN if lo is None else lo
        hi = INT32_MAX if hi is None else hi
        if v.size and (v.min() < lo or v.max() > hi):
            raise ValueError(f"{name} entries must be integers{_ref._range(lo, hi)}, "
                             f"got range [{v.min()}, {v.max()}]")
    elif not jnp.issubdtype(jnp.result_type(value), jnp.integer):
        raise ValueError(f"{name} must be an integer array, got dtype {jnp.result_type(value)}")
    value = jnp.asarray(value, jnp.int32)
    _check_shape(name, value, shape)
    return value


def _check_shape(name: str, value, shape: tuple | None) -> None:
    """``value``'s shape is ``shape`` (``None`` entries free; no check for ``shape`` None) ([N-7])."""
    if shape is not None:
        if value.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, value.shape)):
            want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
            raise ValueError(f"{name} must have shape {want}, got {list(value.shape)}")


def _holds_bool(value) -> bool:
    """Whether a (nested) list or tuple holds a Python or NumPy boolean."""
    if isinstance(value, (bool, np.bool_)):
        return True
    return isinstance(value, (list, tuple)) and any(_holds_bool(x) for x in value)


def select_by_code(code, branches):
    """``branches[code]()`` for a Python int code; for a traced code, every branch selected by value.

    Lets one compiled function serve every named variant (schedule,
    parametrization, rule kind) when the name is passed as a traced integer
    code, while a static name still evaluates only its own branch.
    """
    if isinstance(code, (int, np.integer)) and not isinstance(code, bool):
        return branches[int(code)]()
    values = [b() for b in branches]
    out = values[-1]
    for i in range(len(values) - 2, -1, -1):
        out = jnp.where(code == i, values[i], out)
    return out


# --------------------------------------------------------------------------- policy inputs ([P-15])
# Shapes and dtypes are checked while tracing; values only of concrete arrays.


def float_input(name: str, value, *, allow_int: bool = False) -> jax.Array:
    """``value`` as a JAX array of a floating dtype (integer too with ``allow_int``, cast to float32) ([P-15])."""
    if is_traced(value):
        arr = value
    else:
        try:
            arr = jnp.asarray(value)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{name} must be a real array, got {type(value).__name__}") from exc
    dt = arr.dtype
    ok = jnp.issubdtype(dt, jnp.floating) or (allow_int and jnp.issubdtype(dt, jnp.integer))
    if dt == jnp.bool_ or not ok:
        allowed = "a real (integer or floating)" if allow_int else "a floating"
        raise ValueError(f"{name} must have {allowed} dtype, got {dt}")
    if jnp.issubdtype(dt, jnp.integer):
        arr = arr.astype(jnp.float32)
    return arr


def check_finite(name: str, arr) -> None:
    """A concrete ``arr`` holds only finite values ([P-15]); a traced one is not inspected."""
    # NumPy, not jnp: inside a jit trace even a concrete array would turn into a tracer.
    if not is_traced(arr) and not np.all(np.isfinite(np.asarray(arr))):
        raise ValueError(f"{name} must contain only finite values (no NaN or inf)")


def finite_result(name: str, result, what: str):
    """``result`` unchanged; a concrete one with a non-finite entry is a ValueError naming the input ``name``.

    [N-15]: the inputs were checked finite, so a non-finite result is an overflow of the array's float type.
    A traced result is not inspected (a compiled call cannot raise; IEEE inf and NaN propagate there).
    """
    if not any(is_traced(r) for r in jax.tree_util.tree_leaves(result)):
        host = [np.asarray(r) for r in jax.tree_util.tree_leaves(result)]
        if not all(np.all(np.isfinite(h)) for h in host):
            dtype = host[0].dtype
            raise ValueError(f"{name} is too large in magnitude: {what} overflows {dtype}; a finite result "
                             f"needs smaller values ([N-15])")
    return result


def check_nonempty(name: str, arr) -> None:
    """[N-12] ``arr`` has no empty axis; a shape check, free under jit."""
    if 0 in tuple(arr.shape):
        raise ValueError(f"{name} must have at least one entry along every axis, got shape {tuple(arr.shape)}")


def check_unit_interval(name: str, arr) -> None:
    """A concrete flow time ``arr`` lies in [0, 1] and is finite ([P-15])."""
    if is_traced(arr):
        return
    check_finite(name, arr)
    a = np.asarray(arr)
    if a.size and (np.any(a < 0.0) or np.any(a > 1.0)):
        raise ValueError(f"{name} must lie in [0, 1] (flow time, 0 = noise, 1 = data)")
