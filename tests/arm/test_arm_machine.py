"""Result files record the CPU model; results repeat bitwise on one machine ([S-15], [AX-9])."""

from __future__ import annotations

import csv

import pytest

pytest.importorskip("jax")

from softrtc._machine import cpu_model  # noqa: E402
from softrtc.arm import experiment as E  # noqa: E402
from softrtc.arm.tasks import get_task  # noqa: E402


def _cell(path, episodes, row):
    task = get_task("drift")
    return E._run_cell((str(task.base_checkpoint()), "drift", row, 0, 2, episodes, 10_000, 0, 12, str(path)))


def test_cells_record_the_cpu_model_and_repeat_bitwise(tmp_path):
    """S-15, AX-9: a cell's CSV has a cpu_model column holding this machine's model; the same cell computed
    twice here is byte-identical; a file without the column (written before it existed) still reads and is
    extended with its old episodes unchanged and the new ones marked."""
    row = E.Row("soft2_clip", "", "train_soft", "soft", E.DEFAULT_WINDOW, step="consistent")
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    _cell(a, 1, row)
    _cell(b, 1, row)
    assert a.read_bytes() == b.read_bytes()
    with open(a, newline="") as f:
        rows = list(csv.DictReader(f))
    assert rows[0]["cpu_model"] == cpu_model() and cpu_model()
    # An older file: the same episode without the column.
    old = [{k: v for k, v in rows[0].items() if k != "cpu_model"}]
    with open(b, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=[k for k in E.EPISODE_FIELDS if k != "cpu_model"])
        w.writeheader()
        w.writerows(old)
    before = E.read_episodes(b)
    _cell(b, 2, row)
    with open(b, newline="") as f:
        ext = list(csv.DictReader(f))
    assert [r["cpu_model"] for r in ext] == ["", cpu_model()]
    assert E.read_episodes(b)[0] == before[0] and E.read_episodes(a)[0] == before[0]


def test_manifest_cpu_models():
    """AX-9: the manifest lists every CPU model that wrote into the folder; an older manifest without the key
    reads as none; a malformed entry is an error naming it."""
    me = cpu_model()
    assert E.cpu_models(None) == [me]
    assert E.cpu_models({"task": "drift"}) == [me]
    assert E.cpu_models({"cpu_models": ["Z other", me]}) == sorted({"Z other", me})
    with pytest.raises(ValueError, match=r"manifest\['cpu_models'\] must be a list of strings"):
        E.cpu_models({"cpu_models": "x86"})
