"""What the vector generator's cases have in common ([CF-3], [CF-5], [CF-6]): the case collector, the
tolerances per kind of quantity, and the conversion of NumPy values to the plain JSON of a vector file.
"""

from __future__ import annotations

import math

import numpy as np


# Tolerances (absolute, relative) per kind of quantity, loose enough for float32
# ports ([CF-5]); integers and indices are compared exactly.
TOL_EXACT = {"abs": 0.0, "rel": 0.0}
TOL_WEIGHTS = {"abs": 1e-5, "rel": 1e-5}
TOL_ARITH = {"abs": 1e-5, "rel": 1e-5}
TOL_TRACE = {"abs": 1e-4, "rel": 1e-4}
# Copied values (executed actions, the shifted prior): equal up to rounding to float32, the precision of
# the lowest port ([CF-32]): round to nearest moves a real by at most 2^-24 of its magnitude.
TOL_COPY = {"abs": 0.0, "rel": 2.0 ** -24}
# How far two regenerations may differ ([CF-3]): float64 rounding of NumPy's
# CPU-dependent transcendental kernels, far inside every tolerance above.
REGEN_TOL = {"abs": 1e-12, "rel": 1e-12}

# Functions whose output is a weight vector: an entry the rules give as exactly 0 or 1 is exact ([W-1],
# [W-3], [CF-32]).
WEIGHT_FUNCTIONS = ("prefix_weights", "weights", "hard_weights", "method_weights", "guidance_weights")


def exact_entries(function: str, args: dict, expected: dict) -> dict:
    """{output: flat indices} of the entries that the spec states exactly ([CF-32]): weights of 0 and 1
    ([W-1], [W-3]), the flow time 1 of a token with weight 1 ([C-1], [S-3]), lam(0) = beta ([G-4])."""
    out = {}
    if function in WEIGHT_FUNCTIONS:
        w = np.asarray(expected["weights"], dtype=np.float64)
        out["weights"] = np.flatnonzero((w == 0.0) | (w == 1.0)).tolist()
    elif function in ("token_times", "corrupt", "rtc_sample", "rtc_sample_step"):
        ones = np.flatnonzero(np.asarray(args["weights"], dtype=np.float64) == 1.0).tolist()
        out["trace/time" if function.startswith("rtc_sample") else "times"] = ones
    elif function == "guidance_weight" and args["t"] == 0:
        out["lam"] = [0]
    return {k: v for k, v in out.items() if v}


class _Cases:
    """Collects cases of one vector file, checking ids are unique."""

    def __init__(self):
        self.cases: list[dict] = []
        self._ids: set[str] = set()

    def add(self, cid: str, function: str, requirements, tolerance: dict, args: dict, expected: dict):
        if cid in self._ids:
            raise RuntimeError(f"duplicate case id {cid}")
        self._ids.add(cid)
        tolerance = dict(tolerance)
        if "error" not in expected:
            exact = exact_entries(function, args, expected)
            if exact:
                tolerance["exact"] = exact
        self.cases.append({"id": cid, "function": function, "requirements": sorted(requirements),
                           "tolerance": tolerance, "args": _plain(args), "expected": _plain(expected)})

    def error(self, cid: str, function: str, requirements, args: dict):
        """A case whose call MUST raise ValueError ([N-7])."""
        self.add(cid, function, requirements, TOL_EXACT, args, {"error": "ValueError"})


def _plain(obj):
    """NumPy values to plain Python (float, int, list) so json writes them with repr."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        if not math.isfinite(v):
            raise RuntimeError("vector files hold only finite numbers")
        return v + 0.0  # -0.0 -> 0.0, so the sign of zero never differs between runs
    return obj


def _rule_id(rule: dict) -> str:
    return "-".join(f"{k}{rule[k]}" if k != "kind" else rule[k] for k in sorted(rule, key=lambda k: k != "kind"))
