"""Asynchronous execution (spec chapter X): the shifted prior and the executed action sequence.

Request c >= 1 is made at step c s; its segment executes the previous chunk's
tokens s .. s + d_c - 1 (the committed prefix), then its own tokens d_c .. s - 1.
"""

from __future__ import annotations

import torch

from .checks import int_tensor, integer, tensor


def shift_prior(prev, s: int) -> torch.Tensor:
    """Y[j] = P[j + s] for j < H - s, 0 past the overlap ([X-3])."""
    p = tensor("prev", prev, ndim=2)
    s = integer("s", s, 1, p.shape[0])
    return torch.cat([p[s:], torch.zeros_like(p[:s])])


def check_delays(delays, C: int, H: int, s: int) -> torch.Tensor:
    """One delay per chunk: delays[0] = 0 ([X-2]), every later one executable, 0 <= d <= min(s, H - s) ([X-1])."""
    d = int_tensor("delays", delays, shape=(C,))
    if d[0] != 0:
        raise ValueError(f"delays[0] must be 0 (the first chunk has no prior), got {int(d[0])}")
    d_max = min(s, H - s)
    bad = ((d < 0) | (d > d_max)).nonzero()
    if bad.numel():
        c = int(bad[0, 0])
        raise ValueError(f"delays[{c}] must be an integer in [0, {d_max}] = [0, min(s, H - s)], got {int(d[c])}")
    return d


def execute_chunks(chunks, delays, s: int) -> dict:
    """Executed actions [C s, A] with the chunk and token each came from ([X-2]..[X-5])."""
    ch = tensor("chunks", chunks, ndim=3)
    C, H, _ = ch.shape
    if C < 1 or H < 1:
        raise ValueError(f"chunks must hold at least one chunk of at least one token, got shape {list(ch.shape)}")
    s = integer("s", s, 1, H)
    d = check_delays(delays, C, H, s)
    step = torch.arange(C * s)
    c, k = step // s, step % s  # request c, position k in its segment
    committed = k < d[c]  # the first d_c steps of segment c still run the previous chunk
    chunk_index = c - committed.long()
    token_index = k + s * committed.long()
    return {"actions": ch[chunk_index, token_index], "chunk_index": chunk_index, "token_index": token_index}
