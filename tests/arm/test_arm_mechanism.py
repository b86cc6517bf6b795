"""The consistent-step rows, the T sweep and the window-token measurement of the arm experiment ([AX-5], [AX-10],
[AX-11])."""

from __future__ import annotations

import numpy as np
import pytest

from softrtc.arm import experiment as ex
from softrtc.arm.mechanism import token_pull
from softrtc.arm.tasks import get_task


def test_token_pull_hand_values():
    """AX-5: pull is the projection of a - f on y - f over |y - f|^2; aside is the orthogonal remainder."""
    p, closer, aside = token_pull([1.0, 1.0], [0.0, 0.0], [2.0, 0.0])
    assert (p, closer, aside) == (0.5, True, 1.0)
    # a on the prior: pull 1, nothing aside; a moved away from the prior: negative pull, not closer.
    assert token_pull([2.0, 0.0], [0.0, 0.0], [2.0, 0.0]) == (1.0, True, 0.0)
    p, closer, aside = token_pull([-1.0, 0.0], [0.0, 0.0], [2.0, 0.0])
    assert p == -0.5 and not closer and aside == 0.0
    with pytest.raises(ValueError, match="undefined"):
        token_pull([1.0], [0.0], [0.0])
    with pytest.raises(ValueError, match="finite vectors"):
        token_pull([1.0, np.nan], [0.0, 0.0], [1.0, 0.0])


def test_tier_delays_and_rows():
    """AX-10: the T sweep runs d = 0, 2, 4 with the sweep tier's seeds and episodes; its rows differ from the main
    rows only in T (part of the eval key), and T = 5 rows keep the keys of the committed cells."""
    assert ex.tier_delays(5, "main") == [0, 1, 2, 3, 4, 5]
    assert ex.tier_delays(5, "sweep") == [0, 4, 5]
    assert ex.tier_delays(5, "tsweep") == [0, 2, 4]
    assert ex.tier_delays(3, "tsweep") == [0, 2]
    b = ex.BUDGETS["full"]
    assert b.seeds_episodes("tsweep") == (1, 50) and b.seeds_episodes("main") == (3, 100)
    task = get_task("drift")
    rows = {r.name: r for r in ex.rows_for(task)}
    for T in ex.TSWEEP_STEPS:
        for base in ex.TSWEEP_ROWS:
            r = rows[f"t{T}_{base}"]
            assert r.num_steps == T and r.tier == "tsweep"
            assert ex.train_key(r, task) == ex.train_key(rows[base], task)
            assert ex.eval_key(r, task) != ex.eval_key(rows[base], task)
    # The consistent rows share the fine-tunes of their Algorithm 1 rows and have their own episodes.
    for a, b_ in (("soft2_clip_consistent", "soft2_clip"), ("hard_soft_sampler_consistent", "hard_soft_sampler")):
        assert ex.train_key(rows[a], task) == ex.train_key(rows[b_], task)
        assert ex.eval_key(rows[a], task) != ex.eval_key(rows[b_], task)
    with pytest.raises(ValueError, match="num_steps"):
        ex.Row("x", "x", "naive", num_steps=0)


def test_tsweep_and_mechanism_sections_from_files(tmp_path):
    """AX-6: the report's T-sweep table reads seed-1 cells (T = 5 from the main rows), the mechanism table
    mechanism.json; both say so when absent."""
    from softrtc.arm.report import _mechanism_section, _tsweep_table

    m = {"budget_values": {"sweep_episodes": 2}, "execute_horizon": 5}
    eps = lambda s, d2: [{"episode": i, "success": s[i], "D2": d2[i]} for i in range(len(s))]  # noqa: E731
    res = {"cells": {("train_hard", 1, 0): eps([1, 0, 1], [0.1, 0.3, 9.0]),
                     ("t10_train_hard", 1, 2): eps([1, 1], [0.2, 0.4])}}
    lines = _tsweep_table(res, m)
    # the first 2 episodes only: success 1/2, D2 (0.1 + 0.3) / 2
    assert "| 5 | Train Hard | 0.50 / 0.2000 | not run | not run |" in lines
    assert "| 10 | Train Hard | not run | 1.00 / 0.3000 | not run |" in lines
    assert _tsweep_table({"cells": {}}, m) == ["The T sweep has not been run."]
    assert "No measurement" in _mechanism_section({"mechanism": None})[0]
    mech = {"checkpoint_sha256_16": "ab", "episodes": 3, "steps": {"consistent": {"2": {
        "tokens": 4, "window_tokens": [2, 3], "intended": 0.5, "pull_median": 0.4, "pull_q25": 0.1, "pull_q75": 0.6,
        "closer_share": 0.75, "unrelated_median": 0.01, "moved_median": 0.2, "success": 1 / 3}}}}
    assert "| 2 | 2, 3 | 0.50 | consistent | 0.40 [0.10, 0.60] | 0.75 | 0.010 | 0.200 | 0.33 |" in \
        _mechanism_section({"mechanism": mech})


