"""Adapter of LeRobot's real-time chunking, ``lerobot.policies.rtc`` ([CF-7], [V-1], [V-4], [TP-6], [TP-7]).

Every function calls LeRobot's own code; nothing of RTC is re-implemented here:

- ``prefix_weights``, ``hard_weights``, ``guidance_weights``, ``method_weights`` (inference methods):
  ``RTCProcessor.get_prefix_weights(inference_delay, execution_horizon, chunk_size)`` under the
  schedule of ``RTCConfig.prefix_attention_schedule`` ([W-3], [W-4], [W-8], [G-1]).
- ``guidance_weight`` and ``guided_sample_window``: ``RTCProcessor.denoise_step``, the guided velocity
  of one step ([G-2]..[G-4]); its debug tracker reports the denoised estimate, the weighted error,
  the pull-back and the guidance weight it used. From LeRobot 0.6 on, the Euler loop around it is
  LeRobot's own ``lerobot.policies.common.flow_matching.euler_integrate``.
- ``shift_prior`` and ``execute_chunks``: ``ActionQueue`` in RTC mode, which drops the new chunk's
  first ``real_delay`` actions and hands the unexecuted rest back as ``prev_chunk_left_over``
  ([X-3]..[X-5]).

Glue, kept to the fewest lines and named in the compatibility report (:data:`GLUE`): in LeRobot
0.4.4 the Euler loop that each flow policy writes inline (``pi0``, ``pi05``, ``smolvla``: ``dt = -1/T``,
``time = 1 + k dt``, ``x += dt v``); the zero padding of the prior that ``denoise_step`` does inside
([X-3]); the control loop that takes actions from the queue; and the test's velocity field (the
reference field of [F-1], ported to torch in the flipped convention, standing in for the policy).

LeRobot runs flow time from 1 (noise) to 0 (data), so ``time_convention = "noise_at_1"`` ([V-1]).
Its ``execution_horizon`` is the END of the guided window (our ``e``; ``H - s`` for [G-1]), not the
execute horizon ``s`` ([V-4]); the conversion is made here, once.

LeRobot's package ``__init__`` files import far more than its RTC code uses: ``lerobot.policies``
imports every policy's configuration (datasets, torchvision, huggingface_hub, draccus), and in 0.6
``lerobot.policies.rtc`` imports ``lerobot.processor`` and ``lerobot.utils`` and ``lerobot.configs``
imports its dataset and video configurations. The RTC modules themselves import only torch and the
enum ``lerobot.configs.types.RTCAttentionSchedule``: :func:`load_rtc` imports them with those three
``__init__`` files bypassed, so ``pip install --no-deps lerobot==X`` beside torch is the whole
installation for either release ([TP-6]).
"""

from __future__ import annotations

import importlib
import math
import sys
import types
from pathlib import Path

import numpy as np

INSTALL_HINT = ("pip install --no-deps lerobot==0.4.4 on Python 3.11, or lerobot==0.6.1 on Python 3.12 "
                "(its RTC modules need only torch)")
RTC_MODULES = ("configuration_rtc", "modeling_rtc", "action_queue")
# Packages whose __init__ imports LeRobot's dataset, vision and processor stacks; bypassed while the
# RTC modules import (parents first).
BYPASSED = ("lerobot.configs", "lerobot.policies", "lerobot.policies.rtc")
# LeRobot 0.6's shared Euler loop; absent in 0.4.4, where each policy writes the loop inline.
EULER_MODULE = "lerobot.policies.common.flow_matching"

# Spec schedule names ([W-3]) -> LeRobot's RTCAttentionSchedule members, and the [G-1] variants.
SCHEDULES = {"zeros": "ZEROS", "ones": "ONES", "linear": "LINEAR", "exp": "EXP"}
GUIDANCE_VARIANTS = {"hard": "zeros", "soft": "exp"}
INFERENCE_METHODS = {"inference_hard": "hard", "inference_soft": "soft"}


