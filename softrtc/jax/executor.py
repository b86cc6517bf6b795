"""Asynchronous chunk execution in JAX (spec chapter X, 04-execution.md); twin of ``softrtc.reference.executor``.

``H``, ``A``, the number of chunks ``C`` and the execute horizon ``s`` are
static (they fix output shapes); delays may be traced, so one compiled
function serves every delay sequence. Selection uses gathers and
``jnp.where`` instead of slices with traced bounds.

Traced delays are not range-checked: a delay outside [X-1]'s
``0 <= d <= min(s, H - s)`` gives undefined results (it is not clipped).
Check delays on the host with :func:`check_delay` / :func:`check_delays`;
concrete delays passed to these functions are checked automatically.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from . import _validate as v


def check_delay(H: int, s: int, d) -> int:
    """[X-1] A concrete delay is executable when 0 <= d <= min(s, H - s); returns it as int."""
    H = v.check_horizon(H)
    s = v.check_int("s", s, 1, H)
    return int(v.int_value("d", d, 0, min(s, H - s)))


def check_delays(H: int, s: int, delays) -> np.ndarray:
    """Host-side check of a delay sequence for :func:`execute_chunks` ([X-1], [X-2]): d_0 = 0."""
    H = v.check_horizon(H)
    s = v.check_int("s", s, 1, H)
    return _host_delays(H, s, delays)


def _host_delays(H: int, s: int, delays) -> np.ndarray:
    """:func:`check_delays` for checked ``H`` and ``s``: the caller's integers, before any cast to int32."""
    if isinstance(delays, (str, bytes)) or not (isinstance(delays, Sequence) or hasattr(delays, "__array__")):
        # A dict would be read by its keys and a set in hash order ([X-5]).
        raise ValueError(f"delays must be a non-empty 1-D integer array (or list, tuple), "
                         f"got {type(delays).__name__}")
    if isinstance(delays, Sequence):
        for i, d in enumerate(delays):
            # np.asarray would read a boolean among integers as 0 or 1 ([N-7]).
            if isinstance(d, (bool, np.bool_)):
                raise ValueError(f"delays[{i}] must be an integer in [0, {min(s, H - s)}], got {d!r}")
    ds = np.asarray(delays)
    if ds.ndim != 1 or ds.size < 1:
        raise ValueError(f"delays must be a non-empty 1-D integer array, got shape {list(ds.shape)}")
    v.int_array("delays", ds, lo=0, hi=min(s, H - s))
    if int(ds[0]) != 0:
        raise ValueError(f"delays[0] must be an integer in [0, 0] (first chunk, [X-2]), got {int(ds[0])}")
    return ds


def shift_prior(prev_chunk, s) -> jax.Array:
    """Y[j] = prev[j + s] for j < H - s, 0 for j >= H - s ([X-3]); prev [..., H, A], s may be traced."""
    prev = v.array("prev_chunk", prev_chunk)
    if prev.ndim < 2:
        raise ValueError(f"prev_chunk must have shape [..., H, A], got {list(prev.shape)}")
    H = prev.shape[-2]
    s = v.int_value("s", s, 1, H)
    return _shift(prev, s)


@jax.jit
def _shift(prev, s):
    # Checked by shift_prior(); jitted so an eager call is one dispatch, not one per op.
    H = prev.shape[-2]
    j = jnp.arange(H)
    src = jnp.take(prev, jnp.minimum(j + s, H - 1), axis=-2)
    return jnp.where((j < H - s)[:, None], src, 0.0)


def segment(prev_chunk, new_chunk, s: int, d) -> jax.Array:
    """prev[s : s + d] then new[d : s], shape [..., s, A] ([X-4]); ``s`` static, ``d`` traced or concrete.

    ``d`` is one delay, or one per chunk of a batch (shape ``prev_chunk.shape[:-2]``, e.g. per environment).
    """
    prev = v.array("prev_chunk", prev_chunk)
    if prev.ndim < 2:
        raise ValueError(f"prev_chunk must have shape [..., H, A], got {list(prev.shape)}")
    new = v.array("new_chunk", new_chunk, shape=prev.shape)
    H = prev.shape[-2]
    s = v.check_int("s", s, 1, H)
    if jnp.ndim(d) and prev.ndim > 2:  # one delay per chunk of the batch
        d = v.int_array("d", d, shape=prev.shape[:-2], lo=0, hi=min(s, H - s))
    else:
        d = v.int_value("d", d, 0, min(s, H - s))
    return _segment(prev, new, s, d)


