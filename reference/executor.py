"""Asynchronous chunk execution with a simulated delay (spec chapter X, 04-execution.md).

Chunk c is requested at step c*s with the observation of that step. Its
inference takes d_c steps, during which the previous chunk keeps running: the
segment of steps [c*s, c*s + s) executes

    prev[s : s + d_c]   then   new[d_c : s]                             [X-4]

The first chunk (c = 0) is generated with d_0 = 0 and no prior ([X-2]). The
prior of request c >= 1 is the previous chunk shifted by s into the new chunk's
frame, zero-padded past the overlap ([X-3]):

    >>> import numpy as np
    >>> shift_prior(np.arange(6.0)[:, None], 4)[:, 0].tolist()
    [4.0, 5.0, 0.0, 0.0, 0.0, 0.0]
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ._validate import check_array, check_horizon, check_int


def check_delay(H: int, s: int, d: int) -> int:
    """[X-1] A delay is executable when 0 <= d <= min(s, H - s)."""
    H = check_horizon(H)
    s = check_int("s", s, 1, H)
    return check_int("d", d, 0, min(s, H - s))


def _delays(delays, C: int, H: int, s: int) -> list:
    """The delays of C chunks: delays[0] = 0 ([X-2]), every later one executable ([X-1], [X-5])."""
    # An ordered sequence only: a dict would be read by its keys and a set in hash order ([N-7]).
    if hasattr(delays, "__array__") and not isinstance(delays, (str, bytes)):  # NumPy (or other) arrays
        if np.ndim(delays) != 1:
            raise ValueError(f"delays must be a sequence of {C} integers (one per chunk), got an array of shape "
                             f"{list(np.shape(delays))}")
    elif isinstance(delays, (str, bytes)) or not isinstance(delays, Sequence):
        raise ValueError(f"delays must be a sequence of {C} integers (one per chunk; a list, tuple or 1-D array), "
                         f"got {type(delays).__name__}")
    ds = list(delays)
    if len(ds) != C:
        raise ValueError(f"delays must have one entry per chunk ({C}), got {len(ds)}")
    out = [check_int("delays[0]", ds[0], 0, 0)]
    for c in range(1, C):
        out.append(check_int(f"delays[{c}]", ds[c], 0, min(s, H - s)))
    return out


def shift_prior(prev_chunk, s: int) -> np.ndarray:
    """Prior Y[j] = prev[j + s] for j < H - s, 0 for j >= H - s ([X-3])."""
    prev = check_array("prev_chunk", prev_chunk, ndim=2)
    return _shift(prev, check_int("s", s, 1, prev.shape[0]))


def _shift(prev: np.ndarray, s: int) -> np.ndarray:
    y = np.zeros_like(prev)  # Y[j] = 0 for j >= H - s
    y[: prev.shape[0] - s] = prev[s:]  # Y[j] = P[j + s] for j < H - s
    return y


def segment(prev_chunk, new_chunk, s: int, d: int) -> np.ndarray:
    """Actions executed in the s steps after a request with delay d ([X-4])."""
    prev = check_array("prev_chunk", prev_chunk, ndim=2)
    new = check_array("new_chunk", new_chunk, shape=prev.shape)
    d = check_delay(prev.shape[0], s, d)  # checks s too
    return _segment(prev, new, int(s), d)


def _segment(prev: np.ndarray, new: np.ndarray, s: int, d: int) -> np.ndarray:
    return np.concatenate([prev[s: s + d], new[d: s]], axis=0)  # P[s .. s + d - 1], then new[d .. s - 1]


def _sources(c: int, s: int, d: int) -> tuple[np.ndarray, np.ndarray]:
    """[X-4] (chunk, token) of each step of request c >= 1's segment: chunk c - 1's tokens s .. s + d - 1,
    then chunk c's tokens d .. s - 1."""
    return np.r_[np.full(d, c - 1), np.full(s - d, c)], np.r_[np.arange(s, s + d), np.arange(d, s)]


