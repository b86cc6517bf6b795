"""The five chunk-generation methods in PyTorch (spec chapter S, [S-6], [S-8]); twin of
``softrtc.reference.methods``.

| method          | sampler         | weights                               |
|-----------------|-----------------|---------------------------------------|
| naive           | naive_sample    | zeros (the prior is ignored)          |
| inference_hard  | guided_sample   | guidance_weights(H, s, d, "hard")     |
| inference_soft  | guided_sample   | guidance_weights(H, s, d, "soft")     |
| train_hard      | rtc_sample      | hard_weights(H, d)                    |
| train_soft      | rtc_sample      | soft_weights(H, d, window, s)         |
"""

from __future__ import annotations

import torch

from softrtc.reference.methods import check_method_step

from . import _validate as v
from .executor import check_delay
from .guidance import MAX_GUIDANCE, guidance_weights, guided_sample
from .sampler import check_batch, naive_sample, rtc_sample
from .weights import SoftWindow, check_window, hard_weights, soft_weights

METHODS = ("naive", "inference_hard", "inference_soft", "train_hard", "train_soft")

__all__ = ["METHODS", "method_weights", "generate_chunk"]


def method_weights(method: str, H: int, s: int, d, window=None, *, dtype=None, device=None) -> torch.Tensor:
    """Token weights of a method for executable delays d, an int or an integer tensor ([S-6]).

    The request is checked whole ([S-8]): d by [X-1] for every method; a given window for every
    method; the default window is resolved by train_soft only.
    """
    v.choice("method", method, METHODS)
    d = check_delay(H, s, d)
    if window is not None:
        window = check_window(H, window)
    kw = {"dtype": dtype, "device": device}
    if method == "naive":
        shape = (*d.shape, H) if isinstance(d, torch.Tensor) else (H,)
        dev = d.device if isinstance(d, torch.Tensor) else device
        return torch.zeros(shape, dtype=v.float_kw(dtype, dev)["dtype"], device=dev)
    if method.startswith("inference_"):
        return guidance_weights(H, s, d, method.split("_", 1)[1], **kw)
    if method == "train_hard":
        return hard_weights(H, d, **kw)
    return soft_weights(H, d, SoftWindow() if window is None else window, s, **kw)


def generate_chunk(method: str, velocity_fn, obs, noise, prior, s: int, d, T: int, window=None,
                   max_guidance: float = MAX_GUIDANCE, *, convention: str = "data_at_1",
                   step: str = "algorithm1") -> torch.Tensor:
    """A batch of chunks by ``method`` ([S-6]); ``prior`` None is the first chunk: naive with d = 0 ([X-2]).

    ``d`` is one int for the batch or a tensor [B] of per-example delays. Arguments the method
    ignores are checked all the same ([S-8]). ``step`` ([S-10]) is the training-time sampler's; naive
    accepts either, the guided methods only "algorithm1" ([S-14]).
    """
    v.choice("method", method, METHODS)
    step = check_method_step(method, step)
    x, y, _, T = check_batch(obs, noise, prior, None, T)
    B, H, _ = x.shape
    s = v.integer("s", s, 1, H)
    if window is not None:
        window = check_window(H, window)
    if prior is None:
        d = check_delay(H, s, d)
        if (bool((d != 0).any()) if isinstance(d, torch.Tensor) else d != 0):
            raise ValueError("d must be 0 for the first chunk (prior None, [X-2])")
        return naive_sample(velocity_fn, obs, x, T, convention=convention)
    if isinstance(d, torch.Tensor) and tuple(d.shape) not in ((), (B,)):
        raise ValueError(f"d must be an int or a tensor of shape [{B}], got shape {list(d.shape)}")
    w = method_weights(method, H, s, d, window, dtype=x.dtype, device=x.device)
    if method == "naive":
        return naive_sample(velocity_fn, obs, x, T, convention=convention)
    if method.startswith("inference_"):
        return guided_sample(velocity_fn, obs, x, y, w, T, max_guidance, convention=convention)
    return rtc_sample(velocity_fn, obs, x, y, w, T, convention=convention, step=step)