def test_recomputed_finetune_may_start_new_cells_only(tmp_path):
    """AX-11: a checkpoint whose digest differs from its folder's record may not extend a cell the recorded
    checkpoint wrote; cells it started itself (listed in its .recomputed.json) may be extended."""
    import hashlib
    import json

    task = get_task("drift")
    out = tmp_path / "drift"
    (out / "finetunes").mkdir(parents=True)
    (out / "episodes").mkdir()
    ckpt = tmp_path / "hard_seed1.npz"
    ckpt.write_bytes(b"a recomputed checkpoint")
    digest = hashlib.sha256(ckpt.read_bytes()).hexdigest()[:16]
    rec = {"key": "hard", "seed": 1, "steps": 800, "final_loss": 0.3, "seconds": 1.0, "sha256_16": "0" * 16,
           "window": None}
    (out / "finetunes" / "hard_seed1.json").write_text(json.dumps(rec))
    cell = out / "episodes" / "k_s1_d0.csv"
    cell.write_text("row\n")
    args = (str(ckpt), "drift", None, 1, 0, 10, 10_000, 0, 60, str(cell))
    budget = ex.BUDGETS["quick"]
    with pytest.raises(ValueError, match="came from the recorded one"):
        ex._check_recorded(out, task, budget, "hard", 1, [args], 10_000, 0, print)
    # The same cell listed as started by this checkpoint: accepted without a replay, and a new cell is added.
    (out / "finetunes" / "hard_seed1.recomputed.json").write_text(json.dumps(
        {"sha256_16": digest, "recorded_sha256_16": "0" * 16, "cells": ["k_s1_d0.csv"]}))
    new = (str(ckpt), "drift", None, 1, 1, 10, 10_000, 0, 60, str(out / "episodes" / "k_s1_d1.csv"))
    ex._check_recorded(out, task, budget, "hard", 1, [args, new], 10_000, 0, print)
    got = json.loads((out / "finetunes" / "hard_seed1.recomputed.json").read_text())
    assert got["cells"] == ["k_s1_d0.csv", "k_s1_d1.csv"]
    # A record of another digest does not vouch for this checkpoint: no committed cell to replay -> refused.
    (out / "finetunes" / "hard_seed1.recomputed.json").write_text(json.dumps(
        {"sha256_16": "f" * 16, "recorded_sha256_16": "0" * 16, "cells": ["k_s1_d0.csv"]}))
    with pytest.raises(ValueError, match="came from the recorded one"):
        ex._check_recorded(out, task, budget, "hard", 1, [args], 10_000, 0, print)
    cell.unlink()
    with pytest.raises(ValueError, match="no committed cell"):
        ex._check_recorded(out, task, budget, "hard", 1, [args], 10_000, 0, print)


def test_mechanism_command_writes_the_measurement(tmp_path, capsys):
    """AX-5: `softrtc arm mechanism` measures both solver steps on the same paired episodes and writes one JSON
    file; at d = 2 (H = 10, s = 5, lam 2) the executed window tokens are j = 2, 3 with weights 2/3 and 1/3.
    Bad options are one usage error before any episode runs."""
    import json

    from softrtc.cli import main

    out = tmp_path / "m.json"
    ck = str(get_task("drift").base_checkpoint())
    assert main(["arm", "mechanism", "--checkpoint", ck, "--delays", "2", "--episodes", "1", "--max-steps", "30",
                 "--out", str(out)]) == 0
    got = json.loads(out.read_text())
    assert set(got["steps"]) == {"algorithm1", "consistent"}
    for step in ("algorithm1", "consistent"):
        e = got["steps"][step]["2"]
        assert e["window_tokens"] == [2, 3] and abs(e["intended"] - 0.5) < 1e-12
        assert e["tokens"] > 0 and 0.0 <= e["closer_share"] <= 1.0
    with pytest.raises(SystemExit) as exc:
        main(["arm", "mechanism", "--checkpoint", ck, "--delays", "0"])
    assert exc.value.code == 2 and "each delay must be an integer in [1, 5]" in capsys.readouterr().err
    assert main(["arm", "mechanism", "--checkpoint", str(tmp_path / "none.npz")]) == 2
    assert "checkpoint must be an arm checkpoint file" in capsys.readouterr().err
