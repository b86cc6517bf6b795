"""Results of a conformance run and their reports ([CF-14], [CF-15], [CF-26]).

:class:`RunResult` holds one :class:`CaseResult` per case and which vectors ran;
:func:`format_summary` prints the per-requirement summary, :func:`report_dict` the
``--report`` JSON and :func:`write_junit` the JUnit XML. :func:`check_output_paths`
refuses output paths that clash or are special files before a run starts ([CF-15]).
"""

from __future__ import annotations

import json
import math
import os
import re
import stat
import xml.etree.ElementTree as ET
from dataclasses import asdict, dataclass, field
from pathlib import Path

from .._files import write_atomic

MAX_LISTED_FAILURES = 25
TRACE_NOT_PROVIDED = "trace not provided; chunk checked only"
UNSUPPORTED_CASE = "unsupported case"


@dataclass
class CaseResult:
    """Outcome of one case: status is pass, fail or unsupported."""

    id: str
    file: str
    function: str
    requirements: list
    status: str
    worst: float = 0.0  # largest |got - want| / tolerance over the case's numbers; inf when none could be compared
    message: str = ""
    seconds: float = 0.0


@dataclass
class RunResult:
    impl: str
    adapter_name: str
    time_convention: str
    format_version: str
    spec_versions: list
    cases: list = field(default_factory=list)
    seconds: float = 0.0
    isolation: str = "in process"  # or "child process" ([CF-29])
    # Which vectors ran ([CF-39]): vectors_io.describe_vectors's folder, index, files, digest, shipped.
    vectors: dict | None = None
    # The rollout vectors' part ([CR-10]): status (run, unsupported, skipped), reason, folder, file, sha256, ...
    rollouts: dict | None = None

    @property
    def counts(self) -> dict:
        out = {"pass": 0, "fail": 0, "unsupported": 0}
        for c in self.cases:
            out[c.status] += 1
        return out

    @property
    def ok(self) -> bool:
        """[CF-16] success: no failure, and at least one supported case."""
        n = self.counts
        return n["fail"] == 0 and n["pass"] > 0

    def by_requirement(self) -> dict:
        reqs: dict[str, dict] = {}
        for c in self.cases:
            for r in c.requirements:
                e = reqs.setdefault(r, {"pass": 0, "fail": 0, "unsupported": 0, "worst": 0.0})
                e[c.status] += 1
                if c.status != "unsupported":
                    e["worst"] = max(e["worst"], c.worst)
        for e in reqs.values():
            e["status"] = "FAIL" if e["fail"] else ("PASS" if e["pass"] else "UNSUPPORTED")
        return dict(sorted(reqs.items(), key=lambda kv: _req_key(kv[0])))


def _req_key(rid: str):
    m = re.match(r"([A-Z]+)-(\d+)$", rid)
    return (m.group(1), int(m.group(2))) if m else (rid, 0)


