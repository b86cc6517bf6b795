"""Training-time RTC for any PyTorch flow-matching policy ([PT-4], [PT-5]; chapters D, C, L).

:class:`RTCObjective` holds what a training step needs besides the model: the
weight table ``[H + 1, H]`` of the method (none / hard / soft) and the delay
CDF, as tensors built once. Per batch, :meth:`RTCObjective.draw` draws one
delay and one flow time per example and the noise from an explicit
``torch.Generator`` ([D-4], [C-1], [N-9]) and returns the corrupted chunk and
the per-token times ``[B, H]`` the model is called with; :meth:`RTCObjective.loss`
is the masked loss of [L-2] averaged over the batch ([L-3]). Everything after
the draw is plain tensor code: no host synchronisation, no data-dependent
Python branch, so a step built on it compiles with ``torch.compile``.

    obj = RTCObjective("soft", H=10, s=5, d_max=5)
    batch = obj.draw(actions, generator)                 # x, times [B, H], noise, weights, delays, tau
    pred = model(obs, batch["x"], batch["times"])        # per-token time
    loss = obj.loss(pred, actions, batch)
"""

from __future__ import annotations

import dataclasses

import torch

from . import _validate as v
from .corruption import corrupt, sample_tau
from .delays import check_generator, delay_cdf, delay_probs
from .loss import batch_loss
from .weights import SoftWindow, check_window, weight_table

OBJECTIVES = ("none", "hard", "soft")

__all__ = ["OBJECTIVES", "RTCObjective"]


@dataclasses.dataclass(frozen=True)
class _Config:
    method: str
    H: int
    s: int | None
    window: SoftWindow
    delay_dist: str
    d_min: int
    d_max: int
    decay: float
    convention: str


class RTCObjective:
    """The training objective of a method: ``none`` (plain flow matching, d = 0, w = 0), ``hard``
    (1[j < d], [W-8]) or ``soft`` (the window's weights, [W-7]) ([PT-4]).

    Delays: ``delay_dist`` "uniform" ([D-1]) or "exponential" with ``decay`` ([D-2]) on
    ``d_min .. d_max`` (``d_max <= H``, [D-4]; not limited by [X-1]). ``s`` is the execute horizon the
    soft window is clipped at ([W-6]); it is required by "soft" with overflow "clip". ``convention``
    "data_at_1" or "noise_at_1" ([V-1]): in the flipped one ``times`` are t' and the target is eps - A.
    """

    def __init__(self, method: str = "soft", H: int = 8, s: int | None = 4, window=None, *,
                 delay_dist: str = "uniform", d_min: int = 0, d_max: int = 4, decay: float = 1.0,
                 convention: str = "data_at_1", dtype=None, device=None):
        v.choice("method", method, OBJECTIVES)
        H = v.integer("H", H, 1, v.MAX_HORIZON)
        s = None if s is None else v.integer("s", s, 1, H)
        window = check_window(H, SoftWindow() if window is None else window)
        v.choice("delay_dist", delay_dist, ("uniform", "exponential"))
        d_min = v.integer("d_min", d_min, 0, H)
        d_max = v.integer("d_max", d_max, d_min, H)
        decay = v.real("decay", decay, 0.0, 64.0)
        v.convention(convention)
        if method == "none":
            d_min = d_max = 0  # [T-5]: plain flow matching draws d = 0
        self.config = _Config(method, H, s, window, delay_dist, d_min, d_max, decay, convention)
        kw = v.float_kw(dtype, device)
        self.table = weight_table(H, method, window, s, **kw)  # [H + 1, H]
        self.cdf = delay_cdf(delay_probs(delay_dist, d_min, d_max, decay, **kw))

    def to(self, device=None, dtype=None) -> "RTCObjective":
        """The tables on another device or floating dtype (in place; returns self)."""
        kw = v.float_kw(dtype if dtype is not None else self.table.dtype, device)
        self.table, self.cdf = self.table.to(**kw), self.cdf.to(**kw)
        return self

    def delays(self, u: torch.Tensor) -> torch.Tensor:
        """d = d_min + #{k : cdf_k <= u} for uniforms u [B] ([D-3]); int64 [B]."""
        # the last CDF entry is 1 > u: only the first n - 1 count, as in delays.sample_delay
        return self.config.d_min + (self.cdf[:-1] <= u[..., None]).sum(-1)

    def weights(self, d: torch.Tensor) -> torch.Tensor:
        """Rows d of the weight table: [B, H] ([PT-4])."""
        return self.table[d]

    def draw_uniforms(self, actions, generator: torch.Generator) -> tuple:
        """The random draws of a batch from ``generator``, in this order: u [B] (delays), tau [B], eps
        [B, H, A] ([D-4], [C-1], [C-2], [N-9])."""
        g = check_generator(generator)
        a = self._actions(actions)
        B = a.shape[0]
        u = torch.rand(B, generator=g, dtype=self.cdf.dtype, device=g.device).to(self.cdf.device)
        tau = sample_tau(B, g, dtype=a.dtype, device=a.device)
        noise = torch.randn(a.shape, generator=g, dtype=a.dtype, device=g.device).to(a.device)
        return u, tau, noise

    def prepare(self, actions, u, tau, noise) -> dict:
        """Delays, weights and the corruption from given draws: plain tensor code with no host
        synchronisation, so a compiled training step can include it ([PT-5]).

        Returns ``x`` [B, H, A], ``times`` [B, H] (t, or t' when flipped), ``noise``, ``weights`` [B, H],
        ``delays`` [B], ``tau`` [B].
        """
        a = self._actions(actions)
        d = self.delays(u)
        w = self.weights(d).to(a.dtype)
        x, times = corrupt(a, noise, w, tau, self.config.convention)
        return {"x": x, "times": times, "noise": noise, "weights": w, "delays": d, "tau": tau}

    def draw(self, actions, generator: torch.Generator) -> dict:
        """:meth:`draw_uniforms` then :meth:`prepare`: one batch's corrupted chunk and per-token times."""
        return self.prepare(actions, *self.draw_uniforms(actions, generator))

    def _actions(self, actions) -> torch.Tensor:
        a = v.real_tensor("actions", actions, ndim=3)
        if a.shape[1] != self.config.H or a.shape[0] < 1:
            raise ValueError(f"actions must have shape [B >= 1, H={self.config.H}, A], got {list(a.shape)}")
        return a

    def loss(self, pred, actions, batch: dict) -> torch.Tensor:
        """Mean over the batch of the masked per-example loss ([L-2], [L-3]) against ``batch`` of :meth:`draw`."""
        if not isinstance(batch, dict) or "noise" not in batch or "weights" not in batch:
            raise ValueError("batch must be the dict returned by draw (with 'noise' and 'weights')")
        return batch_loss(pred, actions, batch["noise"], batch["weights"], self.config.convention)
