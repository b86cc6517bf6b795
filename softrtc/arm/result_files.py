"""Checks of the arm experiment's result files as they are read ([AX-12]).

``softrtc arm report`` and a resumed ``softrtc arm experiment`` read files
that a crash, a hand edit or a copy may have damaged. Each reader here
raises one ``ValueError`` naming the file (and the line of an episode file)
and what is wrong, instead of a report that silently drops, double-counts or
averages damaged values:

* JSON files (``manifest.json``, ``prior_error.json``, fine-tune records)
  must parse whole (a half-written file names itself) and hold no NaN or
  infinity;
* an episode file ``<eval key>_s<seed>_d<delay>.csv`` must hold the
  episodes ``0 .. n-1`` once each, in order, of that seed and delay, with
  ``success`` 0 or 1, ``completion`` in [0, 1], finite ``D1..D3``,
  boundary jump and mean ``|a|``, a delay among the task's executable delays,
  a seed and at most as many episodes as the manifest's budget gives the rows
  that share the file.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

__all__ = ["read_json", "check_manifest", "check_episode_file", "check_prior", "check_finetune"]

_INT_FIELDS = ("seed", "delay", "episode", "env_seed", "success", "completed", "steps", "success_step")
_FINITE_FIELDS = ("completion", "D1", "D2", "D3", "boundary", "mean_abs_action")


def _reject_constant(name: str):
    raise ValueError(f"{name} is not a finite number")


def read_json(path, what: str):
    """The JSON value of ``path``; a file that does not parse whole, or holds NaN or infinity, is a
    ValueError naming ``what`` and the file ([AX-12])."""
    path = Path(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"), parse_constant=_reject_constant)
    except (ValueError, UnicodeDecodeError) as exc:  # JSONDecodeError is a ValueError
        raise ValueError(f"{what} {str(path)!r} is damaged (not valid JSON with finite numbers: {exc}); "
                         f"restore it or remove it to recompute it") from None
    except RecursionError:
        raise ValueError(f"{what} {str(path)!r} is damaged (JSON nested too deeply)") from None


def check_manifest(manifest, path) -> dict:
    """``manifest`` if it has the fields a report and a resume read: task, execute horizon, ``H``, budget
    values and a row table with each row's tier and eval key ([AX-4])."""
    where = f"manifest {str(path)!r}"
    if not isinstance(manifest, dict):
        raise ValueError(f"{where} must hold a JSON object, got {type(manifest).__name__}")
    for key, kind in (("task", str), ("execute_horizon", int), ("H", int), ("budget_values", dict), ("rows", dict)):
        if not isinstance(manifest.get(key), kind) or isinstance(manifest.get(key), bool):
            raise ValueError(f"{where} has no valid {key!r} (expected {kind.__name__})")
    if not 1 <= manifest["execute_horizon"] < manifest["H"]:
        raise ValueError(f"{where}: execute_horizon must lie in [1, H - 1], got {manifest['execute_horizon']}")
    for row, info in manifest["rows"].items():
        if not isinstance(info, dict) or not isinstance(info.get("eval_key"), str) \
                or not isinstance(info.get("tier"), str):
            raise ValueError(f"{where}: row {row!r} has no eval_key and tier")
    return manifest


def _budget_counts(manifest, key: str) -> tuple[int, int, bool]:
    """Most seeds and episodes any row sharing eval ``key`` runs, and whether one of them is the base."""
    b = manifest["budget_values"]
    seeds = episodes = 0
    base = False
    for info in manifest["rows"].values():
        if info["eval_key"] != key:
            continue
        main = info["tier"] == "main"
        seeds = max(seeds, b.get("main_seeds" if main else "sweep_seeds", 0))
        episodes = max(episodes, b.get("main_episodes" if main else "sweep_episodes", 0))
        base = base or info.get("train_key") is None
    return seeds, episodes, base


