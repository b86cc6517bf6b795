"""Rollout vectors: the requests of real closed-loop reference episodes, replayed open loop ([CR-10], [CR-15]).

    softrtc conformance generate --rollouts [--out DIR]     writes DIR/rollouts/ (rollouts_arm.json,
                                                            rollouts_kinetix.json, index.json)
    softrtc conformance rollout --impl X --vectors [DIR] [--env arm|kinetix]   replays them

The generator runs the reference in closed loop on the arm and on a Kinetix
level and records, for the first requests of a few episodes of each method of
:data:`METHODS` (:data:`PLAN`), the request's arguments and the reference's
chunk and executed actions. Replaying gives every implementation the recorded
inputs, so it is compared request by request without divergence compounding,
on the served field the file's header names ([CR-3], [CR-14]: the arm's
checkpoint and its SHA-256; the Kinetix level, checkpoint or init seed and
the policy's SHA-256); a replay that cannot serve that same field is refused.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import time
from pathlib import Path

import numpy as np

from softrtc._files import write_atomic
from softrtc.reference._validate import check_choice

from . import SPEC_VERSION, vectors_dir
from .results import UNSUPPORTED_CASE, CaseResult, RunResult
from .rollout_diagnose import TOL
from .rollout_loop import EXEC_REQS, Checker, Episode, Settings, chunk_requirements, run_episode
from .compare import CaseFailure, compare
from .vectors_io import parse_json

ROLLOUT_VECTOR_FORMAT = "1.0"
FILE = "rollouts_arm.json"
METHODS = ("naive", "train_hard", "train_soft", "inference_hard", "inference_soft")
EPISODES = 2
REQUESTS = 20
# One vector file per world, each self-describing (its header's env and policy, [CR-15]).
FILES = {"arm": FILE, "kinetix": "rollouts_kinetix.json"}
# (episodes per method, requests per episode) of each file ([CR-10], [CR-15]): a Kinetix request carries the
# level's 679-value observation, so fewer requests keep its file under 1 MB.
PLAN = {"arm": (EPISODES, REQUESTS), "kinetix": (2, 16)}
SEED = 7
FUNCTION = "rollout_chunk"
# Requests in a row that lose the implementation's process before the remaining ones fail unrun ([CF-30]).
MAX_LOST_IN_A_ROW = 3
ARGS = ("obs", "prev", "noise", "method", "s", "d", "arrival", "T", "window", "max_guidance")


def rollouts_dir(base=None) -> Path:
    """The folder of the rollout vectors: ``rollouts/`` inside the vector folder ([CR-10])."""
    return (vectors_dir() if base is None else Path(base)) / "rollouts"


def _dumps(obj) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)


def _plain(v):
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    return v


def _checkpoint_rel(path: str) -> str:
    return "softrtc/arm/checkpoints/" + path.replace("\\", "/").split("softrtc/arm/checkpoints/")[-1]


def record_cases(field, world, env: str = "arm") -> list:
    """The cases of the rollout vectors: closed-loop reference episodes, the first requests of each (PLAN)."""
    from .rollout_impls import ReferenceRollout

    ref = ReferenceRollout()
    episodes, requests = PLAN[env]
    settings = Settings(METHODS, episodes, (0, 1, 2, 3, 4, 5), requests * field.s, seed=SEED)
    first = ["CR-10"] if env == "arm" else ["CR-10", "CR-15"]
    cases = []
    for method in METHODS:
        for i in range(episodes):
            def answer(c, args, method=method, i=i):
                out = ref.rollout_chunk(field, **args)
                reqs = chunk_requirements(method, args["prev"] is None) + [r for r in EXEC_REQS if r != "CR-2"]
                cases.append({"id": f"CR.{env}.{method}.ep{i:03d}.r{c:03d}", "function": "rollout_chunk",
                              "requirements": first + reqs, "tolerance": dict(TOL),
                              "args": {k: _plain(args[k]) for k in ARGS},
                              "expected": {k: _plain(out[k]) for k in ("chunk", "executed")}})
                return out
            run_episode(answer, field, world, settings, method, i)
    return cases


def _header(env: str, field) -> dict:
    episodes, requests = PLAN[env]
    head = {"format_version": ROLLOUT_VECTOR_FORMAT, "spec_version": SPEC_VERSION, "chapter": "CR",
            "generator": "softrtc.conformance.rollout_vectors", "reference": "softrtc.reference", "env": env,
            "episodes": episodes, "requests": requests, "methods": list(METHODS)}
    if env == "arm":
        head.update(title="Rollout requests of closed-loop reference episodes on the arm (spec/42-rollouts.md)",
                    task="drift", checkpoint=_checkpoint_rel(field.checkpoint),
                    checkpoint_sha256=hashlib.sha256(Path(field.checkpoint).read_bytes()).hexdigest())
    else:
        head.update(title="Rollout requests of closed-loop reference episodes on a Kinetix level "
                          "(spec/42-rollouts.md)", seed=SEED, obs_dim=field.obs_dim, action_dim=field.action_dim,
                    H=field.H, s=field.s, T=field.T, **field.describe())
    return head


def _write_file(folder: Path, name: str, header: dict, cases: list) -> str:
    lines = ["{"] + [f"{_dumps(k)}:{_dumps(header[k])}," for k in sorted(header)] + ['"cases":[']
    lines.append(",\n".join(_dumps(c) for c in cases))
    lines.append("]}")
    text = "\n".join(lines) + "\n"
    write_atomic(folder / name, lambda f: f.write(text.encode("ascii")), binary=True)
    return text


def open_env(env: str, checkpoint=None) -> tuple:
    """``(field, world)`` the vectors of ``env`` are recorded on, cut at the plan's requests ([CR-10], [CR-15])."""
    from .rollout import open_world

    check_choice("env", env, tuple(FILES))
    if env == "arm":
        from .rollout_field import ServedField

        return open_world("arm", checkpoint, max_steps=PLAN["arm"][1] * ServedField(checkpoint).s)
    if checkpoint is not None:
        raise ValueError("checkpoint serves another arm checkpoint; the Kinetix vectors serve the default policy")
    from softrtc.kinetix.protocol import EXECUTE_HORIZON

    return open_world("kinetix", max_steps=PLAN["kinetix"][1] * EXECUTE_HORIZON)


