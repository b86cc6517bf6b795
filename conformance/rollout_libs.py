"""``rollout_chunk`` ([CR-2]) of the JAX twin, the PyTorch library (both conventions) and LeRobot.

Each composes its own library's pieces (prior shift, method weights,
sampler, execution) around the served field of [CR-3]. The field is plain
Python that returns NumPy arrays, so each framework reaches it the way a port
reaches a model it cannot trace: JAX through ``jax.pure_callback`` with a
custom VJP that asks the field for its VJP, PyTorch through an
``autograd.Function`` whose backward does the same.
"""

from __future__ import annotations

import numpy as np

from .adapters.reference import window_from_dict
from .rollout_impls import METHODS, check_request


class JaxRollout:
    """softrtc.jax: ``executor.shift_prior``, ``methods.method_weights``, the samplers, ``executor.segment``.

    The samplers run jitted, one program per sampler and step count; the field is reached through
    ``jax.pure_callback``, which looks up the request's field when called, so one program serves every
    request."""

    name = "jax"
    time_convention = "data_at_1"
    rollout_methods = METHODS

    def __init__(self):
        self._field = None
        self._programs = {}
        self._vf = None

    def _host(self, which: str):
        def call(*arrays):
            fn = self._field if which == "velocity" else self._field.vjp
            rows = [np.asarray(a, np.float64) for a in arrays]
            return np.stack([fn(*(r[b] for r in rows)) for b in range(rows[1].shape[0])]).astype(np.float32)
        return call

    def _velocity_fn(self):
        import jax
        import jax.numpy as jnp

        if self._vf is None:
            @jax.custom_vjp
            def v(obs, x, t):
                return jax.pure_callback(self._host("velocity"), jax.ShapeDtypeStruct(x.shape, jnp.float32), obs, x,
                                         t)

            def fwd(obs, x, t):
                return v(obs, x, t), (obs, x, t)

            def bwd(res, ct):
                obs, x, t = res
                g = jax.pure_callback(self._host("vjp"), jax.ShapeDtypeStruct(x.shape, jnp.float32), obs, x, t, ct)
                return jnp.zeros_like(obs), g, jnp.zeros_like(t)

            v.defvjp(fwd, bwd)
            self._vf = v
        return self._vf

    def _program(self, kind: str, T: int, beta: float):
        import jax

        from softrtc.jax import guidance, sampler

        key = (kind, T, beta)
        if key not in self._programs:
            vf = self._velocity_fn()
            if kind == "naive":
                fn = lambda o, n, y, w: sampler.naive_sample(vf, o, n, T, unroll=False)  # noqa: E731
            elif kind == "guided":
                fn = lambda o, n, y, w: guidance.guided_sample(vf, o, n, y, w, T, beta, unroll=False)  # noqa: E731
            else:
                fn = lambda o, n, y, w: sampler.rtc_sample(vf, o, n, y, w, T, unroll=False)  # noqa: E731
            self._programs[key] = jax.jit(fn)
        return self._programs[key]

    def rollout_chunk(self, field, obs, prev, noise, method, s, d, arrival, T, window, max_guidance):
        from softrtc.jax import executor, methods
        from softrtc.jax import weights as jw

        H, e = check_request(obs, prev, noise, method, s, d, arrival, T, window, max_guidance)
        self._field = field
        o, n = np.asarray(obs, np.float32)[None], np.asarray(noise, np.float32)[None]
        if prev is None or method == "naive":
            chunk = self._program("naive", T, 0.0)(o, n, n, np.zeros(H, np.float32))[0]
        else:
            prior = np.asarray(executor.shift_prior(np.asarray(prev, np.float32), s))
            win = None if window is None else jw.from_reference(window_from_dict(window))
            w = np.asarray(methods.method_weights(method, H, s, d, win))
            kind = "guided" if method.startswith("inference_") else "rtc"
            chunk = self._program(kind, T, float(max_guidance))(o, n, prior[None], w)[0]
        chunk = np.asarray(chunk)
        if prev is None:
            return {"chunk": chunk, "executed": chunk[:s]}
        return {"chunk": chunk, "executed": np.asarray(executor.segment(np.asarray(prev, np.float32), chunk, s, e))}


