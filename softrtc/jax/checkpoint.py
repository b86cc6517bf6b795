"""Self-describing policy checkpoints (spec chapter T, ``spec/31-training-jax.md``, [T-11], [T-12]).

A checkpoint is one ``.npz`` file (a zip archive of ``.npy`` members, read
with ``allow_pickle=False``, so loading never runs code from the file):

* ``__header__``: a uint8 array holding UTF-8 JSON ``{"format": FORMAT,
  "version": VERSION, "policy": {"obs_dim", "action_dim", "config": {...}},
  "arrays": {name: {"dtype", "shape"}}, "metadata": {...}, "checksum":
  "sha256:<hex>"}``;
* one member per parameter, named by its key path in
  ``nnx.state(policy).to_pure_dict()`` joined with ``/`` and prefixed
  ``params/`` (e.g. ``params/mlp_stack/0/adaln_1/kernel``).

The checksum (:func:`checkpoint_checksum`) covers the header without its
``checksum`` field and every array's name, dtype, shape and bytes.

>>> import flax.nnx as nnx, tempfile, os
>>> from softrtc.jax.policy import FlowPolicy, PolicyConfig
>>> pol = FlowPolicy(obs_dim=3, action_dim=2, rngs=nnx.Rngs(0),
...                  config=PolicyConfig(channel_dim=8, channel_hidden_dim=8, token_hidden_dim=4,
...                                      num_layers=1, action_chunk_size=4))
>>> path = os.path.join(tempfile.mkdtemp(), "policy.npz")
>>> save_checkpoint(path, pol, {"step": 0})
>>> restored, meta = load_checkpoint(path)
>>> meta, restored.config == pol.config
({'step': 0}, True)
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import os
import zipfile
import zlib
from typing import Any, Mapping

import flax.nnx as nnx
import numpy as np

from softrtc._files import write_atomic

from .params import load_pure_dict, state_pure_dict
from .policy import FlowPolicy, PolicyConfig

__all__ = ["FORMAT", "VERSION", "save_checkpoint", "load_checkpoint", "read_checkpoint", "checkpoint_checksum"]

FORMAT = "softrtc.jax.policy-checkpoint"
VERSION = 1
HEADER_KEY = "__header__"
PARAM_PREFIX = "params/"


def _flatten(tree: Mapping, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in tree.items():
        name = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(_flatten(v, name + "/"))
        else:
            out[name] = v
    return out


def _nest(flat: Mapping[str, Any]) -> dict:
    nested: dict = {}
    for name, arr in flat.items():
        node = nested
        *parents, leaf = name.split("/")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = arr
    return nested


def checkpoint_checksum(header: Mapping, arrays: Mapping[str, np.ndarray]) -> str:
    """``"sha256:<hex>"`` of a checkpoint's header (less ``checksum``) and arrays ([T-11]).

    The header enters as canonical JSON (sorted keys, no spaces); each array, in
    sorted name order, as its name, dtype string, shape and C-order bytes.
    """
    if not isinstance(header, Mapping):
        raise ValueError(f"header must be a mapping, got {type(header).__name__}")
    if not isinstance(arrays, Mapping) or not all(isinstance(k, str) for k in arrays):
        raise ValueError(f"arrays must be a mapping of str name -> array, got {type(arrays).__name__}")
    if not _str_keys(header):  # [T-11]: JSON would turn a nested key 1 into "1" silently
        raise ValueError("header must be a mapping with str keys at every depth (nested non-string keys are "
                         "rejected, not turned into strings)")
    h = hashlib.sha256()
    body = {k: v for k, v in header.items() if k != "checksum"}
    try:
        text = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"header must hold JSON values only (no NaN, sets or objects): {exc}") from None
    h.update(text.encode())
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        # Length-prefixed fields: no two different (name, dtype, shape) lists hash the same byte stream.
        for part in (name.encode(), a.dtype.str.encode(), json.dumps(list(a.shape)).encode()):
            h.update(len(part).to_bytes(8, "little"))
            h.update(part)
        h.update(a.tobytes())
    return "sha256:" + h.hexdigest()


def _str_keys(value) -> bool:
    """True when every mapping inside ``value`` has str keys (JSON would turn 1 into "1" silently)."""
    if isinstance(value, Mapping):
        return all(isinstance(k, str) and _str_keys(x) for k, x in value.items())
    if isinstance(value, (list, tuple)):
        return all(_str_keys(x) for x in value)
    return True


def _policy_spec(policy: FlowPolicy) -> dict:
    return {"obs_dim": policy.obs_dim, "action_dim": policy.action_dim,
            "config": dataclasses.asdict(policy.config)}


def save_checkpoint(path: str | os.PathLike, policy: FlowPolicy, metadata: Mapping | None = None) -> None:
    """Writes ``policy`` and JSON ``metadata`` to the checkpoint file ``path`` ([T-11]).

    ``metadata`` must be a mapping with string keys whose values JSON can encode
    (finite numbers, strings, bools, None, lists, dicts), e.g.
    ``{"step": 1000, "train_config": TrainConfig(...).to_dict()}``. The file is
    written to a temporary name in the same directory and renamed, so a crash
    never leaves a half-written checkpoint under ``path``.
    """
    if not isinstance(path, (str, os.PathLike)) or not str(path):
        raise ValueError(f"path must be a file path (str or os.PathLike), got {path!r}")
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise ValueError(f"path must be in an existing directory, got {directory!r}")
    if os.path.isdir(path):
        raise ValueError(f"path must be a file path, got the directory {os.fspath(path)!r}")
    if not isinstance(policy, FlowPolicy):
        raise ValueError(f"policy must be a FlowPolicy, got {type(policy).__name__}")
    metadata = {} if metadata is None else metadata
    if not isinstance(metadata, Mapping) or not _str_keys(metadata):
        raise ValueError("metadata must be a mapping with string keys at every depth")
    try:
        metadata = json.loads(json.dumps(dict(metadata), allow_nan=False))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"metadata must be JSON-serialisable with finite numbers: {exc}") from exc

    arrays = {PARAM_PREFIX + k: np.asarray(v) for k, v in _flatten(state_pure_dict(policy)).items()}
    header = {
        "format": FORMAT,
        "version": VERSION,
        "policy": _policy_spec(policy),
        "arrays": {k: {"dtype": a.dtype.str, "shape": list(a.shape)} for k, a in sorted(arrays.items())},
        "metadata": metadata,
    }
    header["checksum"] = checkpoint_checksum(header, arrays)
    members = dict(arrays)
    members[HEADER_KEY] = np.frombuffer(json.dumps(header, sort_keys=True).encode(), np.uint8)

    # a file object keeps numpy from appending ".npz" to the name
    write_atomic(path, lambda f: np.savez(f, **members), binary=True, prefix=".ckpt-")


def _fail(path: Any, what: str) -> ValueError:
    return ValueError(f"checkpoint {os.fspath(path)!r}: {what}")


# End of central directory record of a zip archive: signature, 16 bytes of fields, then the comment length.
_EOCD = b"PK\x05\x06"
_EOCD_SIZE = 22


def _check_archive_end(raw: bytes) -> None:
    """Raise ValueError unless the archive's end-of-directory record (and its comment) ends the file.

    ``zipfile`` searches backwards for the record and ignores whatever follows it, so bytes appended to a
    checkpoint would otherwise load silently ([T-12]: the file is the checkpoint, whole).
    """
    at = raw.rfind(_EOCD, max(0, len(raw) - _EOCD_SIZE - 0xFFFF))
    if at < 0 or len(raw) - at < _EOCD_SIZE:
        raise ValueError("no end-of-archive record")
    end = at + _EOCD_SIZE + int.from_bytes(raw[at + 20:at + 22], "little")
    if end != len(raw):
        raise ValueError(f"{len(raw) - end} bytes after the end of the archive" if end < len(raw)
                         else "the end-of-archive record is cut short")


def read_checkpoint(path: str | os.PathLike) -> tuple[dict, dict]:
    """Reads and verifies a checkpoint; returns ``(pure_dict, header)`` ([T-12]).

    Checks, in order, raising ``ValueError`` that names the file and the problem:
    the file is a readable archive that ends where its end-of-archive record ends
    (truncated, garbled or appended bytes fail here or at the checksum); it has a
    JSON header (one nested too deeply to parse is a corrupt header too); the format tag is :data:`FORMAT`; the version
    is :data:`VERSION`; the header lists exactly the stored arrays with their
    dtypes and shapes; the checksum matches. The tree is not yet compared with a
    policy (see :func:`load_checkpoint`).
    """
    if not isinstance(path, (str, os.PathLike)) or not os.path.isfile(path):
        raise ValueError(f"path must name an existing checkpoint file, got {path!r}")
    try:
        with open(path, "rb") as f:
            raw = f.read()
        if raw[:4] in (b"PK\x03\x04", _EOCD):  # what np.load reads as a zip archive; other bytes fail below
            _check_archive_end(raw)
        loaded = np.load(io.BytesIO(raw), allow_pickle=False)
        if not isinstance(loaded, np.lib.npyio.NpzFile):  # a .npy file loads as a bare array
            raise ValueError("a single array (.npy), not an .npz archive")
        with loaded as npz:
            members = {name: npz[name] for name in npz.files}
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, KeyError) as exc:
        raise _fail(path, f"corrupt or not an .npz checkpoint (unreadable archive: {exc})") from exc

    if HEADER_KEY not in members:
        raise _fail(path, f"no '{HEADER_KEY}' member; not a softrtc checkpoint")
    head = members.pop(HEADER_KEY)
    try:
        if head.dtype != np.uint8 or head.ndim != 1:
            raise ValueError("header is not a uint8 vector")
        header = json.loads(head.tobytes().decode("utf-8"))
        if not isinstance(header, dict):
            raise ValueError("header JSON is not an object")
    except (ValueError, UnicodeDecodeError) as exc:
        raise _fail(path, f"corrupt header ({exc})") from exc
    except RecursionError:
        # json.loads recurses once per nesting level: a crafted header must not end in a traceback.
        raise _fail(path, "corrupt header (JSON nested too deeply to read)") from None

    if header.get("format") != FORMAT:
        raise _fail(path, f"format tag must be {FORMAT!r}, got {header.get('format')!r}")
    if header.get("version") != VERSION:
        raise _fail(path, f"format version {header.get('version')!r} is not supported (expected {VERSION})")
    listed = header.get("arrays")
    if not isinstance(listed, dict):
        raise _fail(path, "header has no 'arrays' table")
    if set(listed) != set(members):
        missing, extra = sorted(set(listed) - set(members)), sorted(set(members) - set(listed))
        raise _fail(path, f"stored arrays differ from the header (missing {missing}, unlisted {extra})")
    for name, a in members.items():
        spec = listed[name]
        if not isinstance(spec, dict) or spec.get("dtype") != a.dtype.str or spec.get("shape") != list(a.shape):
            raise _fail(path, f"array '{name}' has dtype {a.dtype.str} and shape {list(a.shape)}, "
                              f"header says {spec}")
    try:
        checksum = checkpoint_checksum(header, members)
    except ValueError as exc:  # e.g. NaN in the metadata, which no writer of this format produces
        raise _fail(path, f"corrupt header ({exc})") from exc
    except RecursionError:  # metadata nested just under json.loads's limit still overflows the checks' recursion
        raise _fail(path, "corrupt header (JSON nested too deeply to check)") from None
    if header.get("checksum") != checksum:
        raise _fail(path, "checksum mismatch (the file was modified or damaged)")
    if not all(name.startswith(PARAM_PREFIX) for name in members):
        raise _fail(path, f"array names must start with '{PARAM_PREFIX}'")
    pure = _nest({name[len(PARAM_PREFIX):]: a for name, a in members.items()})
    return pure, header


def load_checkpoint(path: str | os.PathLike, policy: FlowPolicy | None = None) -> tuple[FlowPolicy, dict]:
    """Loads a checkpoint written by :func:`save_checkpoint`; returns ``(policy, metadata)`` ([T-12]).

    Without ``policy`` a new :class:`FlowPolicy` is built from the stored
    constructor arguments; with one, its ``obs_dim``, ``action_dim`` and config
    must equal the stored ones and its parameters are replaced in place. After
    the checks of :func:`read_checkpoint`, the stored policy config must be valid
    and the parameter tree must match it key by key and shape by shape
    (``policy.load_pure_dict``); each failure is a ``ValueError`` naming the
    problem.
    """
    pure, header = read_checkpoint(path)
    spec = header.get("policy")
    try:
        if not isinstance(spec, dict) or not isinstance(spec.get("config"), dict):
            raise ValueError("header has no 'policy' section with a 'config' object")
        config = PolicyConfig(**spec["config"])
        obs_dim, action_dim = spec.get("obs_dim"), spec.get("action_dim")
        if policy is None:
            # Initial values are overwritten below; the seed only fixes the shapes' creation.
            policy = FlowPolicy(obs_dim=obs_dim, action_dim=action_dim, config=config, rngs=nnx.Rngs(0))
    except (TypeError, ValueError) as exc:
        raise _fail(path, f"invalid policy constructor config ({exc})") from exc
    if not isinstance(policy, FlowPolicy):
        raise ValueError(f"policy must be a FlowPolicy or None, got {type(policy).__name__}")
    if (policy.obs_dim, policy.action_dim, policy.config) != (obs_dim, action_dim, config):
        raise _fail(path, f"stored policy (obs_dim={obs_dim}, action_dim={action_dim}, {config}) differs from "
                          f"the given policy (obs_dim={policy.obs_dim}, action_dim={policy.action_dim}, "
                          f"{policy.config})")
    try:
        load_pure_dict(policy, pure)
    except ValueError as exc:
        raise _fail(path, f"state does not match the policy config: {exc}") from exc
    return policy, header.get("metadata", {})
