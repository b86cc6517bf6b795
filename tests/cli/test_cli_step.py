"""``softrtc weights --step``: per-token step sizes of the solver step beside the weights ([S-10], [S-13])."""

from __future__ import annotations

import pytest

from softrtc.cli import main


def _table(capsys, argv):
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    out = capsys.readouterr()
    return code, out.out, out.err


def test_weights_prints_step_sizes(capsys):
    """S-10: with --step consistent each delay's weights are followed by c_j / T: (1 - w_j) / T inside the window,
    1 / T on prefix and free tokens (by hand for the default window, H = 8, s = 4, d = 2, T = 5: weights
    1, 1, 2/3, 1/3, 0 give 0.2, 0.2, 1/15 = 0.067, 2/15 = 0.133, 0.2); algorithm1 gives 1 / T everywhere; without
    --step the table is the one it always was."""
    code, out, _ = _table(capsys, ["weights", "--step", "consistent"])
    lines = out.splitlines()
    assert code == 0 and lines[0].endswith("step=consistent T=5")
    i = lines.index("2  4    4  | 1.000 1.000 0.667 0.333 0.000 0.000 0.000 0.000")
    assert lines[i + 1] == "   c/T     | 0.200 0.200 0.067 0.133 0.200 0.200 0.200 0.200"
    code, out, _ = _table(capsys, ["weights", "--step", "algorithm1", "--T", "4"])
    rows = [ln for ln in out.splitlines() if "c/T" in ln]
    assert code == 0 and len(rows) == 5 and all(ln.split("|")[1].split() == ["0.250"] * 8 for ln in rows)
    code, plain, _ = _table(capsys, ["weights"])
    assert code == 0 and "c/T" not in plain and "step=" not in plain
    assert [ln for ln in out.splitlines()[1:] if "c/T" not in ln] == plain.splitlines()[1:]


@pytest.mark.parametrize("argv,msg", [
    (["weights", "--step", "exact"], "argument --step: invalid choice: 'exact' (choose from 'algorithm1', 'consistent')"),
    (["weights", "--T", "3"], "--T applies to --step only"),
    (["weights", "--step", "consistent", "--T", "0"], "--T"),
])
def test_weights_step_options_checked(capsys, argv, msg):
    """S-10, N-11: a bad step name, --T without --step and T outside 1 .. 65536 are errors naming the option."""
    code, _, err = _table(capsys, argv)
    assert code != 0 and msg in err