def load_rtc():
    """LeRobot's RTC modules, the schedule enum and (0.6 on) ``euler_integrate``, as a dict of modules.

    The ``__init__`` files of :data:`BYPASSED` import LeRobot's dataset, vision and processor stacks,
    none of which the RTC modules use. When ``lerobot.policies`` is already imported (a full
    installation in use), the modules are imported normally. Otherwise a bare package object (its
    ``__path__`` only) stands in for each of those packages while the modules import, and is removed
    afterwards, so a later ``import lerobot.policies`` runs the real package. ``lerobot.configs``'s
    stand-in carries the one name the RTC modules take from it, ``RTCAttentionSchedule``. Raises
    ImportError naming :data:`INSTALL_HINT` when LeRobot is not installed.
    """
    try:
        lerobot = importlib.import_module("lerobot")
    except ImportError as exc:
        raise ImportError(f"LeRobot is not installed ({exc}); install it with: {INSTALL_HINT}") from None
    names = [f"lerobot.policies.rtc.{m}" for m in RTC_MODULES]
    if "lerobot.policies" in sys.modules:
        return _import_all(names)
    root = Path(lerobot.__file__).parent
    stubs = {}
    for name in BYPASSED:
        if name in sys.modules:
            continue
        stub = types.ModuleType(name)
        stub.__path__ = [str(root.joinpath(*name.split(".")[1:]))]
        sys.modules[name] = stub
        stubs[name] = stub
    try:
        enum = importlib.import_module("lerobot.configs.types").RTCAttentionSchedule
        if "lerobot.configs" in stubs:
            stubs["lerobot.configs"].RTCAttentionSchedule = enum
        return _import_all(names)
    finally:
        for name, stub in stubs.items():
            if sys.modules.get(name) is stub:
                del sys.modules[name]


def _import_all(names) -> dict:
    mods = {n.rsplit(".", 1)[-1]: importlib.import_module(n) for n in names}
    mods["types"] = importlib.import_module("lerobot.configs.types")
    try:
        mods["flow_matching"] = importlib.import_module(EULER_MODULE)
    except ModuleNotFoundError as exc:  # LeRobot 0.4: no shared loop; only that module may be missing
        if exc.name not in (EULER_MODULE, EULER_MODULE.rsplit(".", 1)[0]):
            raise
        mods["flow_matching"] = None
    return mods


_mods = load_rtc()
RTCConfig = _mods["configuration_rtc"].RTCConfig
RTCProcessor = _mods["modeling_rtc"].RTCProcessor
ActionQueue = _mods["action_queue"].ActionQueue
RTCAttentionSchedule = _mods["types"].RTCAttentionSchedule
euler_integrate = getattr(_mods["flow_matching"], "euler_integrate", None)

_LOOP = ("LeRobot's `euler_integrate`" if euler_integrate is not None
         else "the Euler loop LeRobot writes inline in pi0 / pi05 / smolvla")
# What each provided function exercises of LeRobot, and what is glue ([CF-7]); the report prints it.
GLUE = {
    "prefix_weights": ("RTCProcessor.get_prefix_weights(d, e, H)", "none"),
    "hard_weights": ("RTCProcessor.get_prefix_weights(d, H, H) under the ZEROS schedule", "none"),
    "guidance_weights": ("RTCProcessor.get_prefix_weights(d, H - s, H)",
                         "the variant's schedule (hard: ZEROS, soft: EXP, [G-1]) and e = H - s ([V-4])"),
    "method_weights": ("RTCProcessor.get_prefix_weights(d, H - s, H) for inference_hard / inference_soft",
                       "the method's schedule and e = H - s"),
    "guidance_weight": ("RTCProcessor.denoise_step at flow time t' (its debug tracker's guidance weight)",
                        "a zero one-token state and prior passed to denoise_step"),
    "guided_sample_window": (
        "RTCProcessor.denoise_step at every step (guided velocity, denoised estimate, weighted error, "
        "pull-back, guidance weight)" + (", inside euler_integrate" if euler_integrate is not None else ""),
        ("" if euler_integrate is not None else _LOOP + ", ")
        + "the prior's first H - s rows passed as prev_chunk_left_over (as ActionQueue.get_left_over gives "
          "them), and the test's velocity field"),
    "naive_sample": (
        ("euler_integrate without RTC (the first chunk's path: the policy's own velocity)"
         if euler_integrate is not None else
         "RTCProcessor.denoise_step without a previous chunk (the first chunk's path: the policy's own velocity)"),
        ("the test's velocity field" if euler_integrate is not None else
         _LOOP + " and the test's velocity field; this function tests glue, not LeRobot")),
    "shift_prior": ("ActionQueue.merge / get / get_left_over",
                    "taking s actions from the queue, and the zero padding to H rows that "
                    "denoise_step does inside"),
    "execute_chunks": ("ActionQueue.merge(real_delay = d_c) / get",
                       "the control loop: d_c actions taken while chunk c is computed, then s - d_c; the "
                       "chunk and token indices ride as two extra columns of the queue's processed actions"),
}


def versions() -> dict:
    """Versions of what this adapter runs (for the compatibility report)."""
    import lerobot
    import torch
    return {"lerobot": lerobot.__version__, "torch": torch.__version__.split("+")[0]}


