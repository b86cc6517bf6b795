"""Compatibility report of a third-party implementation ([TP-1]..[TP-6]).

``softrtc conformance report --impl lerobot --out conformance/thirdparty/lerobot.md`` runs the
implementation's adapter through the runner ([CF-13]) and writes a Markdown report with its JSON
beside it (``lerobot.json``): the versions, every requirement id's status, for every failing id the
smallest failing case of each function with its expected and actual values and the hand-written
diagnosis, the reason of every unsupported id, what the adapter glues, and the other implementations
looked for. ``--check`` writes nothing and exits 1 when the committed files differ from a fresh run
([TP-4]); ``--summary FILE.json`` prints the README's summary of a committed report ([TP-5]).

The hand-written text (diagnoses, reasons, glue) lives in the implementation's notes module
(:data:`THIRD_PARTY`); a failing id without a diagnosis, or a diagnosis that does not name a failing
function, stops the report with one error line ([TP-3]).
"""

from __future__ import annotations

import argparse
import importlib
import json
import platform
import re
from dataclasses import dataclass
from pathlib import Path

from .._cli_util import command_error, input_dir, output_file
from .._files import write_atomic
from . import FORMAT_VERSION, runner
from .adapter import load_adapter
# One case in detail (the adapter called on it, values rounded to DIGITS): report_case.py.
from .report_case import _FLOAT, _NUMBER, _round, _round_text, _shown_args, case_size, inspect_case

REPORT_VERSION = 1
# Numbers in a report are rounded to DIGITS significant digits (report_case.py), and a fresh report
# matches a committed one when every number agrees within REL_TOL: float32 kernels differ in their last
# bits from one CPU to another, and a report must not go stale for that ([TP-4]).
REL_TOL = 1e-2
ABS_TOL = 1e-6


@dataclass(frozen=True)
class ThirdParty:
    adapter: str  # the adapter spec for load_adapter ([CF-12])
    notes: str  # module holding the hand-written text
    cases: str | None = None  # module:function giving the implementation's own cases ([TP-8])


THIRD_PARTY = {
    "lerobot": ThirdParty("softrtc.conformance.adapters.lerobot:ADAPTER", "softrtc.conformance.adapters.lerobot_notes",
                          "softrtc.conformance.adapters.lerobot_padding:implementation_cases"),
}


class ReportError(Exception):
    """The report cannot be made; the message is one line."""


# ---------------------------------------------------------------- the report document

def _notes(name: str):
    if name not in THIRD_PARTY:
        raise ReportError(f"--impl must be one of {sorted(THIRD_PARTY)} (an implementation with hand-written "
                          f"notes), got {name!r}")
    return importlib.import_module(THIRD_PARTY[name].notes)


