"""Adapter of the JAX twin in softrtc.jax ([CF-12]); needs jax.

softrtc.jax mirrors the reference module for module, so each method converts
the interface's JSON-shaped arguments (rule and window dicts, field parameter
dicts) with the reference helpers and calls the JAX function of the same name.
The JAX samplers return only the chunk, so sampler cases check the chunk
([CF-11]: a trace of None means "chunk only"). Most of a run's time is XLA
compilation, one per function and input shape; compiled code is kept in JAX's
persistent compilation cache ([CF-17]).
"""

from __future__ import annotations

import functools
import importlib
import importlib.util
import json
import os

import numpy as np

from .reference import rule_from_dict, window_from_dict


def _use_compilation_cache() -> None:
    """Keep compiled kernels across runs in the ``xla`` folder of softrtc's JAX cache ([KC-1]:
    ``$SOFTRTC_JAX_CACHE``, else ``~/.cache/softrtc/jax``; ``SOFTRTC_JAX_CACHE=off`` turns it off)
    unless the user chose JAX's own (``JAX_COMPILATION_CACHE_DIR``) ([CF-17])."""
    from softrtc._files import default_cache_dir, unwritable_reason

    root = default_cache_dir()
    if root is None or os.environ.get("JAX_COMPILATION_CACHE_DIR") or unwritable_reason(root) is not None:
        return
    import jax

    jax.config.update("jax_compilation_cache_dir", str(root / "xla"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)  # most kernels here compile in ms
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


_use_compilation_cache()


def _mod(name: str):
    return importlib.import_module(f"softrtc.jax.{name}")


def _b(a):
    return np.asarray(a)[None]


class JaxAdapter:
    name = "jax"
    time_convention = "data_at_1"

    def __init__(self):
        self._tables = {}

    @staticmethod
    def to_numpy(x):
        return np.asarray(x)

    def endpoint(self, rule, d):
        return _mod("endpoints").endpoint(_mod("endpoints").from_reference(rule_from_dict(rule)), d)

    def prefix_weights(self, H, d, e, schedule, parametrization):
        return _mod("weights").prefix_weights(H, d, e, schedule, parametrization)

    def weights(self, H, d, window, s):
        # One weight_table call per (H, window, s) serves every d: the vectors sweep
        # d = 0 .. H for each window, and per-call dispatch would dominate the run ([CF-17]).
        w = _mod("weights")
        if isinstance(d, bool) or not isinstance(d, (int, np.integer)) or not 0 <= d <= H:
            # raises the JAX twin's own ValueError
            return w.soft_weights(H, d, w.from_reference(window_from_dict(window)), s)
        key = (H, json.dumps(window, sort_keys=True), s)
        if key not in self._tables:
            self._tables[key] = np.asarray(w.weight_table(H, w.from_reference(window_from_dict(window)), s))
        return self._tables[key][d]

    def hard_weights(self, H, d):
        return _mod("weights").hard_weights(H, d)

    def delay_probs(self, dist, d_min, d_max, decay):
        return _mod("delays").delay_probs(dist, d_min, d_max, decay)

    def sample_delay(self, probs, d_min, u):
        return _mod("delays").sample_delay(probs, d_min, u)

    def corrupt(self, actions, noise, w, tau):
        return _mod("corruption").corrupt(actions, noise, w, tau)

    def token_times(self, w, t):
        return _mod("corruption").token_times(w, t)

    def loss(self, pred, actions, noise, w):
        return _mod("loss").flow_matching_loss(pred, actions, noise, w)

    def batch_loss(self, preds, actions, noise, w):
        return _mod("loss").batch_loss(preds, actions, noise, w)

    def _field(self, params):
        return _mod("velocity").ReferenceVelocityField(params)

    def velocity(self, field, obs, x, t):
        return self._field(field)(obs, x, t)

    def velocity_vjp(self, field, obs, x, t, cotangent):
        return self._field(field).vjp(obs, x, t, cotangent)

    @staticmethod
    def _unbatch(x, noise):
        # The JAX samplers return [B, H, A]; an unbatched call has B = 1.
        x = np.asarray(x)
        return x.reshape(np.shape(noise)) if x.ndim == 3 and x.shape[0] == 1 else x

    # The JAX samplers act on batches [B, ...]; a case is a batch of one. Each call
    # is validated on the host first (so invalid cases raise the twin's own
    # ValueError) and then runs jitted, as a user would run it: eager JAX
    # dispatches every op (and re-traces every VJP) one by one.
    def _sample(self, kind, field, obs, noise, prior, w, T, max_guidance=None, step="algorithm1"):
        sampler = _mod("sampler")
        if kind == "guided":
            _mod("guidance").guidance_weight(0.0, max_guidance)  # validates max_guidance
        step = sampler.check_step(step)  # [S-10] validated on the host, as the twin would
        args = sampler.check_batch(_b(obs), _b(noise), None if prior is None else _b(prior),
                                   None if w is None else _b(w), T)
        self._field(field)  # validates the field parameters
        fn = _jitted_sampler(kind, step)
        params = {k: np.asarray(v, np.float32) for k, v in field.items()}
        out = fn(params, args[0], args[1], args[2], args[3], args[4],
                 None if max_guidance is None else float(max_guidance))
        return self._unbatch(out, noise), None

    def naive_sample(self, field, obs, noise, T):
        return self._sample("naive", field, obs, noise, None, None, T)

    def rtc_sample(self, field, obs, noise, prior, w, T):
        return self._sample("rtc", field, obs, noise, prior, w, T)

    def rtc_sample_step(self, field, obs, noise, prior, w, T, step):
        return self._sample("rtc", field, obs, noise, prior, w, T, step=step)

    def guided_sample(self, field, obs, noise, prior, w, T, max_guidance):
        return self._sample("guided", field, obs, noise, prior, w, T, max_guidance)

    def guidance_weights(self, H, s, d, variant):
        return _mod("guidance").guidance_prefix_weights(H, s, d, variant)

    def guidance_weight(self, t, max_guidance):
        # The twin's lam(t) is vectorized over t ([N-10]); the interface function takes one flow time ([CF-34]).
        if np.ndim(t) != 0:
            raise ValueError(f"t must be one flow time (a scalar), got an array of shape {list(np.shape(t))}")
        return _mod("guidance").guidance_weight(t, max_guidance)

    def shift_prior(self, prev, s):
        return _mod("executor").shift_prior(prev, s)

    def execute_chunks(self, chunks, delays, s):
        ex = _mod("executor")
        ch = np.asarray(chunks)
        if ch.ndim != 3 or not np.all(np.isfinite(ch)):
            return ex.execute_chunks(chunks, delays, s)  # raises the twin's own ValueError
        ds = ex.check_delays(ch.shape[1], s, delays)
        return _jitted_execute()(ch.astype(np.float32), ds.astype(np.int32), s)

    def difference_norm(self, actions, order):
        return _mod("metrics").difference_norm(actions, order)

    def action_delta(self, actions):
        return _mod("metrics").action_delta(actions)

    def action_jerk(self, actions):
        return _mod("metrics").action_jerk(actions)

    def boundary_jump(self, actions, chunk_index):
        return _mod("metrics").boundary_jump(actions, chunk_index)

    def bootstrap_interval(self, values, indices, confidence):
        lo, hi = _mod("metrics").bootstrap_interval_from_indices(values, indices, confidence)
        return np.array([float(lo), float(hi)])

    def standard_error(self, values):
        return _mod("metrics").standard_error(values)


@functools.lru_cache(maxsize=None)
def _jitted_sampler(kind: str, step: str = "algorithm1"):
    import jax

    def run(params, obs, noise, prior, w, T, max_guidance):
        field = _mod("velocity").ReferenceVelocityField(params)
        if kind == "naive":
            return _mod("sampler").naive_sample(field, obs, noise, T, unroll=False)
        if kind == "rtc":
            return _mod("sampler").rtc_sample(field, obs, noise, prior, w, T, unroll=False, step=step)
        return _mod("guidance").guided_sample(field, obs, noise, prior, w, T, max_guidance, unroll=False)

    return jax.jit(run, static_argnums=(5, 6))


@functools.lru_cache(maxsize=None)
def _jitted_execute():
    import jax

    return jax.jit(lambda ch, ds, s: _mod("executor").execute_chunks(ch, ds, s), static_argnums=(2,))


def _method_weights(self, method, H, s, d, window):
    return _mod("methods").method_weights(method, H, s, d, None if window is None else
                                          _mod("weights").from_reference(window_from_dict(window)))


# method_weights only where softrtc.jax provides a methods module ([S-6]); otherwise unsupported.
if importlib.util.find_spec("softrtc.jax.methods") is not None:
    JaxAdapter.method_weights = _method_weights


def _f32(x):
    """float64 arrays (and the field's parameter dict) as float32: the twin computes in float32, and a
    float64 argument makes JAX compile a conversion kernel for every new shape ([CF-17])."""
    if isinstance(x, np.ndarray) and x.dtype == np.float64:
        return x.astype(np.float32)
    if isinstance(x, dict) and x and all(isinstance(v, np.ndarray) for v in x.values()):
        return {k: _f32(v) for k, v in x.items()}
    return x


def _float32_inputs(method):
    @functools.wraps(method)
    def call(self, *args):
        return method(self, *(_f32(a) for a in args))
    return call


for _name in ("prefix_weights", "corrupt", "token_times", "loss", "batch_loss", "velocity", "velocity_vjp",
              "naive_sample", "rtc_sample", "rtc_sample_step", "guided_sample", "sample_delay", "shift_prior",
              "execute_chunks",
              "difference_norm", "action_delta", "action_jerk", "boundary_jump", "bootstrap_interval",
              "standard_error"):
    setattr(JaxAdapter, _name, _float32_inputs(getattr(JaxAdapter, _name)))

ADAPTER = JaxAdapter()
