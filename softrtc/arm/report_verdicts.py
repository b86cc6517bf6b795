"""Verdicts on the paper's qualitative claims from an arm experiment summary ([AX-7]).

The claims and their rules are those of :mod:`softrtc.verdicts`, shared with
the Kinetix study table ([KR-5]); this module names what they read in the
arm's summary: success, D2 as the jerk, D1-D3 as the finite-difference
family, the offset sweep's rows ``offset<L>_<overflow>``, and the Soft
``N = 2`` rows the manifest holds.
"""

from __future__ import annotations

from softrtc import verdicts as _shared
from softrtc.verdicts import MIN_EPISODES, MIN_SEEDS, _ci, _diff, _f  # noqa: F401  (the report's formatting)

__all__ = ["verdicts", "MIN_SEEDS", "MIN_EPISODES", "ARM"]

# What the shared claims read in an arm summary (softrtc.arm.report_summary.METRICS).
ARM = _shared.Environment(success="success", success_word="success", succeeds="succeeds", jerk="D2",
                          fd=("D1", "D2", "D3"), fd_label="D1-D3", offset_row=lambda L, ov: f"offset{L}_{ov}")
# The Soft N = 2 rows of [AX-3] in the order their claims are listed.
_SOFT2 = ("soft2_zeros", "soft2_clip", "soft2_clip_consistent")


def verdicts(summary, manifest) -> list:
    """The paper's qualitative claims with a verdict each: supported / not supported / inconclusive ([AX-7])."""
    rows = manifest["rows"]
    same = rows.get("soft1_clip", {}).get("eval_key") == rows.get("train_hard", {}).get("eval_key") and \
        rows.get("soft1_zeros", {}).get("eval_key") == rows.get("train_hard", {}).get("eval_key")
    return _shared.verdicts(summary, ARM, soft2_rows=[r for r in _SOFT2 if r in rows], n1_identical=bool(same))
