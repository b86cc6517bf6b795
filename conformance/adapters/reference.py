"""Adapter of the NumPy reference ([CF-7], [CF-12]): the implementation the vectors come from.

Each method turns the JSON-shaped arguments of the interface (dicts for rules
and windows, a parameter dict for the velocity field) into reference objects
and calls the reference function of the same chapter.
"""

from __future__ import annotations

import numpy as np

from softrtc.reference import (corruption, delays, endpoints, executor, guidance, loss, methods, metrics, sampler,
                               velocity, weights)


def rule_from_dict(rule) -> endpoints.EndpointRule:
    """EndpointRule from its dict form {kind, lam, h_max, length} ([E-1])."""
    if not isinstance(rule, dict):
        raise ValueError(f"rule must be a dict with key 'kind' in {endpoints.RULES}, got {type(rule).__name__}")
    extra = set(rule) - {"kind", "lam", "h_max", "length"}
    if extra:
        raise ValueError(f"rule has unknown keys {sorted(extra)}; allowed: kind, lam, h_max, length")
    return endpoints.EndpointRule(rule.get("kind"), rule.get("lam"), rule.get("h_max"), rule.get("length"))


def window_from_dict(window) -> weights.SoftWindow:
    """SoftWindow from its dict form {rule, schedule, parametrization, overflow} ([W-7]): absent keys but the
    rule take the defaults of [W-7], an unknown key is an error ([CF-34])."""
    if not isinstance(window, dict) or "rule" not in window:
        raise ValueError("window must be a dict with keys rule, schedule, parametrization, overflow")
    extra = set(window) - {"rule", "schedule", "parametrization", "overflow"}
    if extra:
        raise ValueError(f"window has unknown keys {sorted(extra)}; allowed: rule, schedule, parametrization, "
                         "overflow")
    return weights.SoftWindow(rule_from_dict(window["rule"]), window.get("schedule", "linear"),
                              window.get("parametrization", "rtc"), window.get("overflow", "clip"))


def guidance_weights_from_dict(g) -> np.ndarray:
    """W of [G-1] from a guided case's 'guidance' dict {H, s, d, variant, schedule, end, max_guidance}
    ([CF-27]); the schedule and the window's end must be the ones the variant and H - s give."""
    keys = ("H", "s", "d", "variant", "schedule", "end", "max_guidance")
    if not isinstance(g, dict) or sorted(g) != sorted(keys):
        raise ValueError(f"guidance must be a dict with keys {keys}")
    W = guidance.guidance_prefix_weights(g["H"], g["s"], g["d"], g["variant"])
    if g["schedule"] != guidance.GUIDANCE_SCHEDULES[g["variant"]] or g["end"] != g["H"] - g["s"]:
        raise ValueError(f"guidance schedule {g['schedule']!r} and end {g['end']!r} must be "
                         f"{guidance.GUIDANCE_SCHEDULES[g['variant']]!r} and H - s = {g['H'] - g['s']}")
    return W


class ReferenceAdapter:
    """Every interface function, backed by softrtc.reference."""

    name = "reference"
    time_convention = "data_at_1"

    @staticmethod
    def to_numpy(x):
        return np.asarray(x)

    # chapter E / W
    def endpoint(self, rule, d):
        return endpoints.endpoint(rule_from_dict(rule), d)

    def prefix_weights(self, H, d, e, schedule, parametrization):
        return weights.prefix_weights(H, d, e, schedule, parametrization)

    def weights(self, H, d, window, s):
        return weights.soft_weights(H, d, window_from_dict(window), s)

    def hard_weights(self, H, d):
        return weights.hard_weights(H, d)

    # chapter D / C / L
    def delay_probs(self, dist, d_min, d_max, decay):
        return delays.delay_probs(dist, d_min, d_max, decay)

    def sample_delay(self, probs, d_min, u):
        return delays.sample_delay(probs, d_min, u)

    def corrupt(self, actions, noise, w, tau):
        return corruption.corrupt(actions, noise, w, tau)

    def token_times(self, w, t):
        return corruption.token_times(w, t)

    def loss(self, pred, actions, noise, w):
        return loss.flow_matching_loss(pred, actions, noise, w)

    def batch_loss(self, preds, actions, noise, w):
        return loss.batch_loss(preds, actions, noise, w)

    # chapter F / S / G
    def velocity(self, field, obs, x, t):
        return velocity.ReferenceVelocityField(field)(obs, x, t)

    def velocity_vjp(self, field, obs, x, t, cotangent):
        return velocity.ReferenceVelocityField(field).vjp(obs, x, t, cotangent)

    def naive_sample(self, field, obs, noise, T):
        return sampler.naive_sample(velocity.ReferenceVelocityField(field), obs, noise, T, return_trace=True)

    def rtc_sample(self, field, obs, noise, prior, w, T):
        return sampler.rtc_sample(velocity.ReferenceVelocityField(field), obs, noise, prior, w, T, return_trace=True)

    def rtc_sample_step(self, field, obs, noise, prior, w, T, step):
        return sampler.rtc_sample(velocity.ReferenceVelocityField(field), obs, noise, prior, w, T, return_trace=True,
                                  step=step)

    def guided_sample(self, field, obs, noise, prior, w, T, max_guidance):
        return guidance.guided_sample(velocity.ReferenceVelocityField(field), obs, noise, prior, w, T, max_guidance,
                                      return_trace=True)

    def guided_sample_window(self, field, obs, noise, prior, guidance_, T):
        """The guided sampler with W built from the case's window parameters ([CF-27], [G-1])."""
        W = guidance_weights_from_dict(guidance_)
        return guidance.guided_sample(velocity.ReferenceVelocityField(field), obs, noise, prior, W, T,
                                      guidance_["max_guidance"], return_trace=True)

    def method_weights(self, method, H, s, d, window):
        return methods.method_weights(method, H, s, d, None if window is None else window_from_dict(window))

    def guidance_weights(self, H, s, d, variant):
        return guidance.guidance_prefix_weights(H, s, d, variant)

    def guidance_weight(self, t, max_guidance):
        return guidance.guidance_weight(t, max_guidance)

    # chapter X / M
    def shift_prior(self, prev, s):
        return executor.shift_prior(prev, s)

    def execute_chunks(self, chunks, delays_, s):
        return executor.execute_chunks(chunks, delays_, s)

    def difference_norm(self, actions, order):
        return metrics.difference_norm(actions, order)

    def action_delta(self, actions):
        return metrics.action_delta(actions)

    def action_jerk(self, actions):
        return metrics.action_jerk(actions)

    def boundary_jump(self, actions, chunk_index):
        return metrics.boundary_jump(actions, chunk_index)

    def bootstrap_interval(self, values, indices, confidence):
        return metrics.bootstrap_interval_from_indices(values, indices, confidence)

    def standard_error(self, values):
        return metrics.standard_error(values)


ADAPTER = ReferenceAdapter()