def _sources(s: int, d) -> tuple[jax.Array, jax.Array]:
    """[X-4] the source of step i < s after a request with delay d: the previous chunk's token s + i when
    i < d, else the new chunk's token i. Returns ``(from_prev [..., s], token [..., s])``; d may be batched."""
    i = jnp.arange(s, dtype=jnp.int32)
    from_prev = i < jnp.asarray(d)[..., None]
    return from_prev, jnp.where(from_prev, s + i, i)


def _segment(prev, new, s: int, d):
    H = prev.shape[-2]
    from_prev, _ = _sources(s, d)
    # Tokens s + i >= H only occur for i >= H - s >= d, where the new chunk is used.
    old = jnp.take(prev, jnp.minimum(s + jnp.arange(s), H - 1), axis=-2)
    return jnp.where(from_prev[..., None], old, new[..., :s, :])


def segment_sources(H: int, s: int, d) -> tuple[np.ndarray, np.ndarray]:
    """Host-side sources of the ``s`` steps after a request with delay ``d`` ([X-4]).

    Returns ``(from_prev, token)``, each of shape ``[s]``: step i executes the
    previous chunk's token ``token[i]`` when ``from_prev[i]``, else the new
    chunk's token ``token[i]``. For executors that step an environment one
    action at a time.
    """
    d = check_delay(H, s, d)
    # The host twin of _sources: NumPy, because an eager JAX call per request costs more than the rule.
    i = np.arange(int(s), dtype=np.int32)
    from_prev = i < d
    return from_prev, np.where(from_prev, int(s) + i, i).astype(np.int32)


def execute_chunks(chunks, delays, s: int) -> dict:
    """Executed actions of C chunks with delays d_0 .. d_{C-1} ([X-2]..[X-5]).

    chunks [C, H, A]; delays [C] (traced or concrete, d_0 = 0 and [X-1]);
    ``s`` static. Returns ``actions [C*s, A]``, ``chunk_index`` and
    ``token_index [C*s]`` (int32). Step n = c s + i comes from chunk c - 1,
    token s + i when c >= 1 and i < d_c, else from chunk c, token i.
    """
    ch = v.array("chunks", chunks, ndim=3)
    C, H, _ = ch.shape
    if C < 1:
        raise ValueError("chunks must hold at least one chunk, got 0")
    s = v.check_int("s", s, 1, H)
    ds = _delays(H, s, delays)
    if ds.shape != (C,):
        raise ValueError(f"delays must have shape [{C}], got {list(ds.shape)}")
    c = jnp.arange(C, dtype=jnp.int32)
    # The first chunk never takes from a previous one ([X-2]), whatever d_0 holds.
    from_prev, token = _sources(s, jnp.where(c >= 1, ds, 0))
    ci = jnp.where(from_prev, c[:, None] - 1, c[:, None]).reshape(C * s)
    ti = token.reshape(C * s)
    return {"actions": ch[ci, ti], "chunk_index": ci, "token_index": ti}


def _delays(H: int, s: int, delays) -> jax.Array:
    """The delays of :func:`execute_chunks` and :func:`closed_loop` as int32, checked once: concrete ones
    on the host ([X-1], [X-2], [X-5]), traced ones for their dtype (their range is the caller's)."""
    if v.is_traced(delays):
        return v.int_array("delays", delays)
    return jnp.asarray(_host_delays(H, s, delays), jnp.int32)


def _callback_array(name: str, value, what: str):
    """What a caller's function returned, as an array of a real dtype ([N-7]); not cast yet."""
    v.real_dtype(name, value, f"return {what} of a real (integer or float) dtype")
    return value if isinstance(value, (jax.Array, np.ndarray)) or v.is_traced(value) else jnp.asarray(value)


def _generated(generate, H: int, args, A: int | None = None) -> jax.Array:
    """``generate(*args)`` checked: a real chunk [H, A] (A = the first chunk's), finite when concrete ([N-7])."""
    want = f"[H={H}, A]" if A is None else f"[H={H}, A={A}]"
    chunk = _callback_array("generate", generate(*args), f"a chunk of shape {want}")
    if chunk.ndim != 2 or chunk.shape[0] != H or chunk.shape[1] < 1 or (A is not None and chunk.shape[1] != A):
        raise ValueError(f"generate must return chunks of shape {want}, got {list(chunk.shape)}")
    if not v.is_traced(chunk) and not np.all(np.isfinite(np.asarray(chunk))):
        raise ValueError("generate must return finite chunks (no NaN or inf)")
    return jnp.asarray(chunk, jnp.float32)


