"""Conformance adapter of ``softrtc.torch`` in the spec's time convention (data at t = 1) ([CF-7], [CF-21]).

    softrtc conformance run --impl torch

Array arguments become float32 tensors (integer arrays int64 tensors, so a delay
written 2.0 stays a float and is rejected, [CF-23]); the batched functions of
``softrtc.torch`` run on them, the samplers and the field on a batch of one.
"""

from __future__ import annotations

import numpy as np
import torch

from softrtc.torch import (corruption, delays, endpoints, executor, guidance, loss, methods, metrics, sampler,
                           velocity, weights)

DTYPE = torch.float32


def to_numpy(x):
    """Tensors (and lists or tuples of them) to NumPy; used by the runner on every output."""
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def _t(a):
    """A NumPy array argument as a tensor: floats float32, integers int64; anything else unchanged."""
    if isinstance(a, np.ndarray) and a.dtype.kind in "iuf":
        return torch.as_tensor(a, dtype=DTYPE if a.dtype.kind == "f" else torch.int64)
    return a


def _batched(fn, *args):
    """Call a batched function on one example and strip the batch axis from its output and trace."""
    chunk, trace = fn(*args)
    strip = lambda val: val[0] if isinstance(val, torch.Tensor) and val.dim() else val  # noqa: E731
    return chunk[0], [{k: strip(val) for k, val in step.items()} for step in trace]


class TorchAdapter:
    """Every interface function of [CF-7] on ``softrtc.torch``."""

    name = "torch"
    time_convention = "data_at_1"
    convention = "data_at_1"
    to_numpy = staticmethod(to_numpy)

    # chapters E and W
    def endpoint(self, rule, d):
        return endpoints.endpoint(rule, d)

    def prefix_weights(self, H, d, e, schedule, parametrization):
        return weights.prefix_weights(H, d, e, schedule, parametrization, dtype=DTYPE)

    def weights(self, H, d, window, s):
        return weights.soft_weights(H, d, weights.window_from_dict(window), s, dtype=DTYPE)

    def hard_weights(self, H, d):
        return weights.hard_weights(H, d, dtype=DTYPE)

    def method_weights(self, method, H, s, d, window):
        return methods.method_weights(method, H, s, d, None if window is None else weights.window_from_dict(window),
                                      dtype=DTYPE)

    def guidance_weights(self, H, s, d, variant):
        return guidance.guidance_weights(H, s, d, variant, dtype=DTYPE)

    # chapters D, C and L
    def delay_probs(self, dist, d_min, d_max, decay):
        return delays.delay_probs(dist, d_min, d_max, decay, dtype=DTYPE)

    def sample_delay(self, probs, d_min, u):
        return delays.sample_delay(_t(probs), d_min, u)

    def corrupt(self, actions, noise, w, tau):
        return corruption.corrupt(_t(actions), _t(noise), _t(w), tau, self.convention)

    def token_times(self, w, t):
        return corruption.token_times(_t(w), _t(t), self.convention)

    def loss(self, pred, actions, noise, w):
        return loss.loss(_t(pred), _t(actions), _t(noise), _t(w), self.convention)

    def batch_loss(self, preds, actions, noise, w):
        return loss.batch_loss(_t(preds), _t(actions), _t(noise), _t(w), self.convention)

    # chapters F, S and G: the field is built from the case's parameters
    def make_field(self, params):
        """The velocity function the samplers call: v(obs, x, t) of [F-1] in spec time."""
        return velocity.ReferenceVelocityField(params, dtype=DTYPE)

    def velocity(self, params, obs, x, t):
        return velocity.velocity(self.make_field(params), _t(obs), _t(x), _t(t))

    def velocity_vjp(self, params, obs, x, t, cotangent):
        return velocity.velocity_vjp(self.make_field(params), _t(obs), _t(x), _t(t), _t(cotangent))

    def guidance_weight(self, t, max_guidance):
        return guidance.guidance_weight(t, max_guidance, self.convention)

    def naive_sample(self, params, obs, noise, T):
        fn, o, n = self.make_field(params), _t(obs), _t(noise)
        return _batched(lambda: sampler.naive_sample(fn, o[None], n[None], T, convention=self.convention,
                                                     return_trace=True))

    def rtc_sample(self, params, obs, noise, prior, w, T):
        fn, o, n, y, ww = self.make_field(params), _t(obs), _t(noise), _t(prior), _t(w)
        return _batched(lambda: sampler.rtc_sample(fn, o[None], n[None], y[None], ww, T,
                                                   convention=self.convention, return_trace=True))

    def rtc_sample_step(self, params, obs, noise, prior, w, T, step):
        fn, o, n, y, ww = self.make_field(params), _t(obs), _t(noise), _t(prior), _t(w)
        return _batched(lambda: sampler.rtc_sample(fn, o[None], n[None], y[None], ww, T, convention=self.convention,
                                                   return_trace=True, step=step))

    def guided_sample(self, params, obs, noise, prior, w, T, max_guidance):
        fn, o, n, y, ww = self.make_field(params), _t(obs), _t(noise), _t(prior), _t(w)
        return _batched(lambda: guidance.guided_sample(fn, o[None], n[None], y[None], ww, T, max_guidance,
                                                       convention=self.convention, return_trace=True))

    # chapters X and M
    def shift_prior(self, prev, s):
        return executor.shift_prior(_t(prev), s)

    def execute_chunks(self, chunks, d, s):
        return executor.execute_chunks(_t(chunks), _t(d), s)

    def difference_norm(self, actions, order):
        return metrics.difference_norm(_t(actions), order)

    def action_delta(self, actions):
        return metrics.action_delta(_t(actions))

    def action_jerk(self, actions):
        return metrics.action_jerk(_t(actions))

    def boundary_jump(self, actions, chunk_index):
        return metrics.boundary_jump(_t(actions), _t(chunk_index))

    def bootstrap_interval(self, values, indices, confidence):
        return metrics.bootstrap_interval(_t(values), _t(indices), confidence)

    def standard_error(self, values):
        return metrics.standard_error(_t(values))


ADAPTER = TorchAdapter()
