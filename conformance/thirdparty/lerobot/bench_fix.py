"""Latency of one guided denoising step of LeRobot's RTC, as released and with the pull-back fix.

Needs torch, LeRobot and the ``patch`` program (nothing of softrtc). Run from any folder:

    python bench_fix.py [--rounds 15] [--steps 20]

The fix (``lerobot-0.6.1-pullback-jacobian.diff`` beside this file) marks the state as requiring
gradients before the denoiser runs, so ``denoise_step`` adds one backward pass through the denoiser
to every guided step. The script applies the diff's ``modeling_rtc.py`` part to a copy of the
installed module, imports both, and times ``RTCProcessor.denoise_step`` of each on the same inputs in
interleaved rounds, in CPU time of the calling thread (torch runs on one thread, and autograd's
CPU backward runs on the calling thread), so other processes on a busy machine do not count; the
fastest round of each is kept. Two
stand-in denoisers are timed: a small MLP and a wider one on pi0's chunk shape (50 x 32); a policy's
own action expert has its own forward / backward ratio, which bounds the step's ratio near
1 + backward / forward.
"""

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from reproduce import load_rtc  # noqa: E402  (the same import of LeRobot's RTC modules)

DIFF = Path(__file__).resolve().parent / "lerobot-0.6.1-pullback-jacobian.diff"


def source_hunks(diff_text: str) -> str:
    """The part of the diff that changes ``modeling_rtc.py`` (the rest updates LeRobot's tests)."""
    parts = diff_text.split("--- a/")
    return "".join("--- a/" + p for p in parts[1:] if p.startswith("src/lerobot/policies/rtc/modeling_rtc.py"))


def patched_processor(modeling, folder: Path):
    """``RTCProcessor`` of a copy of ``modeling``'s file with the fix applied (``patch`` does it)."""
    hunk = folder / "modeling.diff"
    hunk.write_text(source_hunks(DIFF.read_text()))
    out = folder / "modeling_rtc_fixed.py"
    subprocess.run(["patch", "--silent", "-o", str(out), modeling.__file__, str(hunk)], check=True)
    spec = importlib.util.spec_from_file_location(modeling.__package__ + ".modeling_rtc_fixed", out)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module.RTCProcessor


def mlp(width: int, H: int, A: int, depth: int):
    layers, n = [], H * A
    for _ in range(depth):
        layers += [torch.nn.Linear(n, width), torch.nn.GELU()]
        n = width
    net = torch.nn.Sequential(*layers, torch.nn.Linear(n, H * A))
    return lambda x: net(x.reshape(*x.shape[:-2], H * A)).reshape(x.shape)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=15, help="interleaved rounds (>= 1)")
    ap.add_argument("--steps", type=int, default=20, help="denoise_step calls per round (>= 1)")
    args = ap.parse_args(argv)
    if args.rounds < 1 or args.steps < 1:
        ap.error(f"--rounds and --steps must be >= 1, got {args.rounds}, {args.steps}")
    RTCConfig, RTCProcessor, RTCAttentionSchedule = load_rtc(keep_bypass=True)
    modeling = sys.modules[RTCProcessor.__module__]
    torch.manual_seed(0)
    torch.set_num_threads(1)
    cases = [("small MLP, H 8 x A 2, width 32", 8, 2, mlp(32, 8, 2, 1)),
             ("MLP on pi0's chunk, H 50 x A 32, 4 x 1024", 50, 32, mlp(1024, 50, 32, 4))]
    with tempfile.TemporaryDirectory() as tmp:
        Fixed = patched_processor(modeling, Path(tmp))
        import lerobot
        print(f"LeRobot {lerobot.__version__}, torch {torch.__version__}, one CPU thread, thread CPU time; "
              f"fastest of {args.rounds} interleaved rounds of {args.steps} guided steps")
        print(f"{'denoiser':44s} {'released ms/step':>17s} {'fixed ms/step':>14s} {'ratio':>6s}")
        for name, H, A, denoiser in cases:
            cfg = RTCConfig(enabled=True, execution_horizon=H // 2, max_guidance_weight=5.0,
                            prefix_attention_schedule=RTCAttentionSchedule.LINEAR)
            procs = {"released": RTCProcessor(cfg), "fixed": Fixed(cfg)}
            x, prev = torch.randn(H, A), torch.randn(H // 2, A)
            best = {k: float("inf") for k in procs}
            for _ in range(args.rounds):
                for key, proc in procs.items():
                    start = time.thread_time()
                    for k in range(args.steps):
                        proc.denoise_step(x, prev, 2, 0.9 - 0.8 * k / args.steps, denoiser, execution_horizon=H // 2)
                    best[key] = min(best[key], (time.thread_time() - start) / args.steps)
            r, f = best["released"] * 1e3, best["fixed"] * 1e3
            print(f"{name:44s} {r:17.3f} {f:14.3f} {f / r:6.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
