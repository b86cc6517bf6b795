"""Compile once: JAX's persistent compilation cache and a traced-program cache ([KC-1]..[KC-5]).

Two layers, both on by default in a per-user folder ([KC-1]):

* JAX's persistent compilation cache (``<dir>/xla``): every jitted function
  whose compilation takes at least ``MIN_COMPILE_S`` is stored and reloaded by
  later processes. Its size is bounded (``MAX_CACHE_BYTES``, least recently
  used entries evicted), which also makes JAX lock the folder with a file lock
  around every read and write, so runs sharing the folder never see half a
  file ([KC-2]).
* A program cache (``<dir>/programs``) for the big closed-loop programs
  (Kinetix rollouts, [KC-3]): the compiled executable is serialised under a
  key of everything that shapes it (argument shapes and shardings, the
  configuration, the versions of JAX, jaxlib, flax and kinetix, and a digest
  of the source files of ``softrtc`` and ``kinetix``), so a repeated
  configuration skips *tracing* as well as compiling; tracing the Kinetix
  physics alone takes longer than the 10% compile budget. Files are written
  to a temporary name and renamed, so a concurrent reader sees the whole file
  or none; an unreadable entry is recompiled and replaced.

The folder is ``$SOFTRTC_JAX_CACHE`` when set (``off`` disables both layers),
else ``$XDG_CACHE_HOME/softrtc/jax`` or ``~/.cache/softrtc/jax``; the command
line's ``--compile-cache DIR`` / ``--no-compile-cache`` override both.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import os
import pickle
import platform
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Sequence

import jax
import numpy as np

from softrtc._files import CACHE_ENV, default_cache_dir, unwritable_reason, write_atomic
from softrtc._machine import cpu_features, cpu_model

__all__ = ["CACHE_ENV", "MIN_COMPILE_S", "MAX_CACHE_BYTES", "default_cache_dir", "enable_compile_cache",
           "cache_dir", "source_fingerprint", "host_id", "program_key", "compile_program", "CompiledProgram",
           "clear_memory"]

# [KC-2] programs that compile faster than this are not worth a file.
MIN_COMPILE_S = 0.5
# [KC-2] bound of the XLA layer; setting it turns on JAX's eviction and its file lock.
MAX_CACHE_BYTES = 8 << 30
# 2: stored programs are compiled with layer 1 off (a layer-1 hit does not serialise whole, [KC-3]).
_PROGRAM_FORMAT = 2

_state: dict = {"dir": None, "configured": False}
_memory: dict = {}


def enable_compile_cache(path: str | os.PathLike | None | bool = True) -> Path | None:
    """Turn the cache of [KC-1] on in ``path`` (``True``: :func:`default_cache_dir`) or off (``None``/``False``).

    Returns the folder in use, or ``None`` when off. An explicitly named folder that cannot be
    written is a ``ValueError``; the default folder that cannot be written turns the cache off with a
    warning (a read-only home never stops a run). Safe to call again; the last call wins.
    """
    explicit = path is not True
    if path is True:
        path = default_cache_dir()
    if path is None or path is False:
        jax.config.update("jax_compilation_cache_dir", None)
        _reset_jax_cache()
        _state.update(dir=None, configured=True)
        return None
    if not isinstance(path, (str, os.PathLike)) or not os.fspath(path):
        raise ValueError(f"path must be a folder path, True (the default folder) or None (off), got {path!r}")
    root = Path(path).expanduser()
    reason = unwritable_reason(root)
    if reason is not None:
        if explicit:
            raise ValueError(f"path {root} {reason} (the compile cache needs a writable folder)")
        warnings.warn(f"compile cache off: the default folder {root} {reason}; set {CACHE_ENV} to another folder",
                      stacklevel=2)
        return enable_compile_cache(None)
    (root / "xla" / host_id()).mkdir(parents=True, exist_ok=True)
    (root / "programs").mkdir(parents=True, exist_ok=True)
    # [KC-2]: JAX's own key names the device kind ("cpu") but not the host CPU's instruction set.
    jax.config.update("jax_compilation_cache_dir", str(root / "xla" / host_id()))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_S)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    jax.config.update("jax_compilation_cache_max_size", MAX_CACHE_BYTES)
    _reset_jax_cache()
    _state.update(dir=root, configured=True)
    return root


def _reset_jax_cache() -> None:
    # JAX opens its cache object on first use; a changed folder takes effect only after a reset.
    from jax.experimental.compilation_cache import compilation_cache as cc

    cc.reset_cache()


def cache_dir() -> Path | None:
    """The folder in use; the first call with nothing configured turns on the default ([KC-1])."""
    if not _state["configured"]:
        enable_compile_cache(True)
    return _state["dir"]


def clear_memory() -> None:
    """Forget the programs held in this process (their files stay), and JAX's in-memory caches."""
    _memory.clear()
    jax.clear_caches()