def format_summary(res: RunResult, max_failures: int = MAX_LISTED_FAILURES) -> str:
    """Human-readable summary: one line per requirement id, unsupported functions, failures ([CF-14])."""
    lines = [f"softrtc conformance: impl {res.impl} (adapter '{res.adapter_name}', {res.time_convention}), "
             f"vectors format {res.format_version}, spec {', '.join(res.spec_versions)}; {res.isolation}"]
    v = res.vectors
    if v is not None:  # [CF-39]
        which = "the shipped set" if v["shipped"] else "NOT the shipped set"
        lines.append(f"vectors: {which}, {v['folder']} ({len(v['files'])} files, "
                     f"{'checked against its index.json' if v['index'] else 'no index.json'}; digest "
                     f"sha256:{v['digest'][:16]})")
    if res.rollouts is not None:  # [CR-10]
        lines.append(rollout_line(res.rollouts))
    for rid, e in res.by_requirement().items():
        n = e["pass"] + e["fail"]
        extra = f", {e['unsupported']} unsupported" if e["unsupported"] else ""
        worst = f"worst {e['worst']:.3g} x tol" if n else "worst -"
        lines.append(f"  {e['status']:<11s} {rid:<6s} {worst:<20s} {n:>5d} cases{extra}"
                     + (f" ({e['fail']} failed)" if e["fail"] else ""))
    uns: dict[str, int] = {}
    declined: dict[str, int] = {}
    for c in res.cases:
        if c.status == "unsupported" and c.message.startswith(UNSUPPORTED_CASE):
            for r in c.requirements:
                declined[r] = declined.get(r, 0) + 1
        elif c.status == "unsupported":
            uns[c.function] = uns.get(c.function, 0) + 1
    if uns:
        lines.append("unsupported (adapter lacks the function): "
                     + ", ".join(f"{f} ({n} cases)" for f, n in sorted(uns.items())))
    if declined:  # [CF-26]
        lines.append("unsupported cases (the implementation raised NotImplementedError, or no form of the function "
                     "takes the case), per requirement: "
                     + ", ".join(f"{r} ({n})" for r, n in sorted(declined.items(), key=lambda kv: _req_key(kv[0]))))
    untraced = sum(1 for c in res.cases if c.status == "pass" and c.message == TRACE_NOT_PROVIDED)
    if untraced:
        lines.append(f"{untraced} sampler cases passed without a trace: their chunks are checked, their per-step "
                     "values (blended state, denoised estimate, error, pull-back) are not ([CF-11])")
    fails = [c for c in res.cases if c.status == "fail"]
    if fails:
        lines.append(f"failures ({len(fails)}; first {min(len(fails), max_failures)} shown):")
        for c in fails[:max_failures]:
            lines.append(f"  FAIL {c.id}: {c.message}")
    n = res.counts
    other = f" on {v['folder']}, NOT the shipped vectors" if v is not None and not v["shipped"] else ""
    lines.append(f"{'PASS' if res.ok else 'FAIL'}: {len(res.cases)} cases: {n['pass']} passed, {n['fail']} failed, "
                 f"{n['unsupported']} unsupported; {res.seconds:.1f} s{other}")
    if n["pass"] == 0 and n["fail"] == 0:
        lines.append("no supported case ran: the adapter provides none of the interface functions")
    return "\n".join(lines)


def rollout_line(r: dict) -> str:
    """The summary's lines on the rollout vectors ([CR-10]): one per vector file, which ran or why not; one
    line when none was read."""
    if not r.get("files"):
        return f"rollout vectors: {r['status']}, {r['reason']}"
    lines = []
    for name, e in r["files"].items():
        where = (f"rollout vectors: {r['folder']}/{name} ({e['cases']} cases, checked against its index.json; "
                 f"sha256:{e['sha256'][:16]})")
        if e["status"] == "run":
            load = (f" (implementation started and field loaded in {e['field_load_seconds']:.1f} s)"
                    if "field_load_seconds" in e else "")
            lines.append(f"{where}, field {e['field']} served{load}")
        elif e["status"] == "unsupported":
            lines.append(f"{where}, all unsupported: {e['reason']}")
        else:
            lines.append(f"{where}, skipped: {e['reason']}")
    return "\n".join(lines)


def report_dict(res: RunResult) -> dict:
    """The --report JSON document ([CF-15])."""
    return {"impl": res.impl, "adapter": res.adapter_name, "time_convention": res.time_convention,
            "format_version": res.format_version, "spec_versions": res.spec_versions, "ok": res.ok,
            "isolation": res.isolation, "vectors": res.vectors, "rollouts": res.rollouts,
            "seconds": round(res.seconds, 3), "counts": res.counts,
            "requirements": {k: {kk: (vv if not isinstance(vv, float) or math.isfinite(vv) else "inf")
                                 for kk, vv in v.items()} for k, v in res.by_requirement().items()},
            "cases": [{k: (v if not isinstance(v, float) or math.isfinite(v) else "inf")
                       for k, v in asdict(c).items()} for c in res.cases]}