class TorchRollout:
    """softrtc.torch: ``executor.shift_prior``, ``methods.method_weights``, the samplers in the given convention."""

    rollout_methods = METHODS

    def __init__(self, flipped: bool = False):
        self.name = "torch-flipped" if flipped else "torch"
        self.time_convention = "noise_at_1" if flipped else "data_at_1"

    @staticmethod
    def _velocity_fn(field):
        import torch

        class Served(torch.autograd.Function):
            @staticmethod
            def forward(ctx, obs, x, t):
                ctx.save_for_backward(obs, x, t)
                out = [field(obs[b].numpy(), x[b].detach().numpy(), t[b].numpy()) for b in range(x.shape[0])]
                return torch.as_tensor(np.stack(out), dtype=x.dtype)

            @staticmethod
            def backward(ctx, ct):
                obs, x, t = ctx.saved_tensors
                g = [field.vjp(obs[b].numpy(), x[b].detach().numpy(), t[b].numpy(), ct[b].numpy())
                     for b in range(x.shape[0])]
                return None, torch.as_tensor(np.stack(g), dtype=x.dtype), None

        return lambda obs, x, t: Served.apply(obs, x, t.expand(x.shape[:2]))

    def rollout_chunk(self, field, obs, prev, noise, method, s, d, arrival, T, window, max_guidance):
        import torch

        from softrtc.torch import executor, guidance, methods, sampler

        from .adapters.reference import window_from_dict as wfd
        H, e = check_request(obs, prev, noise, method, s, d, arrival, T, window, max_guidance)
        conv = self.time_convention
        vf = self._velocity_fn(field)
        f32 = torch.float32
        o, n = torch.as_tensor(obs, dtype=f32)[None], torch.as_tensor(noise, dtype=f32)[None]
        p = None if prev is None else torch.as_tensor(prev, dtype=f32)
        if prev is None or method == "naive":
            chunk = sampler.naive_sample(vf, o, n, T, convention=conv)[0]
        else:
            prior = executor.shift_prior(p, s)
            w = methods.method_weights(method, H, s, d, None if window is None else wfd(window), dtype=f32)
            if method.startswith("inference_"):
                chunk = guidance.guided_sample(vf, o, n, prior[None], w, T, max_guidance, convention=conv)[0]
            else:
                chunk = sampler.rtc_sample(vf, o, n, prior[None], w, T, convention=conv)[0]
        if prev is None:
            return {"chunk": chunk.numpy(), "executed": chunk[:s].numpy()}
        # as the library's executor runs it: two chunks, delays (0, e); the second segment is this request's.
        both = executor.execute_chunks(torch.stack([p, chunk]), torch.tensor([0, e]), s)["actions"][s:]
        return {"chunk": chunk.numpy(), "executed": both.numpy()}


class LeRobotRollout:
    """LeRobot 0.4.4: ``RTCProcessor.denoise_step`` in its inline Euler loop, ``ActionQueue`` for the prior
    and the execution; inference-time methods only (LeRobot has no training-time RTC)."""

    name = "lerobot"
    time_convention = "noise_at_1"
    rollout_methods = ("naive", "inference_hard", "inference_soft")

    def rollout_chunk(self, field, obs, prev, noise, method, s, d, arrival, T, window, max_guidance):
        import torch

        from .adapters.lerobot import GUIDANCE_VARIANTS, INFERENCE_METHODS, ActionQueue, RTCConfig, _processor, _take

        H, e = check_request(obs, prev, noise, method, s, d, arrival, T, window, max_guidance)
        if method not in self.rollout_methods:
            raise NotImplementedError(f"LeRobot has inference-time RTC only, no method {method!r}")
        guided = prev is not None and method != "naive"
        proc = _processor(GUIDANCE_VARIANTS[INFERENCE_METHODS[method]] if guided else "linear", max_guidance)
        x = torch.as_tensor(noise, dtype=torch.float32)
        queue, left = None, None
        if prev is not None:
            p = torch.as_tensor(prev, dtype=torch.float32)
            queue = ActionQueue(RTCConfig(enabled=True))
            queue.merge(p, p, real_delay=0)
            _take(queue, s)  # the s actions executed before this request
            left = queue.get_left_over()
        def u(xx, time):  # the policy's denoiser: velocity of a state [H, A] or [1, H, A] at one flow time
            v = field(obs, xx.detach().reshape(H, -1).numpy(), np.full(H, time))
            return torch.as_tensor(v, dtype=torch.float32).reshape(xx.shape)
        dt = -1.0 / T
        for k in range(T):  # the inline Euler loop of LeRobot's flow policies
            time = 1.0 + k * dt
            if guided:
                vel = proc.denoise_step(x, left, d, time, lambda xx: u(xx, time), execution_horizon=H - s)
            else:
                vel = proc.denoise_step(x, None, 0, time, lambda xx: u(xx, time))
            x = x + dt * vel
        chunk = x.detach()
        if prev is None:
            return {"chunk": chunk.numpy(), "executed": chunk[:s].numpy()}
        before = queue.get_action_index()
        executed = _take(queue, e)
        queue.merge(chunk, chunk, real_delay=e, action_index_before_inference=before)
        executed += _take(queue, s - e)
        return {"chunk": chunk.numpy(), "executed": torch.stack(executed).numpy()}