def build(name: str, vectors_dir=None) -> dict:
    """The report document of implementation ``name`` ([TP-1]..[TP-3]); raises ReportError."""
    notes = _notes(name)
    tp = THIRD_PARTY[name]
    files = runner.load_vectors(vectors_dir)
    adapter = load_adapter(tp.adapter)
    adapter_module = importlib.import_module(tp.adapter.split(":")[0])
    res = runner.run(adapter, vectors_dir, files=files)
    cases_by_id = {c["id"]: (c, d) for d in files for c in d["cases"]}
    reqs = res.by_requirement()

    failing = {}
    for rid, e in reqs.items():
        if e["status"] != "FAIL":
            continue
        diag = notes.DIAGNOSES.get(rid)
        if diag is None:
            raise ReportError(f"requirement {rid} fails but {tp.notes} has no diagnosis for it ([TP-3])")
        fails = [c for c in res.cases if c.status == "fail" and rid in c.requirements]
        functions = sorted({c.function for c in fails})
        unexplained = [f for f in functions if f not in diag["functions"]]
        if unexplained:
            raise ReportError(f"requirement {rid} fails in {unexplained}, which its diagnosis in {tp.notes} does not "
                              f"cover (it covers {diag['functions']}) ([TP-3])")
        shown = []
        for f in functions:
            c = min((c for c in fails if c.function == f), key=lambda c: (case_size(cases_by_id[c.id][0]), c.id))
            case, data = cases_by_id[c.id]
            shown.append({"id": c.id, "function": f, "failed_cases": sum(1 for x in fails if x.function == f),
                          "args": _shown_args(case), "message": _round_text(c.message),
                          **inspect_case(adapter, f, case, data)})
        failing[rid] = {"kind": diag["kind"], "summary": diag["summary"], "diagnosis": diag["text"],
                        "cases": shown}
    # a diagnosed id that ran cases and failed none is stale; one the run did not reach (a partial vector
    # directory, or only unsupported cases) is kept
    stale = sorted(r for r in notes.DIAGNOSES if r in reqs and r not in failing and reqs[r]["pass"])
    if stale:
        raise ReportError(f"{tp.notes} diagnoses {stale}, which do not fail: remove or update them ([TP-3])")

    unsupported, absent = {}, {}
    for rid, e in reqs.items():
        if not e["unsupported"]:
            continue
        why: dict[tuple, int] = {}
        for c in res.cases:
            if c.status != "unsupported" or rid not in c.requirements:
                continue
            if c.message.startswith("adapter has no "):
                if c.function not in notes.UNSUPPORTED_FUNCTIONS:
                    raise ReportError(f"{tp.notes} gives no reason why {c.function} is unsupported ([TP-3])")
                absent[c.function] = notes.UNSUPPORTED_FUNCTIONS[c.function]
                key = (c.function, "")
            else:  # the case was declined ([CF-26], [CF-27]): the implementation's own words
                key = (c.function, c.message.split("NotImplementedError: ", 1)[-1])
            why[key] = why.get(key, 0) + 1
        unsupported[rid] = {"status": e["status"], "cases": e["unsupported"],
                            "why": [{"function": f, "declined": r, "cases": n} for (f, r), n in sorted(why.items())]}

    glue_only = {f: {"reason": reason, "cases": sum(1 for c in res.cases if c.function == f),
                     "requirements": sorted({r for c in res.cases if c.function == f for r in c.requirements},
                                            key=_req_key)}
                 for f, reason in notes.GLUE_ONLY.items()}
    versions = {"implementation": adapter_module.versions(), "softrtc": _softrtc_version(),
                "vectors_format": FORMAT_VERSION, "spec": ", ".join(res.spec_versions),
                "python": ".".join(platform.python_version_tuple()[:2])}
    return {
        "report_version": REPORT_VERSION,
        "implementation": notes.IMPLEMENTATION, "impl": name, "adapter": tp.adapter,
        "time_convention": res.time_convention, "install": notes.INSTALL, "source": notes.SOURCE,
        "versions": versions,
        "counts": res.counts,
        "requirements": {rid: {"status": e["status"], "pass": e["pass"], "fail": e["fail"],
                               "unsupported": e["unsupported"],
                               "worst": _worst(e),
                               "glue_only": bool(e["pass"] + e["fail"]) and all(
                                   c.function in notes.GLUE_ONLY for c in res.cases
                                   if rid in c.requirements and c.status != "unsupported")}
                         for rid, e in reqs.items()},
        "failing": failing,
        "unsupported": unsupported,
        "unsupported_functions": dict(sorted(absent.items())),
        "adapter_functions": {f: {"calls": calls, "glue": glue}
                              for f, (calls, glue) in sorted(adapter_module.GLUE.items())},
        "glue_only": glue_only,
        "others": [{"name": n, "finding": t} for n, t in notes.OTHERS],
        **_own_cases(tp, notes),
    }


def _own_cases(tp: ThirdParty, notes) -> dict:
    """The implementation's own cases and the notes' text on them ([TP-8]); nothing when it has none."""
    if tp.cases is None:
        return {}
    module, fn = tp.cases.split(":")
    return {"own_cases": {"title": notes.OWN_CASES["title"], "text": notes.OWN_CASES["text"],
                          **getattr(importlib.import_module(module), fn)()}}


def _worst(e: dict):
    """The worst error / tolerance of an id: 3 digits when it fails; when it passes only "< 0.1" or "< 1", since
    the float32 rounding that makes up a passing ratio differs from CPU to CPU ([TP-4]); None when no case ran."""
    if not e["pass"] + e["fail"]:
        return None
    if e["fail"]:
        return _round(e["worst"], 3)
    return "< 0.1" if e["worst"] < 0.1 else "< 1"