def write_junit(res: RunResult, path) -> None:
    """JUnit XML: one testsuite per vector file, one testcase per case ([CF-15])."""
    root = ET.Element("testsuites", name=f"softrtc-conformance-{res.adapter_name}",
                      tests=str(len(res.cases)), failures=str(res.counts["fail"]),
                      skipped=str(res.counts["unsupported"]), time=f"{res.seconds:.3f}")
    suites: dict[str, ET.Element] = {}
    v = res.vectors
    for c in res.cases:
        s = suites.get(c.file)
        if s is None:
            s = suites[c.file] = ET.SubElement(root, "testsuite", name=f"conformance.{Path(c.file).stem}")
            s.attrib.update(tests="0", failures="0", skipped="0")
            if v is not None:  # [CF-39]: which vectors ran, on every suite (testsuites takes no properties)
                props = ET.SubElement(s, "properties")
                for name, value in (("vectors_folder", v["folder"]), ("vectors_digest", v["digest"]),
                                    ("vectors_shipped", "true" if v["shipped"] else "false"),
                                    ("vector_file_sha256", v["files"].get(c.file) or _rollout_sha(res, c.file))):
                    ET.SubElement(props, "property", name=name, value=value)
        s.set("tests", str(int(s.get("tests")) + 1))
        tc = ET.SubElement(s, "testcase", classname=f"conformance.{Path(c.file).stem}.{c.function}", name=c.id,
                           time=f"{c.seconds:.6f}")
        ET.SubElement(tc, "properties")
        props = tc.find("properties")
        ET.SubElement(props, "property", name="requirements", value=" ".join(c.requirements))
        if c.status == "fail":
            s.set("failures", str(int(s.get("failures")) + 1))
            ET.SubElement(tc, "failure", message=c.message, type="ConformanceFailure")
        elif c.status == "unsupported":
            s.set("skipped", str(int(s.get("skipped")) + 1))
            ET.SubElement(tc, "skipped", message=c.message)
    write_atomic(path, lambda f: ET.ElementTree(root).write(f, encoding="utf-8", xml_declaration=True), binary=True)


def _rollout_sha(res: RunResult, name: str) -> str:
    return ((res.rollouts or {}).get("files") or {}).get(name, {}).get("sha256", "")


def write_report(res: RunResult, path) -> None:
    """The --report JSON ([CF-15]), written whole or not at all (a temporary file beside it, then renamed)."""
    text = json.dumps(report_dict(res), indent=1, sort_keys=True) + "\n"
    write_atomic(path, lambda f: f.write(text))


_SPECIAL = ((stat.S_ISLNK, "a symbolic link"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
            (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"), (stat.S_ISDIR, "a folder"))


def output_problem(path) -> str | None:
    """Why ``path`` cannot be an output file, or None: an existing entry that is not a regular file (a
    symbolic link, dangling or not, a FIFO, a device, a socket, a folder) is never replaced ([CF-15])."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return None
    except OSError as exc:
        return f"cannot be checked ({exc.strerror or exc})"
    if stat.S_ISREG(mode):
        return None
    kind = next((name for test, name in _SPECIAL if test(mode)), "not a regular file")
    return f"is {kind}; an output is written only as a regular file (a temporary file renamed into place)"


def check_output_paths(paths: dict) -> None:
    """ValueError (one line naming the option) unless every output path of ``paths`` ({option: path or
    None}) may be written: not a special file (:func:`output_problem`), and no two naming the same file,
    however spelt ([CF-15])."""
    seen: dict[str, str] = {}
    for option, path in paths.items():
        if path is None:
            continue
        why = output_problem(path)
        if why:
            raise ValueError(f"{option} {os.fspath(path)} {why}")
        try:  # an existing file by its inode, so a hard link to it is the same file too
            st = os.stat(path)
            key = f"inode {st.st_dev}:{st.st_ino}"
        except OSError:
            key = os.path.realpath(path)
        if key in seen:
            raise ValueError(f"{seen[key]} and {option} name the same file {os.fspath(path)}; each output needs a "
                             "file of its own")
        seen[key] = option
