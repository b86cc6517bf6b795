"""Reading vector files: the number convention, integrity against index.json, and the case checks
([CF-2], [CF-23], [CF-24], [CF-25]).

A file is read once, and only when it is a regular file of at most
MAX_VECTOR_FILE_BYTES ([CF-40]): its bytes are checked against ``index.json``
(when the directory has one), parsed with :func:`parse_json`, and every case is
checked by :mod:`.vector_checks` before any implementation is called. Anything
wrong is a :class:`VectorError` naming the file (and the case): the runner then
stops with status 2 ([CF-16]). :func:`describe_vectors` says which vectors were
read and whether they are the shipped set ([CF-39]).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import stat
from pathlib import Path

from . import FORMAT_VERSION, vectors_dir

# Integers a vector file may hold: exactly representable as a double, so a port in any language reads them
# exactly ([CF-28]).
MAX_ABS_INT = 2 ** 53
# The largest vector file or index read ([CF-40]): the shipped files are a few MB; a link to /dev/zero or a
# runaway file must not exhaust memory.
MAX_VECTOR_FILE_BYTES = 64 << 20


class VectorError(Exception):
    """The vector directory is missing or holds files this runner cannot read."""


def _reject_constant(name: str):
    raise ValueError(f"{name} is not a JSON number (vector files hold finite numbers only, [CF-3])")


def _finite_float(text: str) -> float:
    v = float(text)
    if not math.isfinite(v):
        raise ValueError(f"the number {text[:40]} overflows a double (vector files hold finite numbers only, "
                         "[CF-28])")
    return v


def _bounded_int(text: str) -> int:
    v = int(text)
    if abs(v) > MAX_ABS_INT:
        raise ValueError(f"the integer {text[:40]} is beyond 2^53 in magnitude ([CF-28])")
    return v


def parse_json(text, checked: bool = True):
    """JSON text to Python under the number convention of [CF-23]: a number written with a fraction or an
    exponent is a float, one written without is an int. NaN and Infinity are refused, and so is nesting
    deeper than Python's parser follows; with ``checked`` (the default) also a float that overflows a
    double (``1e999``) and an integer beyond 2^53 in magnitude ([CF-28]); each raises ValueError.
    :func:`load_vectors` parses unchecked and checks every number of every case afterwards, array by array."""
    if not isinstance(text, (str, bytes, bytearray)):
        raise ValueError(f"text must be JSON text (str or bytes), got {type(text).__name__}")
    hooks = {"parse_float": _finite_float, "parse_int": _bounded_int} if checked else {}
    try:
        return json.loads(text, parse_constant=_reject_constant, **hooks)
    except RecursionError:
        raise ValueError("JSON nested too deeply ([CF-28])") from None


def _path(name: str, value) -> Path:
    """A str or os.PathLike argument as a Path ([N-7])."""
    if not isinstance(value, (str, os.PathLike)):
        raise ValueError(f"{name} must be a path (str or os.PathLike), got {type(value).__name__}")
    return Path(value)


_KINDS = ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISSOCK, "a socket"), (stat.S_ISDIR, "a folder"))


def _kind(mode: int) -> str:
    return next((name for test, name in _KINDS if test(mode)), "not a regular file")


def read_vector_bytes(path) -> bytes:
    """The bytes of ``path``, a regular file (a symbolic link to one is followed) of at most
    MAX_VECTOR_FILE_BYTES ([CF-40]). A FIFO, a device, a socket or a folder is refused before anything is
    read from it: it is opened without blocking and checked on the open descriptor, so neither a FIFO nobody
    writes to nor a swap of the file between the check and the read can hang the runner."""
    p = _path("path", path)
    try:
        fd = os.open(p, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        raise VectorError(f"cannot read vector file {p}: {exc.strerror or exc}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            link = f" (a link to {os.path.realpath(p)})" if os.path.islink(p) else ""
            raise VectorError(f"{p.name}: not a regular file but {_kind(st.st_mode)}{link}; the vectors in "
                              f"{p.parent} are refused ([CF-40])")
        if st.st_size > MAX_VECTOR_FILE_BYTES:
            raise VectorError(f"{p.name}: {st.st_size} bytes, more than the {MAX_VECTOR_FILE_BYTES >> 20} MiB a "
                              "vector file may hold ([CF-40])")
        chunks, size = [], 0
        while True:
            chunk = os.read(fd, min(1 << 20, MAX_VECTOR_FILE_BYTES + 1 - size))
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
            if size > MAX_VECTOR_FILE_BYTES:
                raise VectorError(f"{p.name}: grew beyond the {MAX_VECTOR_FILE_BYTES >> 20} MiB a vector file may "
                                  "hold while it was read ([CF-40])")
        return b"".join(chunks)
    except OSError as exc:
        raise VectorError(f"cannot read vector file {p}: {exc.strerror or exc}") from None
    finally:
        os.close(fd)


def set_digest(files: dict) -> str:
    """SHA-256 of the lines "SHA256  NAME\n" of ``files`` ({name: sha256}) sorted by name: one digest for
    a set of vector files, as ``sha256sum`` lists them ([CF-39])."""
    lines = "".join(f"{files[n]}  {n}\n" for n in sorted(files))
    return hashlib.sha256(lines.encode("utf-8")).hexdigest()


def shipped_files() -> dict | None:
    """{name: sha256} of the shipped vectors, from the package's own index.json; None when it cannot be read."""
    try:
        index = parse_json(read_vector_bytes(vectors_dir() / "index.json").decode("utf-8"))
        files = {str(n): str(e["sha256"]) for n, e in index["files"].items()}
    except (VectorError, OSError, ValueError, UnicodeDecodeError, KeyError, TypeError, AttributeError):
        return None
    return files


