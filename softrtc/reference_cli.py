"""``softrtc weights`` / ``softrtc examples``: the reference's worked examples."""

from __future__ import annotations

import json

import numpy as np

from ._cli_util import command_error, int_in, real_in
from .reference import endpoints, metrics
from .reference.endpoints import delay_scaled, fixed, hard, offset
from .reference.executor import execute_chunks
from .reference.guidance import guidance_prefix_weights
from .reference.sampler import MAX_STEPS, STEPS, naive_sample, rtc_sample, step_multipliers
from .reference.velocity import ReferenceVelocityField
from .reference.weights import SoftWindow, hard_weights, prefix_weights, soft_weights


# Options each rule uses, with their defaults; an option given for a rule that ignores it is an error.
_RULE_OPTIONS = {"delay_scaled": {"lam": 2.0, "h_max": 5}, "offset": {"length": 1, "h_max": 5},
                 "fixed": {"length": 1}, "hard": {}}


def _rule_from_args(args):
    used = _RULE_OPTIONS[args.rule]
    for name in ("lam", "h_max", "length"):
        if getattr(args, name) is not None and name not in used:
            raise ValueError(f"--{name.replace('_', '-')} does not apply to --rule {args.rule} "
                             f"(it takes {', '.join('--' + k.replace('_', '-') for k in used) or 'no options'})")
    v = {k: (getattr(args, k) if getattr(args, k) is not None else dflt) for k, dflt in used.items()}
    if args.rule == "delay_scaled":
        return delay_scaled(v["lam"], v["h_max"])
    if args.rule == "offset":
        return offset(v["length"], v["h_max"])
    if args.rule == "fixed":
        return fixed(v["length"])
    return hard()


def weights_table(H: int, s: int, window: SoftWindow, delays=None, step: str | None = None,
                  num_steps: int = 5) -> str:
    """Text table of the soft weights for each delay ([W-7]); with ``step`` ([S-10]) each delay's row is
    followed by the per-token step sizes c_j / T of that solver step for ``num_steps`` = T Euler steps.

    >>> print(weights_table(4, 2, SoftWindow(delay_scaled(2.0, 2)), [1], "consistent", 4))
    H=4 s=2 window={"rule": {"kind": "delay_scaled", "lam": 2.0, "h_max": 2}, "schedule": "linear", \
"parametrization": "rtc", "overflow": "clip"} step=consistent T=4
    d  e(d) e* | j=0   j=1   j=2   j=3
    1  2    2  | 1.000 0.500 0.000 0.000
       c/T     | 0.250 0.125 0.250 0.250
    """
    from .reference._validate import check_horizon, check_int
    from .reference.sampler import check_step
    H = check_horizon(H)
    s = check_int("s", s, 1, H)
    if step is not None:
        step = check_step(step)
        num_steps = check_int("num_steps", num_steps, 1, MAX_STEPS)
    delays = range(0, min(s, H - s) + 1) if delays is None else delays
    head = f"H={H} s={s} window={json.dumps(window.to_dict())}"
    lines = [head if step is None else f"{head} step={step} T={num_steps}",
             ("d  e(d) e* | " + " ".join(f"j={j:<3d}" for j in range(H))).rstrip()]
    from .reference.weights import effective_endpoint
    for d in delays:
        e = endpoints.endpoint(window.rule, d)
        es = effective_endpoint(H, d, min(e, H), s, window.overflow)
        w = soft_weights(H, d, window, s)
        lines.append(f"{d:<2d} {e:<4d} {es:<2d} | " + " ".join(f"{x:5.3f}" for x in w))
        if step is not None:  # [S-10] token j moves by c_j v_j / T
            lines.append(f"{'':<2} {'c/T':<4} {'':<2} | " + " ".join(f"{c / num_steps:5.3f}"
                                                                   for c in step_multipliers(w, step)))
    return "\n".join(lines)