_FINGERPRINT: list = []


def source_fingerprint() -> str:
    """SHA-256 over the versions of jax, jaxlib, flax and kinetix-env and the bytes of every ``.py`` file of
    the ``softrtc`` and ``kinetix`` packages ([KC-3]): any edit to code a program is traced from changes it."""
    if _FINGERPRINT:
        return _FINGERPRINT[0]
    import kinetix

    import softrtc
    import softrtc.reference

    h = hashlib.sha256()
    for dist in ("jax", "jaxlib", "flax", "kinetix-env"):
        try:
            h.update(f"{dist}={importlib.metadata.version(dist)};".encode())
        except importlib.metadata.PackageNotFoundError:
            h.update(f"{dist}=?;".encode())
    roots = {Path(softrtc.__file__).parent, Path(softrtc.reference.__file__).parent, Path(kinetix.__file__).parent}
    for root in sorted(roots):
        for f in sorted(root.rglob("*.py")):
            h.update(str(f.relative_to(root)).encode())
            h.update(hashlib.sha256(f.read_bytes()).digest())
    _FINGERPRINT.append(h.hexdigest())
    return _FINGERPRINT[0]


def host_id() -> str:
    """16 hex digits of SHA-256 of the machine type, CPU model and CPU feature flags ([KC-2], [KC-3]).

    An XLA:CPU executable uses the instructions of the CPU it was compiled on; a cache folder shared by
    machines of different CPUs (a home folder on a cluster) must not hand one machine's programs to another.
    """
    parts = [platform.machine(), cpu_model(), list(cpu_features())]
    return hashlib.sha256(json.dumps(parts).encode()).hexdigest()[:16]


def _is_key(x) -> bool:
    return hasattr(x, "dtype") and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def program_key(name: str, config: Any, flat_avals: Sequence, flat_shardings: Sequence, treedef,
                out_sharding) -> str:
    """The key of a program ([KC-3]): SHA-256 of its name, ``config`` (its ``repr``), the flat argument
    shapes, dtypes and shardings, the argument tree, the devices, the host CPU (:func:`host_id`) and
    :func:`source_fingerprint`."""
    devs = jax.devices()
    parts = {"format": _PROGRAM_FORMAT, "name": name, "config": repr(config),
             "avals": [(tuple(a.shape), str(a.dtype)) for a in flat_avals],
             "shardings": [repr(s) for s in flat_shardings], "out": repr(out_sharding), "tree": str(treedef),
             "devices": [(d.platform, d.device_kind, d.id) for d in devs], "processes": jax.process_count(),
             "x64": bool(jax.config.jax_enable_x64), "xla_flags": os.environ.get("XLA_FLAGS", ""), "host": host_id(),
             "source": source_fingerprint()}
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()


class CompiledProgram:
    """A compiled program that takes the original (nested) arguments ([KC-3], [KD-2]).

    Arguments are flattened, PRNG key arrays passed as their key data, and, when several processes
    share the run, every argument is placed as a global array from the copy every process holds.
    """

    def __init__(self, compiled, treedef, key_impls, flat_shardings, seconds: float, source: str):
        self.compiled, self.treedef, self.key_impls = compiled, treedef, key_impls
        self.flat_shardings = flat_shardings
        self.seconds, self.source = seconds, source

    def __call__(self, *args):
        leaves, treedef = jax.tree.flatten(args)
        if treedef != self.treedef:
            raise ValueError(f"args must have the structure the program was compiled for, got {treedef}")
        flat = [jax.random.key_data(x) if impl is not None else x for x, impl in zip(leaves, self.key_impls)]
        if jax.process_count() > 1:
            flat = [_global(x, s) for x, s in zip(flat, self.flat_shardings)]
        return self.compiled(*flat)