def describe_vectors(files: list) -> dict | None:
    """Which vectors ``files`` (as :func:`load_vectors` returns them) are ([CF-39]): ``folder`` (absolute),
    ``index`` (whether it had index.json), ``files`` {name: sha256}, their ``digest`` (:func:`set_digest`)
    and ``shipped``: whether the same files with the same digests as the package's own vectors. None for
    vectors not read by load_vectors (a hand-built list)."""
    if not files or not all("_sha256" in d and "_dir" in d for d in files):
        return None
    digests = {d["_file"]: d["_sha256"] for d in files}
    return {"folder": files[0]["_dir"], "index": bool(files[0].get("_index")), "files": digests,
            "digest": set_digest(digests), "shipped": digests == shipped_files()}


def load_vectors(directory=None) -> list[dict]:
    """Read every vector file of ``directory`` (index.json excluded), checking format_version ([CF-2]),
    the index ([CF-25]) and every case ([CF-24], [CF-28]); raise VectorError naming the first problem."""
    from .vector_checks import check_case, check_fields, check_header

    d = _path("directory", directory) if directory is not None else vectors_dir()
    if not d.is_dir():
        raise VectorError(f"vectors directory {d} {'is not a directory' if d.exists() else 'does not exist'}")
    files = sorted(p for p in d.glob("*.json") if p.name != "index.json")
    if not files:
        raise VectorError(f"vectors directory {d} holds no *.json vector files")
    index = _read_index(d, files)
    out, seen = [], {}
    for p in files:
        raw = read_vector_bytes(p)
        digest = hashlib.sha256(raw).hexdigest()
        if index is not None:
            _check_digest(p.name, digest, index[p.name])
        try:
            data = parse_json(raw.decode("utf-8"), checked=False)
        except (ValueError, UnicodeDecodeError) as exc:
            raise VectorError(f"cannot read vector file {p}: {exc}") from None
        if not isinstance(data, dict):
            raise VectorError(f"{p.name}: expected a JSON object with 'format_version' and 'cases', "
                              f"got a {type(data).__name__}")
        check_format(p.name, data.get("format_version"))
        check_header(p.name, data)
        fields = data.get("fields", {})
        if not isinstance(fields, dict):
            raise VectorError(f"{p.name}: 'fields' must be a JSON object, got {type(fields).__name__}")
        check_fields(p.name, fields)
        for i, case in enumerate(data["cases"]):
            check_case(p.name, i, case, fields)
            if case["id"] in seen:
                raise VectorError(f"{p.name}: case {i}: id {case['id']!r} already used in {seen[case['id']]} ([CF-6])")
            seen[case["id"]] = p.name
        if index is not None and len(data["cases"]) != index[p.name].get("cases"):
            raise VectorError(f"{p.name}: {len(data['cases'])} cases, index.json lists {index[p.name].get('cases')} "
                              "([CF-25])")
        data["_file"], data["_sha256"] = p.name, digest
        data["_dir"], data["_index"] = str(d.resolve()), index is not None
        out.append(data)
    return out


def check_format(where: str, version) -> None:
    """A format_version this runner reads: the same major version as FORMAT_VERSION ([CF-2])."""
    major = FORMAT_VERSION.split(".")[0]
    if str(version or "").split(".")[0] != major:
        raise VectorError(f"{where}: format_version {version!r} is not readable by this runner (needs {major}.x)")


def _read_index(d: Path, files: list) -> dict | None:
    """``d/index.json``'s ``files`` entry, {name: {sha256, cases, ...}}, once it lists exactly ``files`` in a
    readable format ([CF-25]); None when the directory has no index (a hand-made set of cases)."""
    path = d / "index.json"
    if not os.path.lexists(path):
        return None
    try:
        index = parse_json(read_vector_bytes(path).decode("utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise VectorError(f"cannot read {path}: {exc}") from None
    listed = index.get("files") if isinstance(index, dict) else None
    if not isinstance(listed, dict) or not all(isinstance(v, dict) for v in listed.values()):
        raise VectorError(f"{path}: expected an object with 'files': {{name: {{sha256, cases, ...}}}} ([CF-2])")
    check_format(str(path), index.get("format_version"))
    names = {p.name for p in files}
    missing, unlisted = sorted(set(listed) - names), sorted(names - set(listed))
    if missing:
        raise VectorError(f"{missing[0]}: listed in index.json but missing from {d} ([CF-25])")
    if unlisted:
        raise VectorError(f"{unlisted[0]}: not listed in index.json; the vectors in {d} are not one generated set "
                          "([CF-25])")
    return listed


def _check_digest(name: str, digest: str, entry: dict) -> None:
    """The file's SHA-256 (``digest``) must be the one index.json lists ([CF-25])."""
    if digest != entry.get("sha256"):
        raise VectorError(f"{name}: SHA-256 {digest[:12]}... differs from index.json's {str(entry.get('sha256'))[:12]}"
                          "...: the file was changed after generation (regenerate with `softrtc conformance "
                          "generate`, or run a hand-made set from a folder without index.json) ([CF-25])")