def demo() -> int:
    """Worked examples of the reference (make demo, first step)."""
    print("Prefix weights, d=2, e=6, H=10 ([W-4] rtc / [W-5] paper):")
    print("  rtc   ", np.round(prefix_weights(10, 2, 6, "linear"), 3).tolist())
    print("  paper ", np.round(prefix_weights(10, 2, 6, "linear", "paper"), 3).tolist())
    print("\nSoft RTC weights of the default window (the paper's main rule and schedule, rtc, clip; [W-7]), H=8, s=4:")
    print(weights_table(8, 4, SoftWindow()))
    print("\nSame with overflow='zeros' (as in the paper's experiments, [W-6]):")
    print(weights_table(8, 4, SoftWindow(overflow="zeros")))
    print("\nOffset L=0 equals Hard RTC ([W-8]):",
          all(np.array_equal(soft_weights(8, d, SoftWindow(offset(0, 8)), 4), hard_weights(8, d))
              for d in range(5)))
    print("Delay-scaled lam=1 equals Hard RTC ([W-5] consequence):",
          all(np.array_equal(soft_weights(8, d, SoftWindow(delay_scaled(1, 5)), 4), hard_weights(8, d))
              for d in range(5)))
    print("Guidance weights d=2, H=8, s=4 ([G-1]): hard",
          guidance_prefix_weights(8, 4, 2, "hard").tolist(), "soft",
          np.round(guidance_prefix_weights(8, 4, 2, "soft"), 3).tolist())

    field = ReferenceVelocityField.init(seed=0, horizon=8, action_dim=2, obs_dim=4)
    rng = np.random.default_rng(0)
    obs, noise = rng.standard_normal(4), rng.standard_normal((8, 2))
    prev = naive_sample(field, obs, rng.standard_normal((8, 2)), 5)
    from .reference.executor import shift_prior
    y = shift_prior(prev, 4)
    naive = naive_sample(field, obs, noise, 5)
    same = rtc_sample(field, obs, noise, y, np.zeros(8), 5)
    print("\nRTC sampler with d=0 equals the naive sampler bitwise ([S-7]):", np.array_equal(naive, same))
    soft = rtc_sample(field, obs, noise, y, soft_weights(8, 2, SoftWindow(), 4), 5)
    print("Soft RTC chunk (d=2), first action dim:", np.round(soft[:, 0], 3).tolist())
    ex = execute_chunks(np.stack([prev, soft]), [0, 2], 4)
    print("Executed 8 steps, source chunk per step ([X-4]):", ex["chunk_index"].tolist(),
          "token:", ex["token_index"].tolist())
    print(f"Action delta {metrics.action_delta(ex['actions']):.4f}, jerk {metrics.action_jerk(ex['actions']):.4f}, "
          f"boundary jump {metrics.boundary_jump(ex['actions'], ex['chunk_index']):.4f} ([M-1]..[M-3])")
    return 0


def add_subparsers(sub) -> None:
    p = sub.add_parser("weights", help="print the Soft RTC weight table of a window ([W-7])")
    mw = endpoints.MAX_WINDOW
    p.add_argument("--H", type=int_in("value", 1, mw), default=8, help=f"chunk horizon, 1 .. {mw} (default 8)")
    p.add_argument("--s", type=int_in("value", 1, mw), default=4, help="execute horizon, 1 .. H (default 4)")
    p.add_argument("--rule", choices=endpoints.RULES, default="delay_scaled",
                   help="endpoint rule of the window (default delay_scaled)")
    p.add_argument("--lam", type=real_in("value", 0.0, float(mw)), default=None,
                   help="delay multiplier of delay_scaled (default 2)")
    p.add_argument("--h-max", type=int_in("value", 0, mw), default=None,
                   help="maximum endpoint of delay_scaled and offset, <= H (default 5)")
    p.add_argument("--length", type=int_in("value", 0, mw), default=None,
                   help="L of offset or h of fixed (default 1)")
    p.add_argument("--schedule", choices=("zeros", "ones", "linear", "exp"), default="linear",
                   help="schedule on the window (default linear)")
    p.add_argument("--parametrization", choices=("rtc", "paper"), default="rtc",
                   help="window parametrization (default rtc)")
    p.add_argument("--overflow", choices=("clip", "zeros"), default="clip",
                   help="window past the overlap (default clip)")
    p.add_argument("--step", choices=STEPS, default=None,
                   help="also print each token's step size c_j / T of this solver step of the training-time "
                        "sampler ([S-10]; algorithm1: 1 / T everywhere, consistent: (1 - w_j) / T inside the window)")
    p.add_argument("--T", type=int_in("value", 1, MAX_STEPS), default=None,
                   help=f"Euler steps T of --step, 1 .. {MAX_STEPS} (default 5)")
    p.set_defaults(func=_weights_cmd)
    e = sub.add_parser("examples", help="print the reference's worked examples")
    e.set_defaults(func=lambda args: demo())


def _weights_cmd(args) -> int:
    try:
        # Relations between options are checked here so that the error names the options ([N-11]).
        if args.s > args.H:
            raise ValueError(f"--s must be an integer in [1, {args.H}] (--H), got {args.s}")
        rule = _rule_from_args(args)
        if rule.kind != "hard" and rule.bound() > args.H:
            opt = "--h-max" if rule.kind in ("delay_scaled", "offset") else "--length"
            given = getattr(args, "h_max" if opt == "--h-max" else "length") is not None
            raise ValueError(f"{opt} must be <= --H={args.H}, got {rule.bound()}"
                             + ("" if given else f" (the default; pass {opt} <= {args.H} for a short chunk)"))
        if args.T is not None and args.step is None:
            raise ValueError(f"--T applies to --step only (the step sizes c_j / T), got --T {args.T} without --step")
        window = SoftWindow(rule, args.schedule, args.parametrization, args.overflow)
        print(weights_table(args.H, args.s, window, step=args.step, num_steps=5 if args.T is None else args.T))
    except ValueError as exc:
        return command_error(getattr(args, "_prog", "softrtc weights"), exc)
    return 0