def _compile(lowered, *, bypass_layer1: bool):
    """Compile ``lowered``; with ``bypass_layer1`` JAX's persistent cache is neither read nor written.

    XLA:CPU executables that JAX loaded from its persistent cache serialise without some of their
    kernels (jaxlib 0.9: the reloaded file fails with "Function ... not found"), so a program meant
    for layer 2 is always compiled from its lowering ([KC-3])."""
    if not bypass_layer1:
        return lowered.compile()
    # JAX decides once per process whether its cache is in use; a reset makes it read the flag again.
    before = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)
    _reset_jax_cache()
    try:
        return lowered.compile()
    finally:
        jax.config.update("jax_enable_compilation_cache", before)
        _reset_jax_cache()


def _global(x, sharding):
    """A global array of ``sharding`` built from this process's full copy ``x`` (every process holds the same)."""
    host = np.asarray(jax.device_get(x))
    return jax.make_array_from_callback(host.shape, sharding, lambda idx: host[idx])


def compile_program(name: str, fn: Callable, args: tuple, in_shardings: Sequence, out_sharding, *,
                    config: Any = None, use_cache: bool = True) -> CompiledProgram:
    """Compile ``fn(*args)`` or load it from the program cache ([KC-3]).

    ``in_shardings`` gives one sharding per top-level argument (applied to all its leaves);
    ``config`` is anything else that shapes the traced code (its ``repr`` enters the key). Within a
    process a program is compiled once. ``.seconds`` of the result is the time this call took and
    ``.source`` says where the program came from: ``"memory"``, ``"disk"`` or ``"compiled"``.
    """
    if not isinstance(args, tuple) or len(args) != len(in_shardings):
        raise ValueError(f"args must be a tuple with one entry per in_shardings entry ({len(in_shardings)})")
    t0 = time.perf_counter()
    leaves, treedef = jax.tree.flatten(args)
    key_impls = [jax.random.key_impl(x) if _is_key(x) else None for x in leaves]
    flat_sh = [s for a, s in zip(args, in_shardings) for _ in jax.tree.leaves(a)]
    avals = [jax.ShapeDtypeStruct(jax.random.key_data(x).shape if impl is not None else np.shape(x),
                                  np.uint32 if impl is not None else x.dtype, sharding=s)
             for x, impl, s in zip(leaves, key_impls, flat_sh)]
    key = program_key(name, config, avals, flat_sh, treedef, out_sharding)
    if key in _memory:
        prog = _memory[key]
        return CompiledProgram(prog.compiled, treedef, key_impls, flat_sh, time.perf_counter() - t0, "memory")
    root = cache_dir() if use_cache else None
    # Several processes each hold their own executable; only a single-process program is stored.
    store = root is not None and jax.process_count() == 1
    path = root / "programs" / f"{name}-{key[:40]}.bin" if store else None
    compiled, source = None, "compiled"
    if path is not None and path.is_file():
        try:
            from jax.experimental import serialize_executable as se

            blob = pickle.loads(path.read_bytes())
            if blob.get("key") != key:
                raise ValueError("key mismatch")
            compiled = se.deserialize_and_load(blob["exe"], blob["in_tree"], blob["out_tree"])
            source = "disk"
        except Exception as exc:  # a damaged or foreign entry is recompiled and replaced
            warnings.warn(f"program cache entry {path} unreadable ({type(exc).__name__}: {exc}); recompiling",
                          stacklevel=2)
            compiled = None
    if compiled is None:
        def flat_fn(*flat):
            xs = [jax.random.wrap_key_data(x, impl=impl) if impl is not None else x
                  for x, impl in zip(flat, key_impls)]
            return fn(*jax.tree.unflatten(treedef, xs))

        jitted = jax.jit(flat_fn, in_shardings=tuple(flat_sh), out_shardings=out_sharding)
        compiled = _compile(jitted.lower(*avals), bypass_layer1=path is not None)
        source = "compiled"
        if path is not None:
            try:
                from jax.experimental import serialize_executable as se

                exe, in_tree, out_tree = se.serialize(compiled)
                blob = pickle.dumps({"key": key, "exe": exe, "in_tree": in_tree, "out_tree": out_tree})
                write_atomic(path, lambda f: f.write(blob), binary=True)
            except Exception as exc:  # a program that cannot be serialised still runs
                warnings.warn(f"program {name} not stored in the cache ({type(exc).__name__}: {exc})", stacklevel=2)
    prog = CompiledProgram(compiled, treedef, key_impls, flat_sh, time.perf_counter() - t0, source)
    _memory[key] = prog
    return prog