def _req_key(rid: str):
    m = re.match(r"([A-Z]+)-(\d+)$", rid)
    return (m.group(1), int(m.group(2))) if m else (rid, 0)


def _softrtc_version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("softrtc")
    except PackageNotFoundError:
        return "unknown"


# ---------------------------------------------------------------- comparison

def differences(a, b, where: str = "report") -> list[str]:
    """Where two report documents differ beyond the rounding tolerance of [TP-4]: strings must be equal
    with their numbers within REL_TOL (relative) or ABS_TOL, numbers likewise, everything else exactly."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = [f"{where}.{k}: only in the {'committed' if k in a else 'fresh'} report"
               for k in sorted(set(a) ^ set(b))]
        for k in sorted(set(a) & set(b)):
            out += differences(a[k], b[k], f"{where}.{k}")
        return out
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{where}: {len(a)} entries, fresh {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in differences(x, y, f"{where}[{i}]")]
    if isinstance(a, str) and isinstance(b, str):
        na, nb = _NUMBER.findall(a), _NUMBER.findall(b)
        if _NUMBER.sub("#", a) != _NUMBER.sub("#", b) or len(na) != len(nb) \
                or not all(_same_number(_parse(x), _parse(y)) for x, y in zip(na, nb)):
            return [f"{where}: {a!r} != fresh {b!r}"]
        return []
    if isinstance(a, bool) or isinstance(b, bool) or a is None or b is None:
        return [] if a == b else [f"{where}: {a!r} != fresh {b!r}"]
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return [] if _same_number(a, b) else [f"{where}: {a!r} != fresh {b!r}"]
    return [] if a == b else [f"{where}: {a!r} != fresh {b!r}"]


def _parse(token: str):
    """A number written in a string: an int when written without a fraction or exponent ([CF-23])."""
    return float(token) if _FLOAT.fullmatch(token) else int(token)


def _same_number(x, y) -> bool:
    """Integers (counts, indices) exactly; reals within the rounding tolerance of [TP-4]."""
    if isinstance(x, int) and isinstance(y, int):
        return x == y
    return x == y or abs(x - y) <= ABS_TOL + REL_TOL * max(abs(x), abs(y))


# ---------------------------------------------------------------- Markdown

def _cell(v) -> str:
    return json.dumps(v, separators=(", ", ": ")) if not isinstance(v, str) else v


def render(doc: dict) -> str:
    """The Markdown report of a report document ([TP-2])."""
    v = doc["versions"]
    n = doc["counts"]
    impl_versions = ", ".join(f"{k} {x}" for k, x in doc["versions"]["implementation"].items())
    L = [f"# Compatibility report: {doc['implementation']}", "",
         f"Generated by `softrtc conformance report --impl {doc['impl']} --out <this file>` from the adapter "
         f"`{doc['adapter']}`; do not edit by hand.", "",
         f"- Versions: {impl_versions}; softrtc {v['softrtc']}; conformance vectors format {v['vectors_format']}, "
         f"spec {v['spec']}; Python {v['python']}.",
         f"- Installation: `{doc['install']}`.",
         f"- Code under test: {doc['source']}.",
         f"- Time convention: `{doc['time_convention']}` ([V-1]).",
         f"- Cases: {n['pass']} pass, {n['fail']} fail, {n['unsupported']} unsupported "
         f"(of {sum(n.values())}).", "",
         "## Requirements", "",
         "| id | status | cases run | failed | unsupported | worst error / tolerance |",
         "|---|---|---|---|---|---|"]
    for rid, e in _ordered(doc["requirements"]).items():
        worst = "-" if e["worst"] is None else str(e["worst"])
        status = e["status"] + (" (glue only)" if e["glue_only"] else "")
        L.append(f"| {rid} | {status} | {e['pass'] + e['fail']} | {e['fail']} | {e['unsupported']} | {worst} |")
    L += ["", "(glue only: every case of the id that ran tests the adapter's glue, not the implementation; see "
          "below.)"]
    L += ["", "## Failing requirements", ""]
    if not doc["failing"]:
        L.append("None.")
    for rid, f in _ordered(doc["failing"]).items():
        L += [f"### {rid}: {f['summary']}", "", f"*{f['kind']}.* {f['diagnosis']}", ""]
        for c in f["cases"]:
            L.append(f"- Smallest failing `{c['function']}` case ({c['failed_cases']} failed): `{c['id']}`")
            L.append(f"  - arguments: `{_cell(c['args'])}`")
            L.append(f"  - runner: {c['message']}")
            if "expected" in c:
                L.append(f"  - expected: `{_cell(c['expected'])}`")
            L.append(f"  - actual ({c.get('called', c['function'])}): `{_cell(c['actual'])}`")
            step = c.get("first_differing_step")
            if step:
                differ = ", ".join(f"{k} (max |diff| {d})" for k, d in step["differ"].items())
                L.append(f"  - first differing trace step: {step['step']}; agreeing: "
                         f"{', '.join(step['agree']) or 'none'}; differing: {differ}")
        L.append("")
    L += ["## Unsupported requirements and why", "",
          "Functions of the interface the adapter does not provide ([CF-9]):", "",
          "| function | why |", "|---|---|"]
    for fname, why in doc["unsupported_functions"].items():
        L.append(f"| `{fname}` | {why} |")
    L += ["", "Unsupported cases per requirement id (declined: the adapter raised NotImplementedError for the "
          "case, [CF-26], with the reason it gave):", ""]
    for rid, u in _ordered(doc["unsupported"]).items():
        parts = [f"`{w['function']}` {w['cases']}" + (f" (declined: {w['declined']})" if w["declined"] else "")
                 for w in u["why"]]
        L.append(f"- {rid} ({u['status']}, {u['cases']} unsupported): {'; '.join(parts)}")
    L += ["", "## What the adapter calls, and what is glue", "",
          "| function | LeRobot code called | glue in the adapter |".replace("LeRobot", doc["implementation"]),
          "|---|---|---|"]
    for fname, g in doc["adapter_functions"].items():
        L.append(f"| `{fname}` | {g['calls']} | {g['glue']} |")
    L += ["", "Cases that test glue rather than the implementation:", ""]
    for fname, g in doc["glue_only"].items():
        L.append(f"- `{fname}` ({g['cases']} cases; {', '.join(g['requirements'])}): {g['reason']}")
    if "own_cases" in doc:
        L += _render_own_cases(doc["own_cases"])
    L += ["", "## Other RTC implementations looked for", ""]
    for o in doc["others"]:
        L.append(f"- {o['name']}: {o['finding']}")
    return "\n".join(L) + "\n"


def _render_own_cases(own: dict) -> list[str]:
    """The section of [TP-8]: one row per case, LeRobot's weights per code path and the [W-6] option each is."""
    L = ["", f"## {own['title']}", "", own["text"], "",
         "| H | d | left-over rows | window end e | path | weights | pulled toward 0 | [W-6] option |",
         "|---|---|---|---|---|---|---|---|"]
    for c in own["cases"]:
        head = f"| {c['H']} | {c['d']} | {c['left_over_rows']} | {c['execution_horizon']} |"
        for path in ("denoise_step", "rollout"):
            if path in c:
                r = c[path]
                pulled = ", ".join(str(j) for j in r["pulled_toward_zero"]) or "none"
                L.append(f"{head} {path} | {_cell(r['weights'])} | {pulled} | {r['option']} |")
        L.append(f"{head} spec clip / zeros | {_cell(c['spec_clip'])} / {_cell(c['spec_zeros'])} | | |")
    return L


