"""LeRobot with a left-over shorter than its guided window, against [W-6] ([TP-8]).

When the queue holds fewer unexecuted actions ``r`` than the window's end ``e`` (LeRobot's
``execution_horizon``), the prior exists only for tokens ``j < r``. [W-6] names two options: ``clip``
(the default: ``e* = max(d, min(e, r))``, the window ends at the prior's last row) and ``zeros`` (the
prior is zero-padded to ``e`` and window tokens ``j >= r`` are pulled toward the zero action).

LeRobot has both, in two places. ``RTCProcessor.denoise_step`` lowers ``execution_horizon`` to the
rows it is given (``clip``). LeRobot 0.6's rollout loop (``lerobot/rollout/inference/rtc.py``) first
pads or truncates the left-over to ``execution_horizon`` rows with ``_normalize_prev_actions_length``
("for stable compiled inference"), so ``denoise_step`` no longer sees a short left-over: ``zeros``.

Each case runs LeRobot's own code (``denoise_step``'s weights from its debug tracker, and 0.6's
padding function) and compares its weights and guidance targets with both options of [W-6] computed
by the reference (``softrtc.reference.weights.prefix_weights``). ``_normalize_prev_actions_length``
lives in a module that imports LeRobot's policy, processor and robot stacks; it is taken from the
installed file's source alone (the function's own code, compiled with torch as its one global),
which is glue.
"""

from __future__ import annotations

import ast
import importlib.util
from pathlib import Path

import numpy as np

from softrtc.reference.weights import prefix_weights
from .lerobot import RTCConfig, RTCProcessor, _schedule

ROLLOUT_MODULE = "lerobot.rollout.inference.rtc"
PAD_FUNCTION = "_normalize_prev_actions_length"
# (H, d, r, e): chunk length, delay, rows of left-over, window end; linear schedule, A = 1.
CASES = ((8, 1, 3, 6), (8, 2, 4, 6), (10, 0, 2, 5), (8, 3, 3, 6), (8, 2, 6, 6))


def load_padding():
    """LeRobot's ``_normalize_prev_actions_length`` from the installed source, or None (LeRobot 0.4: no
    rollout module, and its example loop passes the left-over as it is)."""
    spec = importlib.util.find_spec("lerobot")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(spec.submodule_search_locations[0], *ROLLOUT_MODULE.split(".")[1:]).with_suffix(".py")
    if not path.is_file():
        return None
    tree = ast.parse(path.read_text())
    fn = [n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == PAD_FUNCTION]
    if len(fn) != 1:
        raise ImportError(f"{ROLLOUT_MODULE} has no single function {PAD_FUNCTION}")
    import torch
    scope = {"torch": torch}
    exec(compile(ast.Module(body=fn, type_ignores=[]), str(path), "exec"), scope)
    return scope[PAD_FUNCTION]


def _lerobot_step(left_over, H, d, e):
    """Weights and guidance target of one ``denoise_step`` (a zero policy, so the target is the prior)."""
    import torch
    proc = RTCProcessor(RTCConfig(enabled=True, prefix_attention_schedule=_schedule("linear"), debug=True))
    x = torch.zeros(H, 1)
    proc.denoise_step(x, left_over, d, 0.5, lambda z: torch.zeros_like(z), execution_horizon=e)
    step = proc.get_all_debug_steps()[-1]
    w = step.weights.reshape(-1).numpy().astype(np.float64)
    # err = W (Y - x1) with x1 = 0: the padded prior Y where W > 0
    target = np.where(w > 0, (step.err.reshape(-1).numpy() / np.where(w > 0, w, 1)), np.nan)
    return w, target


def implementation_cases() -> dict:
    """The cases ([TP-8]): per case LeRobot's weights in both code paths and which [W-6] option each is."""
    import torch
    pad = load_padding()
    rows = []
    for H, d, r, e in CASES:
        prior = torch.arange(1, r + 1, dtype=torch.float32).reshape(r, 1)  # rows 1, 2, ..., r: never zero
        clip = prefix_weights(H, d, max(d, min(e, r)), "linear", "rtc")
        zeros = prefix_weights(H, d, e, "linear", "rtc")
        paths = {"denoise_step": prior}
        if pad is not None:
            paths["rollout"] = pad(prior, e)
        row = {"H": H, "d": d, "left_over_rows": r, "execution_horizon": e,
               "spec_clip": _rounded(clip), "spec_zeros": _rounded(zeros)}
        for name, left in paths.items():
            w, target = _lerobot_step(left, H, d, e)
            toward_zero = [j for j in range(H) if w[j] > 0 and target[j] == 0]
            option = ("clip" if np.allclose(w, clip, atol=1e-6) else "") + \
                     ("zeros" if np.allclose(w, zeros, atol=1e-6) and not np.allclose(clip, zeros) else "")
            row[name] = {"weights": _rounded(w), "pulled_toward_zero": toward_zero,
                         "option": option or "neither"}
        rows.append(row)
    return {"cases": rows, "rollout_padding": pad is not None}


def _rounded(w) -> list:
    return [round(float(v), 4) for v in np.asarray(w).reshape(-1)]