def check_episode_file(path, episodes: list[dict], manifest) -> list[dict]:
    """``episodes`` (the rows of ``path`` as :func:`softrtc.arm.experiment.read_episodes` types them) if the
    file is a valid cell of ``manifest`` ([AX-4], [AX-12]); line numbers count the header as line 1."""
    path = Path(path)
    try:
        key, seed_part, delay_part = path.stem.rsplit("_", 2)
        if seed_part[:1] != "s" or delay_part[:1] != "d" or not (seed_part[1:].isascii() and seed_part[1:].isdigit()
                                                                and delay_part[1:].isascii()
                                                                and delay_part[1:].isdigit()):
            raise ValueError
        seed, delay = int(seed_part[1:]), int(delay_part[1:])
    except ValueError:
        raise ValueError(f"episode file {str(path)!r} is not named <eval key>_s<seed>_d<delay>.csv") from None
    n_seeds, n_episodes, base = _budget_counts(manifest, key)
    if n_episodes == 0:
        raise ValueError(f"episode file {str(path)!r}: eval key {key!r} belongs to no row of the manifest")
    max_delay = min(manifest["execute_horizon"], manifest["H"] - manifest["execute_horizon"])
    if delay > max_delay:
        raise ValueError(f"episode file {str(path)!r}: delay {delay} is not among the task's delays "
                         f"0 .. {max_delay}")
    if not ((seed == 0 and base) or 1 <= seed <= n_seeds):
        raise ValueError(f"episode file {str(path)!r}: seed {seed} is not among the budget's seeds of its rows "
                         f"({'0 (the base)' if base else f'1 .. {n_seeds}'})")
    if len(episodes) > n_episodes:
        raise ValueError(f"episode file {str(path)!r} holds {len(episodes)} episodes; the budget gives its rows at "
                         f"most {n_episodes}")
    for i, ep in enumerate(episodes):
        _check_episode(ep, i, seed, delay, f"episode file {str(path)!r} line {i + 2}")
    return episodes


def _check_episode(ep: dict, index: int, seed: int, delay: int, where: str) -> None:
    if ep["episode"] != index:
        what = "repeats an episode" if ep["episode"] < index else "skips an episode"
        raise ValueError(f"{where} {what}: episode {ep['episode']}, expected {index} (episodes 0 .. n-1 once each)")
    if (ep["seed"], ep["delay"]) != (seed, delay):
        raise ValueError(f"{where}: seed {ep['seed']} and delay {ep['delay']} differ from the file name's "
                         f"s{seed} and d{delay}")
    if ep["success"] not in (0, 1):
        raise ValueError(f"{where}: success must be 0 or 1, got {ep['success']}")
    if not 0.0 <= ep["completion"] <= 1.0:  # also False for NaN
        raise ValueError(f"{where}: completion must lie in [0, 1], got {ep['completion']}")
    if ep["completed"] < 0 or ep["steps"] < 1:
        raise ValueError(f"{where}: completed must be >= 0 and steps >= 1, got {ep['completed']} and {ep['steps']}")
    for k in _FINITE_FIELDS[1:]:
        if not math.isfinite(ep[k]):
            raise ValueError(f"{where}: {k} must be a finite number, got {ep[k]}")


def read_episode_rows(path) -> list[dict]:
    """The typed rows of an episode file, each field checked for its type: a value that is not an integer
    or a number is an error naming the file, the line and the field."""
    import csv

    out = []
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        missing = [k for k in ("row",) + _INT_FIELDS + _FINITE_FIELDS if k not in (reader.fieldnames or ())]
        if missing:
            raise ValueError(f"episode file {str(path)!r} lacks the columns {missing}")
        for line, r in enumerate(reader, start=2):
            d = {"row": r["row"]}
            for k in _INT_FIELDS + _FINITE_FIELDS:
                text = r[k]
                try:
                    if text is None:
                        raise ValueError
                    d[k] = int(text) if k in _INT_FIELDS else float(text)
                except ValueError:
                    kind = "an integer" if k in _INT_FIELDS else "a number"
                    raise ValueError(f"episode file {str(path)!r} line {line}: {k} must be {kind}, "
                                     f"got {text!r}") from None
            out.append(d)
    return out


def check_prior(prior, path) -> dict:
    """``prior_error.json`` ([AX-5]): ``sigma`` a table of finite non-negative numbers, ``rms`` per delay."""
    where = f"prior error {str(path)!r}"
    if not isinstance(prior, dict) or not isinstance(prior.get("sigma"), list) or not isinstance(prior.get("rms"),
                                                                                                     dict):
        raise ValueError(f"{where} must hold an object with 'sigma' (a table) and 'rms' (per delay)")
    for i, row in enumerate(prior["sigma"]):
        if not isinstance(row, list) or not all(_number(x) and x >= 0 for x in row):
            raise ValueError(f"{where}: sigma row {i} must be a list of finite numbers >= 0, got {row!r}")
    return prior


def check_finetune(rec, path) -> dict:
    """A fine-tune record ([AX-4]): key, seed, steps, a finite final loss and the checkpoint digest."""
    where = f"fine-tune record {str(path)!r}"
    if not isinstance(rec, dict):
        raise ValueError(f"{where} must hold a JSON object, got {type(rec).__name__}")
    if not isinstance(rec.get("sha256_16"), str) or len(rec["sha256_16"]) != 16:
        raise ValueError(f"{where} has no 16-digit checkpoint digest 'sha256_16'")
    if not _number(rec.get("final_loss")) or not isinstance(rec.get("steps"), int) or rec["steps"] < 1:
        raise ValueError(f"{where}: final_loss must be a finite number and steps an integer >= 1, got "
                         f"{rec.get('final_loss')!r} and {rec.get('steps')!r}")
    return rec


def _number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