def summary(doc: dict) -> str:
    """The README's summary of a report document ([TP-5])."""
    n = doc["counts"]
    impl_versions = ", ".join(f"{k} {x}" for k, x in doc["versions"]["implementation"].items())
    reqs = _ordered(doc["requirements"])
    passing = [r for r, e in reqs.items() if e["status"] == "PASS" and not e["glue_only"]]
    glue = [r for r, e in reqs.items() if e["status"] == "PASS" and e["glue_only"]]
    failing = [r for r, e in reqs.items() if e["status"] == "FAIL"]
    unsupported = [r for r, e in reqs.items() if e["status"] == "UNSUPPORTED"]
    L = [f"{doc['implementation']} ({impl_versions}; vectors format {doc['versions']['vectors_format']}, spec "
         f"{doc['versions']['spec']}): {n['pass']} cases pass, {n['fail']} fail, {n['unsupported']} are "
         f"unsupported. Requirement ids passing: {', '.join(passing) or 'none'}"
         + (f" (and {', '.join(glue)} through the adapter's glue only)" if glue else "")
         + f"; failing: {', '.join(failing) or 'none'}; unsupported: {len(unsupported)} ids.", "",
         "| failing id | kind | what differs |", "|---|---|---|"]
    for rid, f in _ordered(doc["failing"]).items():
        L.append(f"| {rid} | {f['kind']} | {f['summary']} |")
    return "\n".join(L) + "\n"


