"""Generate the conformance vectors of conformance/vectors/ from the NumPy reference ([CF-1]..[CF-6]).

The cases of each chapter, and so the coverage of [CF-4], are built by the ``gen_<chapter>`` functions of
:mod:`.cases_training` and :mod:`.cases_runtime`.

    python -m softrtc.conformance.generate [--out DIR]
    softrtc conformance generate [--out DIR]

Every random input comes from ``numpy.random.default_rng`` with a fixed seed and
every number is written with Python's shortest round-trip ``repr``, keys sorted,
so two runs on one machine give byte-identical files ([CF-3]); on another
machine they agree within :data:`REGEN_TOL` (:func:`compare`,
``softrtc conformance generate --check``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import tempfile
from pathlib import Path

from .._cli_util import command_error, output_dir
from . import FORMAT_VERSION, SPEC_VERSION, vectors_dir
from .cases_base import REGEN_TOL, _plain
from .cases_runtime import gen_conventions, gen_executor, gen_guidance, gen_metrics, gen_sampler, gen_velocity
from .cases_step import gen_sampler_step
from .cases_training import gen_corruption, gen_delays, gen_endpoints, gen_loss, gen_weights
from .vectors_io import parse_json

# ---------------------------------------------------------------- files

FILES = {
    "endpoints": ("E", "Endpoint rules e(d) (spec/01-weights.md 1.1)", gen_endpoints),
    "weights": ("W", "Token weights, schedules, parametrizations, overflow (spec/01-weights.md 1.2)", gen_weights),
    "delays": ("D", "Training delay distributions and inverse-CDF draws (spec/02-training.md 2.1)", gen_delays),
    "corruption": ("C", "Weighted corruption and per-token times (spec/02-training.md 2.2)", gen_corruption),
    "loss": ("L", "Weighted flow-matching loss (spec/02-training.md 2.3)", gen_loss),
    "velocity": ("F", "Reference velocity field and its VJP (spec/03-inference.md 3.1)", gen_velocity),
    "sampler": ("S", "Naive and training-time RTC sampler traces (spec/03-inference.md 3.2)", gen_sampler),
    "sampler_step": ("S", "Training-time RTC sampler with a named solver step: Algorithm 1 and the time-consistent "
                     "step (spec/03-inference.md 3.2.1)", gen_sampler_step),
    "guidance": ("G", "Inference-time RTC guidance weights and guided-sampler traces (spec/03-inference.md 3.3)",
                 gen_guidance),
    "executor": ("X", "Prior shift and asynchronous execution (spec/04-execution.md)", gen_executor),
    "metrics": ("M", "Metrics on executed sequences (spec/05-metrics.md)", gen_metrics),
    "conventions": ("V", "Per-token times through the flipped-time mapping (spec/06-conventions.md)",
                    gen_conventions),
}


# Vector files written by hand from the spec's worked examples and closed forms, independent of this
# generator ([CF-33]); the generator only copies and indexes them.
HAND_FILES = ("worked_examples.json",)


def _dumps(obj) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)


def render(name: str) -> str:
    """Text of one vector file: header keys sorted, then one case per line ([CF-3])."""
    if not isinstance(name, str) or name not in FILES:
        raise ValueError(f"name must be one of the vector files {sorted(FILES)}, got {name!r}")
    chapter, title, fn = FILES[name]
    res = fn()
    cases, extra = (res if isinstance(res, tuple) else (res, {}))
    header = {"format_version": FORMAT_VERSION, "spec_version": SPEC_VERSION, "chapter": chapter, "title": title,
              "generator": "softrtc.conformance.generate", "reference": "softrtc.reference"}
    header.update(_plain(extra))
    lines = ["{"]
    lines += [f"{_dumps(k)}:{_dumps(header[k])}," for k in sorted(header)]
    lines.append('"cases":[')
    lines.append(",\n".join(_dumps(case) for case in cases.cases))
    lines.append("]}")
    return "\n".join(lines) + "\n"


def generate(out_dir=None) -> dict:
    """Write every vector file and index.json into ``out_dir`` ([CF-1]); return {file: size in bytes}."""
    if out_dir is not None and not isinstance(out_dir, (str, os.PathLike)):
        raise ValueError(f"out_dir must be a path (str or os.PathLike), got {type(out_dir).__name__}")
    out = Path(out_dir) if out_dir is not None else vectors_dir()
    if out.exists() and not out.is_dir():
        raise ValueError(f"out_dir must be a directory, got the file {out}")
    out.mkdir(parents=True, exist_ok=True)
    sizes, index = {}, {}
    for name in FILES:
        text = render(name)
        (out / f"{name}.json").write_text(text, encoding="ascii")
        sizes[f"{name}.json"] = len(text)
        index[f"{name}.json"] = {"chapter": FILES[name][0], "cases": text.count('"id":'),
                                 "sha256": hashlib.sha256(text.encode("ascii")).hexdigest()}
    for name in HAND_FILES:  # written by hand ([CF-33]): copied as they are and indexed
        raw = (vectors_dir() / name).read_bytes()
        if (out / name).resolve() != (vectors_dir() / name).resolve():
            (out / name).write_bytes(raw)
        sizes[name] = len(raw)
        index[name] = {"chapter": "HAND", "cases": raw.count(b'"id":'), "sha256": hashlib.sha256(raw).hexdigest()}
    idx = _dumps({"format_version": FORMAT_VERSION, "spec_version": SPEC_VERSION, "files": index}) + "\n"
    (out / "index.json").write_text(idx, encoding="ascii")
    sizes["index.json"] = len(idx)
    return sizes


def _walk_diff(a, b, where: str, worst: list) -> None:
    """Raises ValueError where ``a`` and ``b`` differ other than in the value of a real number; collects
    (|a - b|, excess over REGEN_TOL) of the reals in ``worst``."""
    if isinstance(a, dict) and isinstance(b, dict):
        if list(a) != list(b):
            raise ValueError(f"{where}: keys differ ({sorted(a)} against {sorted(b)})")
        for k in a:
            _walk_diff(a[k], b[k], f"{where}/{k}", worst)
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            raise ValueError(f"{where}: lengths differ ({len(a)} against {len(b)})")
        for i, (x, y) in enumerate(zip(a, b)):
            _walk_diff(x, y, f"{where}[{i}]", worst)
    elif type(a) is float and type(b) is float:
        diff = abs(a - b)
        worst.append((diff, diff / (REGEN_TOL["abs"] + REGEN_TOL["rel"] * abs(b)), where))
    elif type(a) is not type(b) or a != b:
        raise ValueError(f"{where}: {a!r} against {b!r}")


def compare(got_dir, want_dir) -> dict:
    """Compare two vector directories file by file ([CF-3]).

    Returns ``{file: {"identical": bool, "max_abs_diff": float, "within": bool, "worst": str | None}}``
    for every ``*.json`` of ``want_dir`` except ``index.json`` (whose digests follow the bytes):
    ``identical`` when the bytes agree; otherwise the files must have the same
    structure, strings, booleans and integers ([CF-23]), and ``within`` tells
    whether every real agrees within :data:`REGEN_TOL`. Raises ValueError when
    a file is missing or differs in anything but the value of a real.
    """
    dirs = []
    for name, d in (("got_dir", got_dir), ("want_dir", want_dir)):
        if not isinstance(d, (str, os.PathLike)) or not Path(d).is_dir():
            raise ValueError(f"{name} must be an existing directory, got {d!r}")
        dirs.append(Path(d))
    got, want = dirs
    names = sorted(p.name for p in want.glob("*.json") if p.name != "index.json")
    if not names:
        raise ValueError(f"want_dir {want} holds no vector files")
    out = {}
    for name in names:
        if not (got / name).is_file():
            raise ValueError(f"{name} is missing from {got}")
        a, b = (got / name).read_bytes(), (want / name).read_bytes()
        if a == b:
            out[name] = {"identical": True, "max_abs_diff": 0.0, "within": True, "worst": None}
            continue
        worst: list = []
        _walk_diff(parse_json(a), parse_json(b), name, worst)  # [CF-23] ints stay ints
        top = max(worst, key=lambda w: w[1], default=(0.0, 0.0, None))
        out[name] = {"identical": False, "max_abs_diff": max((w[0] for w in worst), default=0.0),
                     "within": top[1] <= 1.0, "worst": top[2]}
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=output_dir(), default=None, help="output directory (default: the vectors shipped with softrtc, conformance/vectors/ in a source "
                             "checkout)")
    parser.add_argument("--check", action="store_true",
                        help="regenerate into a temporary directory and compare with --out (default: the shipped "
                             "vectors) instead of writing; exit 1 unless every number agrees within "
                             f"{REGEN_TOL['abs']:g} + {REGEN_TOL['rel']:g} |x|")
    parser.add_argument("--rollouts", action="store_true",
                        help="write (or --check) the rollout vectors of [CR-10] instead, in the folder rollouts/ of "
                             "--out; needs jax (closed-loop reference episodes on the arm, about a minute)")


def _check(prog: str, out_dir) -> int:
    want = Path(out_dir) if out_dir is not None else vectors_dir()
    if not want.is_dir():
        raise ValueError(f"--out must be an existing directory of vector files with --check, got {want}")
    if not any(p.name != "index.json" for p in want.glob("*.json")):  # nothing to check against: a usage error
        raise ValueError(f"--out {want} holds no vector files to check the regeneration against")
    with tempfile.TemporaryDirectory() as tmp:
        generate(tmp)
        try:
            res = compare(tmp, want)
        except ValueError as exc:
            print(f"{prog}: the regenerated vectors differ from {want} beyond rounding: {exc}", file=sys.stderr)
            return 1
    for name, r in res.items():
        status = ("byte-identical" if r["identical"] else
                  f"max |diff| {r['max_abs_diff']:.2e} ({'within' if r['within'] else 'BEYOND'} rounding)")
        print(f"{name:20s} {status}")
    ok = all(r["within"] for r in res.values())
    print("regeneration agrees" if ok else "regeneration differs beyond rounding", f"with {want}")
    return 0 if ok else 1


def _rollouts(prog: str, args) -> int:
    """`generate --rollouts [--check]` ([CR-10])."""
    from . import rollout_vectors

    if args.check:
        diffs = rollout_vectors.check_generation(args.out)
        for d in diffs[:20]:
            print(f"{prog}: differs: {d}", file=sys.stderr)
        print("rollout vectors: regeneration agrees" if not diffs else f"rollout vectors: {len(diffs)} differences")
        return 0 if not diffs else 1
    sizes = rollout_vectors.generate(args.out)
    for name, size in sizes.items():
        print(f"{name:20s} {size:>9d} bytes")
    print(f"total {sum(sizes.values())} bytes in {rollout_vectors.rollouts_dir(args.out)}")
    return 0


def run_from_args(args) -> int:
    prog = getattr(args, "_prog", "softrtc conformance generate")
    try:
        if getattr(args, "rollouts", False):
            return _rollouts(prog, args)
        if getattr(args, "check", False):
            return _check(prog, args.out)
        sizes = generate(args.out)
    except BrokenPipeError:
        raise  # the reader of stdout went away: the command line stops quietly ([N-11])
    except (ValueError, OSError) as exc:
        return command_error(prog, exc)
    for name, size in sizes.items():
        print(f"{name:20s} {size:>9d} bytes")
    print(f"total {sum(sizes.values())} bytes in {Path(args.out) if args.out else vectors_dir()}")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m softrtc.conformance.generate",
                                     description="Generate the softrtc conformance vectors from the NumPy reference.")
    add_arguments(parser)
    parser.set_defaults(_prog=parser.prog)
    return run_from_args(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