def generate(out_dir=None, checkpoint=None, envs=tuple(FILES)) -> dict:
    """Write the vector file of each env in ``envs`` and their ``index.json`` into ``rollouts_dir(out_dir)``;
    returns {file: bytes}. ``checkpoint`` (arm only) serves another arm checkpoint."""
    if isinstance(envs, str) or not envs or any(e not in FILES for e in envs):
        raise ValueError(f"envs must be a non-empty sequence of {tuple(FILES)}, got {envs!r}")
    out = rollouts_dir(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sizes, listed = {}, {}
    for env in FILES:
        if env not in envs:
            continue
        field, world = open_env(env, checkpoint if env == "arm" else None)
        cases = record_cases(field, world, env)
        text = _write_file(out, FILES[env], _header(env, field), cases)
        sizes[FILES[env]] = len(text)
        listed[FILES[env]] = {"chapter": "CR", "env": env, "cases": len(cases),
                              "sha256": hashlib.sha256(text.encode("ascii")).hexdigest()}
    index = {"format_version": ROLLOUT_VECTOR_FORMAT, "spec_version": SPEC_VERSION, "files": listed}
    idx = _dumps(index) + "\n"
    write_atomic(out / "index.json", lambda f: f.write(idx.encode("ascii")), binary=True)
    sizes["index.json"] = len(idx)
    return sizes


def _folder(folder) -> Path:
    folder = rollouts_dir() if folder is None else Path(folder)
    if (folder / "rollouts").is_dir() and not (folder / "index.json").is_file():
        folder = folder / "rollouts"
    return folder


def listed_envs(folder=None) -> tuple:
    """The envs whose vector files the index of ``folder`` lists, in the order of :data:`FILES`."""
    folder = _folder(folder)
    try:
        index = parse_json((folder / "index.json").read_text(encoding="utf-8"))
    except OSError as exc:
        raise ValueError(f"cannot read the rollout vectors in {folder}: {exc}") from None
    files = index.get("files") if isinstance(index, dict) else None
    if not isinstance(files, dict):
        raise ValueError(f"{folder / 'index.json'} has no 'files' mapping")
    return tuple(env for env, name in FILES.items() if name in files)


def load(folder=None, env: str = "arm") -> tuple:
    """``(header, cases)`` of the rollout vectors of ``env`` in ``folder`` (default the shipped ones), checked
    against ``index.json`` (digest, case count, format, env) before any case is read ([CR-10], as [CF-25])."""
    check_choice("env", env, tuple(FILES))
    folder = _folder(folder)
    name = FILES[env]
    try:
        index = parse_json((folder / "index.json").read_text(encoding="utf-8"))
        raw = (folder / name).read_bytes()
    except OSError as exc:
        raise ValueError(f"cannot read the rollout vectors in {folder}: {exc}") from None
    entry = index.get("files", {}).get(name) if isinstance(index, dict) else None
    if not isinstance(entry, dict) or entry.get("sha256") != hashlib.sha256(raw).hexdigest():
        raise ValueError(f"{folder / name} does not match the SHA-256 listed in {folder / 'index.json'}")
    doc = parse_json(raw.decode("ascii"))
    if str(doc.get("format_version", "")).split(".")[0] != ROLLOUT_VECTOR_FORMAT.split(".")[0]:
        raise ValueError(f"{folder / name} has format_version {doc.get('format_version')!r}; this runner reads "
                         f"{ROLLOUT_VECTOR_FORMAT}")
    if doc.get("env") != env:
        raise ValueError(f"{folder / name} holds the vectors of env {doc.get('env')!r}, not {env!r}")
    cases = doc.get("cases")
    if not isinstance(cases, list) or len(cases) != entry.get("cases"):
        raise ValueError(f"{folder / name} does not hold the {entry.get('cases')} cases index.json lists")
    for c in cases:
        if not isinstance(c, dict) or set(c.get("args", {})) != set(ARGS) \
                or set(c.get("expected", {})) != {"chunk", "executed"}:
            raise ValueError(f"{folder / name}: case {c.get('id') if isinstance(c, dict) else c!r} lacks the "
                             f"arguments {ARGS} or the outputs chunk, executed")
    return doc, cases


def field_for(header: dict):
    """The served field a vector file was recorded with, rebuilt from its header ([CR-10], [CR-15]);
    ValueError when this installation cannot serve the same one (checkpoint or policy digest differs)."""
    if header.get("env") == "arm":
        from .rollout_field import ServedField

        field = ServedField()
        check_checkpoint(header, field.checkpoint)
        return field
    from .rollout_kinetix import KinetixField

    ck = header.get("checkpoint")
    if ck is not None:
        import softrtc

        here = Path(softrtc.__file__).resolve().parent / ck
        ck = here if here.is_file() else Path(ck)
    try:
        field = KinetixField(header.get("level"), ck, header.get("init_seed") if ck is None else None)
    except (ValueError, OSError) as exc:
        raise ValueError(f"the Kinetix rollout vectors' policy (level {header.get('level')!r}, checkpoint {ck}, "
                         f"init seed {header.get('init_seed')}) cannot be served: {exc}") from None
    if field.about["policy_sha256"] != header.get("policy_sha256"):
        raise ValueError(f"the Kinetix policy served here (SHA-256 {field.about['policy_sha256']}) is not the one "
                         f"the rollout vectors were recorded with (SHA-256 {header.get('policy_sha256')})")
    return field


def _args(case: dict) -> dict:
    a = dict(case["args"])
    for k in ("obs", "prev", "noise"):
        if a[k] is not None:
            a[k] = np.asarray(a[k], np.float64)
    return a


def replay(impl=None, *, impl_cmd=None, vectors_dir=None, env: str | None = "arm", in_process: bool = False,
           timeout: float = 60.0) -> dict:
    """Every recorded request of the vector file of ``env`` (None: every file the index lists) against an
    implementation, open loop ([CR-10], [CR-15]); {"result": RunResult}. Each file is served its own field."""
    from .rollout import open_impl

    envs = listed_envs(vectors_dir) if env is None else (check_choice("env", env, tuple(FILES)),)
    if not envs:
        raise ValueError("the rollout vectors' index lists no vector file")
    loaded = [(e, *load(vectors_dir, e)) for e in envs]
    fields = [field_for(header) for _, header, _ in loaded]  # every policy checked before any request
    t0 = time.perf_counter()
    out, under, header = [], None, loaded[0][1]
    for (e, header, cases), field in zip(loaded, fields):
        under = open_impl(impl, impl_cmd, field, in_process, timeout)
        try:
            out += replay_cases(under, field, cases, FILES[e])
        finally:
            under.close()
    res = RunResult(impl if impl is not None else impl_cmd, under.name, under.time_convention,
                    str(header.get("format_version")), [str(header.get("spec_version"))], out,
                    time.perf_counter() - t0, under.isolation)
    return {"result": res}


def check_checkpoint(header: dict, path) -> None:
    """ValueError unless the checkpoint file ``path`` is the one the rollout vectors were recorded with."""
    if hashlib.sha256(Path(path).read_bytes()).hexdigest() != header.get("checkpoint_sha256"):
        raise ValueError(f"the served checkpoint {path} is not the one the rollout vectors were "
                         f"recorded with ({header.get('checkpoint')}, SHA-256 {header.get('checkpoint_sha256')})")


def replay_cases(under, field, cases: list, name: str = FILE) -> list:
    """One CaseResult per recorded request answered by ``under`` (an opened implementation, [CR-4]) on the
    served ``field`` ([CR-10]): NotImplementedError makes the case unsupported ([CR-2], [CF-26]), any other
    failure fails it; after MAX_LOST_IN_A_ROW requests in a row that lose the child, the rest fail unrun."""
    from .rollout import RequestLost

    checker = Checker(field, "vectors")
    out, lost = [], []
    for n, case in enumerate(cases):
        if len(lost) >= MAX_LOST_IN_A_ROW:
            out.append(CaseResult(case["id"], name, FUNCTION, case["requirements"], "fail", float("inf"),
                                  f"not run: the implementation's process was lost on {len(lost)} requests in "
                                  f"a row (last: {lost[-1]}) ([CF-30])"))
            continue
        args = _args(case)
        ep = Episode(args["method"], 0, 0)
        t1 = time.perf_counter()
        try:
            got = under.answer(n, args)
        except NotImplementedError as exc:
            out.append(CaseResult(case["id"], name, FUNCTION, case["requirements"], "unsupported", 0.0,
                                  f"{UNSUPPORTED_CASE}: {exc}"))
            lost.clear()
            continue
        except Exception as exc:  # noqa: BLE001 - the implementation's failure is the case's
            out.append(CaseResult(case["id"], name, FUNCTION, case["requirements"], "fail", float("inf"),
                                  f"{type(exc).__name__}: {str(exc)[:300]}", time.perf_counter() - t1))
            lost = lost + [case["id"]] if isinstance(exc, RequestLost) else []
            continue
        lost.clear()
        out.append(_judge(case, got, checker, ep, args, time.perf_counter() - t1, name))
    return out


def _judge(case: dict, got, checker, ep, args, seconds: float, name: str = FILE) -> CaseResult:
    """One replayed request: both outputs within the case's tolerance; a failure is diagnosed ([CR-9])."""
    worst, msgs, reqs = 0.0, [], list(case["requirements"])
    try:
        for key in ("chunk", "executed"):
            worst = max(worst, compare(key, got[key], case["expected"][key], case["tolerance"]))
    except (CaseFailure, KeyError, TypeError) as exc:
        ratio = getattr(exc, "ratio", float("inf"))
        if isinstance(got, dict) and "chunk" in got and "executed" in got:
            checker.cases = []
            checker.check(ep, 0, None, args, {k: np.asarray(got[k], np.float64) for k in ("chunk", "executed")})
            bad = [c for c in checker.cases if c.status == "fail"]
            if bad:
                head = [r for r in case["requirements"] if r in ("CR-10", "CR-15")]
                reqs = head + [r for c in bad for r in c.requirements if r not in head]
                msgs = [c.message for c in bad]
        return CaseResult(case["id"], name, "rollout_chunk", sorted(set(reqs), key=reqs.index), "fail", ratio,
                          "; ".join(msgs) or str(exc), seconds)
    return CaseResult(case["id"], name, "rollout_chunk", reqs, "pass", worst, "", seconds)


def check_generation(out_dir=None) -> list:
    """Differences between the shipped rollout vectors (every file the index lists) and a regeneration
    beyond 1e-9 (or in structure)."""
    import tempfile

    envs = listed_envs(out_dir)
    diffs = []
    with tempfile.TemporaryDirectory() as tmp:
        generate(tmp, envs=envs)
        for env in envs:
            _, want = load(out_dir, env)
            _, got = load(tmp, env)
            if [c["id"] for c in got] != [c["id"] for c in want]:
                diffs.append(f"{FILES[env]}: the regenerated cases are not the shipped ones (ids differ)")
                continue
            for g, w in zip(got, want):
                for part in ("args", "expected"):
                    for k, v in w[part].items():
                        if isinstance(v, list) and \
                                np.max(np.abs(np.asarray(g[part][k]) - np.asarray(v)), initial=0) > 1e-9:
                            diffs.append(f"{w['id']} {part}.{k}")
    return diffs


# ---------------------------------------------------------------- inside `conformance run`

# What the runner needs to serve each file's field ([CR-3], [CR-14]), and the extra that installs it.
NEEDS = {"arm": (("jax", "flax", "pymunk"), "arm"), "kinetix": (("jax", "flax", "kinetix"), "kinetix")}


def served_checkpoint() -> Path:
    """The checkpoint the runner serves on the arm ([CR-3]), found without importing the arm package (and
    its JAX)."""
    spec = importlib.util.find_spec("softrtc.arm")
    if spec is None or not spec.submodule_search_locations:
        raise ValueError("the package softrtc.arm, which holds the served checkpoint, is not installed")
    return Path(list(spec.submodule_search_locations)[0]) / "checkpoints" / "drift" / "base.npz"


def missing_module(env: str) -> str | None:
    """The first module the runner lacks to serve the field of ``env``'s vectors, or None."""
    return next((m for m in NEEDS[env][0] if importlib.util.find_spec(m) is None), None)


def at_the_door(vectors_dir=None) -> dict:
    """The rollout part of a `conformance run` ([CR-10]), decided before any case runs: every vector file the
    index of ``rollouts_dir(vectors_dir)`` lists, read and checked (index, digest, format, env; the arm's
    checkpoint), each to run or skipped with the reason (a field this installation cannot serve). Returns
    the plan ``{"status": "run" | "skipped", "reason", "folder", "files": {name: {"env", "cases", "sha256",
    "status", "reason"}}}`` (the cases and headers under ``_loaded``); ValueError for rollout vectors that are
    present but cannot be read, or were recorded with another arm checkpoint."""
    folder = rollouts_dir(vectors_dir)
    if not folder.exists():
        return {"status": "skipped", "reason": f"the vector folder has no rollouts/ ({folder})",
                "folder": str(folder)}
    envs = listed_envs(folder)
    if not envs:
        raise ValueError(f"{folder / 'index.json'} lists no rollout vector file")
    files, loaded = {}, []
    for env in envs:
        header, cases = load(folder, env)
        entry = {"env": env, "cases": len(cases), "sha256": hashlib.sha256((folder / FILES[env]).read_bytes())
                 .hexdigest(), "status": "run", "reason": "",
                 "field": header.get("checkpoint") if env == "arm" else f"Kinetix level {header.get('level')}"}
        missing = missing_module(env)
        if missing:
            extra = NEEDS[env][1]
            entry.update(status="skipped", reason=f"the runner serves their field with JAX: needs the '{extra}' "
                                                  f"extra (missing module {missing}): pip install 'softrtc[{extra}]'")
        elif env == "arm":
            check_checkpoint(header, served_checkpoint())
        files[FILES[env]] = entry
        loaded.append((env, header, cases))
    running = [e for e in files.values() if e["status"] == "run"]
    return {"status": "run" if running else "skipped",
            "reason": "" if running else "; ".join(sorted({e["reason"] for e in files.values()})),
            "folder": str(folder.resolve()), "files": files, "_loaded": loaded}


def skipped(reason: str) -> dict:
    """The plan of a run that leaves the rollout vectors out, and says why ([CR-10])."""
    return {"status": "skipped", "reason": reason}


def run_part(plan: dict, result: RunResult, impl=None, *, impl_cmd=None, in_process: bool = False,
             functions=(), timeout: float = 60.0, start_timeout: float = 120.0, memory_mb=None) -> None:
    """The rollout cases of a `conformance run` ([CR-10]) added to ``result`` (``result.rollouts`` says what
    ran): an implementation without ``rollout_chunk`` (an ``--impl-cmd`` whose hello line, ``functions``,
    does not list it; an adapter without the attribute) has them unsupported without any field being
    loaded ([CF-9]); otherwise it answers them in one process of its own (or in this one with
    ``in_process``) on each file's served field, as ``conformance rollout --vectors`` does. One that cannot
    start fails them; a file whose field cannot be served here is skipped with the reason."""
    from .rollout import _InProcess, open_impl
    from .rollout_child import LacksRolloutChunk
    from .rollout_impls import NoRolloutChunk

    info = {k: v for k, v in plan.items() if not k.startswith("_")}
    result.rollouts = info
    if plan["status"] != "run":
        return
    todo = [(env, header, cases) for env, header, cases in plan["_loaded"]
            if info["files"][FILES[env]]["status"] == "run"]

    def every_case(status: str, why: str) -> None:
        info.update(status=status if status == "unsupported" else "run", reason=why)
        for env, _, cases in todo:
            info["files"][FILES[env]].update(status=info["status"], reason=why)
            result.cases.extend(CaseResult(c["id"], FILES[env], FUNCTION, list(c["requirements"]), status,
                                           0.0 if status == "unsupported" else float("inf"), why) for c in cases)

    lacks = f"adapter has no {FUNCTION}"
    if impl_cmd is not None and FUNCTION not in functions:
        return every_case("unsupported", f"{lacks} (its hello line does not list it)")
    try:
        if impl_cmd is None and not isinstance(impl, str):
            if not callable(getattr(impl, FUNCTION, None)):
                return every_case("unsupported", lacks)
            under = _InProcess(impl, None)
        else:
            under = open_impl(impl, impl_cmd, None, in_process, timeout, start_timeout, memory_mb)
    except (NoRolloutChunk, LacksRolloutChunk):
        return every_case("unsupported", lacks)
    except Exception as exc:  # noqa: BLE001 - the implementation's failure to start is its cases'
        return every_case("fail", f"the implementation could not be started for the rollout vectors: "
                                  f"{type(exc).__name__}: {str(exc)[:300]}")
    try:
        for env, header, cases in todo:
            entry = info["files"][FILES[env]]
            t0 = time.perf_counter()
            try:
                field = field_for(header)
            except (ValueError, ImportError) as exc:
                entry.update(status="skipped", reason=f"its field cannot be served here: {str(exc)[:300]}")
                continue
            under.bind(field)
            entry["field_load_seconds"] = round(time.perf_counter() - t0, 3)
            result.cases.extend(replay_cases(under, field, cases, FILES[env]))
            entry["seconds"] = round(time.perf_counter() - t0, 3)
    finally:
        under.close()
    if not any(e["status"] == "run" for e in info["files"].values()):
        info.update(status="skipped", reason="; ".join(sorted({e["reason"] for e in info["files"].values()})))


__all__ = ["generate", "load", "replay", "rollouts_dir", "check_generation", "at_the_door", "run_part",
           "listed_envs", "field_for", "FILES"]