def closed_loop(generate, env_step, env_state, obs0, delays, H: int, s: int):
    """Closed-loop execution with a functional environment ([X-2], [X-3], [X-4], [X-6]).

    * ``generate(obs, prior, d, c) -> chunk [H, A]``: called once with
      ``prior=None`` and ``d = 0`` for the first chunk (traced separately,
      [X-2]) and, inside a ``lax.scan``, with a prior [H, A] and traced d, c
      for requests c >= 1. Randomness comes from ``c`` (e.g. fold it into a key).
    * ``env_step(env_state, action) -> (env_state, obs)``: one control step.

    What the two functions return is checked while tracing ([N-7]): chunks of
    shape [H, A] with one A throughout, observations of ``obs0``'s shape, a
    state of ``env_state``'s structure and shapes, all of a real dtype (a
    complex chunk is an error, not reduced to its real part); a concrete first
    chunk must be finite. ``obs0`` is a real array with no empty axis.

    ``delays [C]`` may be traced (C static). Returns a dict with ``actions
    [C*s, A]``, ``chunks [C, H, A]``, ``priors [C, H, A]`` (zeros for c = 0),
    ``request_obs [C, ...]`` and the final ``env_state``.
    """
    if not callable(generate) or not callable(env_step):
        raise ValueError("generate and env_step must be callables")
    H = v.check_horizon(H)
    s = v.check_int("s", s, 1, H)
    ds = _delays(H, s, delays)
    if ds.ndim != 1 or ds.shape[0] < 1:
        raise ValueError(f"delays must have shape [C] with C >= 1, got {list(ds.shape)}")
    if v.is_traced(obs0):
        v.real_dtype("obs0", obs0)
    obs0 = v.array("obs0", obs0)
    try:
        state_spec = jax.tree.map(lambda a: (jnp.shape(a), jnp.result_type(a)), env_state)
    except TypeError as exc:
        raise ValueError(f"env_state must be a pytree of arrays, got {type(env_state).__name__}") from exc

    def checked_step(state, a):
        out = env_step(state, a)
        if not isinstance(out, (tuple, list)) or len(out) != 2:
            raise ValueError(f"env_step must return a pair (env_state, obs), got {type(out).__name__}")
        state, obs = out
        obs = _callback_array("env_step", obs, f"an observation of obs0's shape {list(obs0.shape)}")
        if tuple(obs.shape) != tuple(obs0.shape):
            raise ValueError(f"env_step must return observations of obs0's shape {list(obs0.shape)}, "
                             f"got {list(obs.shape)}")
        try:
            got = jax.tree.map(lambda x: (jnp.shape(x), jnp.result_type(x)), state)
        except TypeError:
            got = None
        if got is None or jax.tree.structure(got) != jax.tree.structure(state_spec) \
                or jax.tree.leaves(got) != jax.tree.leaves(state_spec):
            raise ValueError("env_step must return an env_state of the given env_state's tree structure, "
                             "shapes and dtypes")
        return state, obs

    def run_segment(state, seg):
        # A fresh step function per segment, as before the checks: the same program is traced.
        state, obs_seq = jax.lax.scan(lambda st, a: checked_step(st, a), state, seg)
        return state, obs_seq[-1]

    first = _generated(generate, H, (obs0, None, jnp.int32(0), jnp.int32(0)))
    A = first.shape[1]
    state, obs = run_segment(env_state, first[:s])

    def request(carry, inp):
        state, obs, prev = carry
        c, d = inp
        prior = _shift(prev, s)
        new = _generated(generate, H, (obs, prior, d, c), A)
        seg = _segment(prev, new, s, d)
        state2, obs2 = run_segment(state, seg)
        return (state2, obs2, new), (seg, new, prior, obs)

    C = ds.shape[0]
    cs = jnp.arange(1, C, dtype=jnp.int32)
    (state, _, _), (segs, news, priors, req_obs) = jax.lax.scan(request, (state, obs, first), (cs, ds[1:]))
    return {
        "actions": jnp.concatenate([first[None, :s], segs], axis=0).reshape(C * s, A),
        "chunks": jnp.concatenate([first[None], news], axis=0),
        "priors": jnp.concatenate([jnp.zeros_like(first)[None], priors], axis=0),
        "request_obs": jnp.concatenate([obs0[None], req_obs], axis=0),
        "env_state": state,
    }