def execute_chunks(chunks, delays, s: int) -> dict:
    """Executed action sequence of C chunks generated with delays d_0 .. d_{C-1} ([X-2]..[X-5]).

    Returns a dict with ``actions`` [C*s, A], ``chunk_index`` and ``token_index``
    [C*s] (which chunk and which of its tokens each executed action came from).
    """
    ch = check_array("chunks", chunks, ndim=3)
    C, H, A = ch.shape
    if C < 1:
        raise ValueError("chunks must hold at least one chunk, got 0")
    s = check_int("s", s, 1, H)
    ds = _delays(delays, C, H, s)
    # the first chunk executes its own tokens 0 .. s - 1.
    actions, src_c, src_j = [ch[0, :s]], [np.zeros(s, int)], [np.arange(s)]
    for c in range(1, C):
        actions.append(_segment(ch[c - 1], ch[c], s, ds[c]))
        sc, sj = _sources(c, s, ds[c])
        src_c.append(sc)
        src_j.append(sj)
    return {"actions": np.concatenate(actions), "chunk_index": np.concatenate(src_c).astype(int),
            "token_index": np.concatenate(src_j).astype(int)}


def closed_loop(generate, env_step, obs0, num_chunks: int, H: int, s: int, delays) -> dict:
    """Run the executor in closed loop ([X-6]).

    generate(obs, prior, d, c) -> chunk [H, A]  (prior is None for c = 0)
    env_step(action) -> obs                      (called once per executed action)

    Request c sees the observation of step c*s. Returns the executed actions,
    the observations seen by each request, the chunks and the priors.
    """
    if not callable(generate) or not callable(env_step):
        raise ValueError("generate and env_step must be callables")
    C = check_int("num_chunks", num_chunks, 1)
    H = check_horizon(H)
    s = check_int("s", s, 1, H)
    ds = _delays(delays, C, H, s)
    obs = obs0
    chunks, priors, request_obs, executed = [], [], [], []
    prev = None
    for c in range(C):
        d = ds[c]
        prior = None if prev is None else _shift(prev, s)
        request_obs.append(np.asarray(obs))
        new = check_array(f"chunk {c} returned by generate", generate(obs, prior, d, c), ndim=2)
        # Every chunk has the first one's A: checked here, so the error names generate, not segment's argument.
        want = f"[H={H}, A]" if prev is None else f"[H={H}, A={prev.shape[1]}]"
        if new.shape[0] != H or (prev is not None and new.shape[1] != prev.shape[1]):
            raise ValueError(f"generate must return chunks of shape {want}, got {list(new.shape)} for chunk {c}")
        seg = new[:s] if prev is None else _segment(prev, new, s, d)
        for a in seg:
            executed.append(a)
            obs = env_step(a)
        chunks.append(new)
        priors.append(prior)
        prev = new
    return {"actions": np.asarray(executed), "chunks": np.asarray(chunks), "priors": priors,
            "request_obs": request_obs}


def public_first_segment(first_chunk, second_chunk, s: int, d: int) -> np.ndarray:
    """The first segment of the public RTC evaluation loop, an alternative to [X-2] ([X-7]).

    There, ``first_chunk`` is generated at the reset observation without a
    prior, then ``second_chunk`` at the same observation with ``first_chunk``
    as its prior (same frame, no shift) and delay ``d``; the first ``s`` steps
    execute ``first_chunk[:d]`` then ``second_chunk[d:s]``, and request 1
    (step ``s``) takes ``second_chunk`` as its previous chunk ([X-3]).

    >>> a, b = np.zeros((4, 1)), np.ones((4, 1))
    >>> public_first_segment(a, b, 3, 1)[:, 0].tolist()
    [0.0, 1.0, 1.0]
    """
    first = check_array("first_chunk", first_chunk, ndim=2)
    second = check_array("second_chunk", second_chunk, shape=first.shape)
    d = check_delay(first.shape[0], s, d)
    return np.concatenate([first[:d], second[d:s]], axis=0)