def _torch():
    import torch
    return torch


def _schedule(name):
    """A spec schedule name as LeRobot's enum; LeRobot's enum raises ValueError for an unknown one."""
    return RTCAttentionSchedule(SCHEDULES.get(name, name) if isinstance(name, str) else name)


def _processor(schedule="linear", max_guidance=10.0, debug=False, maxlen=1):
    return RTCProcessor(RTCConfig(enabled=True, prefix_attention_schedule=_schedule(schedule),
                                  max_guidance_weight=max_guidance, debug=debug, debug_maxlen=maxlen))


class LeRobotAdapter:
    """LeRobot's RTC behind the adapter interface; functions LeRobot does not have are absent ([CF-9])."""

    name = "lerobot"
    time_convention = "noise_at_1"

    @staticmethod
    def to_numpy(x):
        torch = _torch()
        return x.detach().cpu().numpy() if torch.is_tensor(x) else np.asarray(x)

    # ---------------------------------------------------------------- weights ([W-3], [W-4], [W-8], [G-1])
    def prefix_weights(self, H, d, e, schedule, parametrization):
        if parametrization != "rtc":
            raise NotImplementedError("LeRobot builds the rtc parametrization only ([W-4]); "
                                      f"it has no {parametrization!r}")
        return _processor(schedule).get_prefix_weights(d, e, H)

    def hard_weights(self, H, d):
        return _processor("zeros").get_prefix_weights(d, H, H)

    def guidance_weights(self, H, s, d, variant):
        if variant not in GUIDANCE_VARIANTS:
            raise NotImplementedError(f"variant {variant!r} has no LeRobot schedule; "
                                      f"known: {sorted(GUIDANCE_VARIANTS)}")
        return _processor(GUIDANCE_VARIANTS[variant]).get_prefix_weights(d, H - s, H)

    def method_weights(self, method, H, s, d, window):
        if method not in INFERENCE_METHODS:
            raise NotImplementedError(f"LeRobot has inference-time RTC only, no method {method!r}")
        return self.guidance_weights(H, s, d, INFERENCE_METHODS[method])

    # ---------------------------------------------------------------- guidance ([G-2]..[G-5])
    def guidance_weight(self, t, max_guidance):
        torch = _torch()
        proc = _processor(max_guidance=max_guidance, debug=True)
        zero = torch.zeros(1, 1)
        proc.denoise_step(zero, zero, 0, t, lambda x: torch.zeros_like(x), execution_horizon=1)
        return proc.get_all_debug_steps()[-1].guidance_weight

    def guided_sample_window(self, field, obs, noise, prior, guidance, T):
        torch = _torch()
        g = guidance
        H = noise.shape[0]
        proc = _processor(g["schedule"], g["max_guidance"], debug=True, maxlen=T)
        left_over = torch.as_tensor(prior, dtype=torch.float32)[: H - g["s"]]
        calls = Recorder(FlippedField(field, obs))
        rtc = {"inference_delay": g["d"], "prev_chunk_left_over": left_over, "execution_horizon": g["end"]}
        x = _euler(proc, calls, torch.as_tensor(noise, dtype=torch.float32), T, rtc)
        steps = proc.get_all_debug_steps()
        trace = [{"state": c["x"], "time": torch.full((H,), c["time"]), "velocity": c["v"],
                  "denoised": _unbatch(st.x1_t), "error": _unbatch(st.err), "vjp": _unbatch(st.correction),
                  "guidance_weight": st.guidance_weight, "guided_velocity": _unbatch(st.v_t),
                  "next_state": _unbatch(st.x_t)}
                 for c, st in zip(calls.calls, steps, strict=True)]
        return x, trace

    def naive_sample(self, field, obs, noise, T):
        torch = _torch()
        calls = Recorder(FlippedField(field, obs))
        x = _euler(_processor(), calls, torch.as_tensor(noise, dtype=torch.float32), T, None)
        nxt = [c["x"] for c in calls.calls[1:]] + [x]
        trace = [{"state": c["x"], "time": torch.full((x.shape[0],), c["time"]), "velocity": c["v"],
                  "next_state": n} for c, n in zip(calls.calls, nxt)]
        return x, trace

    # ---------------------------------------------------------------- execution ([X-3]..[X-5])
    def shift_prior(self, prev, s):
        torch = _torch()
        prev = torch.as_tensor(prev)
        queue = ActionQueue(RTCConfig(enabled=True))
        queue.merge(prev, prev, real_delay=0)
        _take(queue, s)
        left = queue.get_left_over()
        out = torch.zeros_like(prev)  # denoise_step's right padding with zeros
        out[: left.shape[0]] = left
        return out

    def execute_chunks(self, chunks, delays, s):
        torch = _torch()
        chunks = torch.as_tensor(chunks)
        C, H, A = chunks.shape
        queue = ActionQueue(RTCConfig(enabled=True))
        executed = []
        for c in range(C):
            d = delays[c].item()
            before = queue.get_action_index()
            executed += _take(queue, d)  # executed while chunk c is being computed
            tags = torch.stack([torch.full((H,), float(c), dtype=chunks.dtype),
                                torch.arange(H, dtype=chunks.dtype)], dim=1)
            queue.merge(chunks[c], torch.cat([chunks[c], tags], dim=1), real_delay=d,
                        action_index_before_inference=before)
            executed += _take(queue, s - d)
        rows = torch.stack(executed) if executed else torch.zeros(0, A + 2, dtype=chunks.dtype)
        return {"actions": rows[:, :A], "chunk_index": rows[:, A].long(), "token_index": rows[:, A + 1].long()}