def _ordered(by_id: dict) -> dict:
    """Requirement ids in spec order (N-7 before N-12), whatever order a JSON file keeps them in."""
    return dict(sorted(by_id.items(), key=lambda kv: _req_key(kv[0])))


# ---------------------------------------------------------------- command line

def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--impl", default=None, help=f"implementation with notes: {', '.join(sorted(THIRD_PARTY))}")
    parser.add_argument("--out", type=output_file(), default=None,
                        help="Markdown report to write (its JSON is written beside it, .json)")
    parser.add_argument("--check", action="store_true",
                        help="write nothing; exit 1 when the report at --out differs from a fresh one")
    parser.add_argument("--summary", default=None, metavar="FILE.json",
                        help="print the README summary of a committed JSON report and exit")
    parser.add_argument("--vectors", type=input_dir(), default=None,
                        help="vector directory (default: the vectors shipped with softrtc)")


def json_text(doc: dict) -> str:
    return json.dumps(doc, indent=1, sort_keys=True) + "\n"


def check(md_path, doc: dict) -> list[str]:
    """Differences between the committed report at ``md_path`` (and its JSON) and ``doc`` ([TP-4])."""
    md_path, json_path = Path(md_path), Path(md_path).with_suffix(".json")
    if not json_path.is_file() or not md_path.is_file():
        return [f"{json_path if not json_path.is_file() else md_path} does not exist"]
    committed = json.loads(json_path.read_text())
    out = differences(committed, json.loads(json_text(doc)))
    if md_path.read_text() != render(committed):
        out.append(f"{md_path} is not the rendering of {json_path}")
    return out


def run_from_args(args) -> int:
    prog = getattr(args, "_prog", "softrtc conformance report")
    if args.summary is not None:
        if args.impl or args.out or args.check:
            return command_error(prog, "--summary takes no other option")
        try:
            print(summary(json.loads(Path(args.summary).read_text())), end="")
        except (OSError, ValueError, KeyError) as exc:
            return command_error(prog, f"cannot read report {args.summary}: {exc}")
        return 0
    if not args.impl or not args.out:
        return command_error(prog, "--impl and --out are required (or --summary FILE.json)")
    if not str(args.out).endswith(".md"):
        return command_error(prog, f"--out must name a .md file, got {args.out}")
    if not args.check:
        try:  # at the door: both files the report writes are regular files of their own ([CF-15])
            runner.check_output_paths({"--out": args.out, "--out's JSON": str(Path(args.out).with_suffix(".json"))})
        except ValueError as exc:
            return command_error(prog, exc)
    try:
        doc = build(args.impl, args.vectors)
    except (ReportError, runner.VectorError) as exc:
        return command_error(prog, exc)
    except Exception as exc:  # the adapter cannot load (the implementation not installed): one line
        return command_error(prog, f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}")
    if args.check:
        diffs = check(args.out, doc)
        for d in diffs[:20]:
            print(f"stale: {d}")
        print(f"{args.out}: {'stale' if diffs else 'up to date'}")
        return 1 if diffs else 0
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(out.with_suffix(".json"), lambda f: f.write(json_text(doc)))
    write_atomic(out, lambda f: f.write(render(json.loads(json_text(doc)))))
    print(f"wrote {out} and {out.with_suffix('.json')}: {doc['counts']}")
    return 0
