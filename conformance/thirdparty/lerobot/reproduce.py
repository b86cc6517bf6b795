"""LeRobot's guided RTC step drops the policy's Jacobian from its pull-back: a reproducer.

Needs torch and LeRobot only (nothing of softrtc). Run:  python reproduce.py   (exit status 1: the
defect is present; 0: the pull-back equals autograd's VJP).

``RTCProcessor.denoise_step`` guides the velocity ``v`` of a state ``x`` toward the previous chunk
``Y`` through the denoised estimate ``x1(x) = x - t * v(x)`` (time ``t`` from 1 = noise to 0 = data):

    err = W * (Y - x1(x))                 weighted error, W the prefix weights
    g   = (d x1 / d x)^T err              pull-back, = err - t * (dv/dx)^T err
    v_guided = v(x) - lam(t) * g

It calls the denoiser before ``x_t.requires_grad_(True)``, so autograd treats ``v`` as a constant and
returns ``g = err``: the term ``- t (dv/dx)^T err`` is lost. Below, a small seeded MLP stands in for the
policy; the pull-back LeRobot reports (its debug tracker's ``correction``) is compared with autograd's
VJP of ``x1`` at ``x``, and LeRobot's guided velocity with ``v - lam g``.
"""

import importlib
import sys
import types
from pathlib import Path

import torch


def load_rtc(keep_bypass: bool = False):
    """LeRobot's RTC modules. A full LeRobot installation imports them as usual; with
    ``pip install --no-deps lerobot`` the package ``__init__`` files (which import LeRobot's dataset,
    vision and processor stacks) are bypassed while the modules import, and afterwards too when
    ``keep_bypass`` (so that another copy of an RTC module can still be imported)."""
    try:
        from lerobot.policies.rtc.configuration_rtc import RTCConfig
        from lerobot.policies.rtc.modeling_rtc import RTCProcessor
        from lerobot.configs.types import RTCAttentionSchedule
        return RTCConfig, RTCProcessor, RTCAttentionSchedule
    except ImportError:
        for name in [m for m in sys.modules if m == "lerobot" or m.startswith("lerobot.")]:
            del sys.modules[name]
    root = Path(importlib.import_module("lerobot").__file__).parent
    bare = {}
    for name in ("lerobot.configs", "lerobot.policies", "lerobot.policies.rtc"):
        bare[name] = sys.modules[name] = types.ModuleType(name)
        bare[name].__path__ = [str(root.joinpath(*name.split(".")[1:]))]
    try:
        schedule = importlib.import_module("lerobot.configs.types").RTCAttentionSchedule
        bare["lerobot.configs"].RTCAttentionSchedule = schedule
        config = importlib.import_module("lerobot.policies.rtc.configuration_rtc").RTCConfig
        processor = importlib.import_module("lerobot.policies.rtc.modeling_rtc").RTCProcessor
        return config, processor, schedule
    finally:
        for name, module in bare.items():
            if not keep_bypass and sys.modules.get(name) is module:
                del sys.modules[name]


def main() -> int:
    RTCConfig, RTCProcessor, RTCAttentionSchedule = load_rtc()
    torch.manual_seed(0)
    H, A, delay, horizon, time = 8, 2, 2, 6, 0.6  # chunk length, action dim, delay, window end, flow time
    policy = torch.nn.Sequential(torch.nn.Linear(H * A, 32), torch.nn.Tanh(), torch.nn.Linear(32, H * A))

    def velocity(x):
        return policy(x.reshape(*x.shape[:-2], H * A)).reshape(x.shape)

    x = torch.randn(H, A)
    prev = torch.randn(H - 2, A)  # the previous chunk's unexecuted actions
    proc = RTCProcessor(RTCConfig(enabled=True, execution_horizon=horizon, max_guidance_weight=5.0,
                                  prefix_attention_schedule=RTCAttentionSchedule.LINEAR, debug=True))
    guided = proc.denoise_step(x, prev, delay, time, velocity, execution_horizon=horizon).detach()
    step = proc.get_all_debug_steps()[-1]
    pullback, err, lam = step.correction.detach(), step.err.detach(), float(step.guidance_weight)

    # autograd's VJP of x1(x) = x - t v(x) at x, with the weighted error as cotangent
    def denoised(z):
        return z - time * velocity(z)

    vjp = torch.autograd.functional.vjp(denoised, x, err)[1]
    with torch.no_grad():
        expected = velocity(x) - lam * vjp

    gap = (pullback - vjp).abs().max().item()
    print(f"LeRobot {importlib.import_module('lerobot').__version__}, torch {torch.__version__}; "
          f"H = {H}, A = {A}, delay {delay}, execution_horizon {horizon}, time {time}, guidance weight {lam:.4g}")
    print(f"max |pull-back - autograd VJP|         = {gap:.3e}")
    print(f"max |pull-back - weighted error|       = {(pullback - err).abs().max().item():.3e}")
    print(f"max |Jacobian term t (dv/dx)^T err|    = {(err - vjp).abs().max().item():.3e}")
    print(f"max |guided velocity - (v - lam VJP)|  = {(guided - expected).abs().max().item():.3e}")
    if gap > 1e-5:
        print("DEFECT: the pull-back is the weighted error alone; the policy's Jacobian term is missing")
        return 1
    print("OK: the pull-back is autograd's VJP through the denoised estimate")
    return 0


if __name__ == "__main__":
    sys.exit(main())
