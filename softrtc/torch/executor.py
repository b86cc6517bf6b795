"""Asynchronous execution in PyTorch (spec chapter X, 04-execution.md): the shifted prior and the executed
action sequence. Request c >= 1 executes the previous chunk's tokens s .. s + d_c - 1, then its own
d_c .. s - 1 ([X-4])."""

from __future__ import annotations

import torch

from . import _validate as v

__all__ = ["check_delay", "shift_prior", "execute_chunks"]


def check_delay(H: int, s: int, d):
    """An executable delay, 0 <= d <= min(s, H - s) ([X-1]); an int or an integer tensor."""
    H = v.integer("H", H, 1, v.MAX_HORIZON)
    s = v.integer("s", s, 1, H)
    return v.delays("d", d, 0, min(s, H - s))


def shift_prior(prev, s: int) -> torch.Tensor:
    """Y[..., j, :] = P[..., j + s, :] for j < H - s, 0 past the overlap ([X-3]); prev [..., H, A]."""
    p = v.real_tensor("prev", prev, min_ndim=2)
    s = v.integer("s", s, 1, p.shape[-2])
    return torch.cat([p[..., s:, :], torch.zeros_like(p[..., :s, :])], dim=-2)


def execute_chunks(chunks, delays, s: int) -> dict:
    """Executed actions [C s, A] with the chunk and token each came from ([X-1]..[X-5])."""
    ch = v.real_tensor("chunks", chunks, ndim=3)
    C, H, _ = ch.shape
    if C < 1 or H < 1:
        raise ValueError(f"chunks must hold at least one chunk of at least one token, got shape {list(ch.shape)}")
    s = v.integer("s", s, 1, H)
    d = v.int_tensor("delays", delays, expected=(C,), device=ch.device)
    if int(d[0]) != 0:
        raise ValueError(f"delays[0] must be 0 (the first chunk has no prior, [X-2]), got {int(d[0])}")
    d_max = min(s, H - s)
    bad = ((d < 0) | (d > d_max)).nonzero()
    if bad.numel():
        c = int(bad[0, 0])
        raise ValueError(f"delays[{c}] must be an integer in [0, {d_max}] = [0, min(s, H - s)], got {int(d[c])}")
    step = torch.arange(C * s, device=ch.device)
    c, k = step // s, step % s
    committed = (k < d[c]).long()  # the first d_c steps of segment c still run the previous chunk ([X-4])
    chunk_index, token_index = c - committed, k + s * committed
    return {"actions": ch[chunk_index, token_index], "chunk_index": chunk_index, "token_index": token_index}