def _euler(proc, denoise, noise, T, rtc):
    """``T`` Euler steps from flow time 1 to 0 with LeRobot's guided step ``denoise_step`` when ``rtc``
    holds its inputs (delay, left-over, window end), the policy's own velocity otherwise.

    LeRobot 0.6: its ``euler_integrate`` on a batch of one, which also records each step's state and
    guided velocity in the processor's debug tracker. LeRobot 0.4 has no loop of its own: the glue
    below is the loop its flow policies write inline, and it records the same two values.
    """
    torch = _torch()
    if euler_integrate is not None:
        extra = {"rtc_enabled": True, **rtc} if rtc is not None else {}
        out = euler_integrate(lambda x, t: denoise(x, float(t[0])), noise.unsqueeze(0), T,
                              rtc_processor=proc if rtc is not None else None, **extra)
        return out.squeeze(0)
    x = noise
    dt = -1.0 / T
    for k in range(T):  # glue: the inline loop of LeRobot 0.4's pi0 / pi05 / smolvla
        time = 1.0 + k * dt
        if rtc is None:
            v = denoise(x, time)
        else:
            v = proc.denoise_step(x, rtc["prev_chunk_left_over"], rtc["inference_delay"], time,
                                  lambda z, time=time: denoise(z, time), execution_horizon=rtc["execution_horizon"])
        x = x + dt * v
        if proc.is_debug_enabled():
            proc.track(time=time, x_t=x, v_t=v)
    return x


def _unbatch(t):
    """A tracked tensor without the batch axis that ``denoise_step`` / ``euler_integrate`` add."""
    return t[0] if t is not None and t.dim() == 3 else t


class Recorder:
    """The test's policy as LeRobot's denoiser ``(x, time) -> velocity``, keeping each call's state,
    time and unguided velocity for the trace (glue: LeRobot's tracker keeps the guided velocity only)."""

    def __init__(self, field):
        self.field = field
        self.calls = []

    def __call__(self, x, time: float):
        state = x.reshape(self.field.H, -1)
        v = self.field(state, time)
        self.calls.append({"x": state.detach().clone(), "time": time, "v": v.detach().clone()})
        return v.reshape(x.shape)


def _take(queue, n) -> list:
    """Up to ``n`` actions from the queue, as a robot loop takes them (it idles when the queue is empty)."""
    out = []
    while len(out) < n:
        a = queue.get()
        if a is None:
            break
        out.append(a)
    return out


class FlippedField:
    """The test's policy: the reference velocity field of [F-1] in torch, float32, flipped ([V-1]).

    ``u(x, t') = -v(x, 1 - t')`` with the same time for every token, as LeRobot's policies call it.
    """

    def __init__(self, params, obs):
        torch = _torch()
        self.p = {k: torch.as_tensor(np.asarray(v), dtype=torch.float32) for k, v in params.items()}
        self.obs = torch.as_tensor(obs, dtype=torch.float32)
        self.H = self.p["Wt"].shape[0] // 3

    def __call__(self, x, time: float):
        torch = _torch()
        t = torch.full((self.H,), 1.0 - time)
        phi = torch.stack([t, torch.sin(math.pi * t), torch.cos(math.pi * t)], dim=-1).reshape(-1)
        p = self.p
        h = torch.tanh(x.reshape(-1) @ p["W1"] + phi @ p["Wt"] + self.obs @ p["Wo"] + p["b1"])
        return -(h @ p["W2"] + p["b2"]).reshape(x.shape)


ADAPTER = LeRobotAdapter()
