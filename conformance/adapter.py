"""The adapter interface between the conformance runner and an implementation ([CF-7]..[CF-12]).

An adapter is any object (a module works) with a ``name`` string, an optional
``time_convention`` ("data_at_1", the spec's, or "noise_at_1", [V-1]), an
optional ``to_numpy(x)`` and any subset of the functions of :data:`INTERFACE`.
Functions are called positionally, in the order listed there; a function the
adapter lacks makes its cases *unsupported*, never failed ([CF-9]).

Load one with :func:`load_adapter`: a built-in name (``reference``, ``jax``,
``torch``, ``torch-flipped``, ``lerobot``), ``package.module[:ATTR]`` or
``path/to/file.py[:ATTR]``. Without ``:ATTR`` the module's ``ADAPTER`` is used
when present, else the module itself. A file is imported from its path under a
module name of its own, never by its stem ([CF-12]).
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import re
import sys
from dataclasses import dataclass
from pathlib import Path

TIME_CONVENTIONS = ("data_at_1", "noise_at_1")

BUILTIN = {
    "reference": "softrtc.conformance.adapters.reference:ADAPTER",
    "jax": "softrtc.conformance.adapters.jax:ADAPTER",
    "torch": "softrtc.conformance.adapters.torch:ADAPTER",
    "torch-flipped": "softrtc.conformance.adapters.torch_flipped:ADAPTER",
    "lerobot": "softrtc.conformance.adapters.lerobot:ADAPTER",
}


@dataclass(frozen=True)
class Fn:
    """One interface function: positional arguments, outputs and the [V-1] mapping roles.

    kind: "value" (returns the single output), "tuple" (returns the outputs in
    order), "dict" (returns a mapping with the output names), "sample" (returns
    (chunk, trace) with trace a list of per-step dicts, or None).
    time_args / time_out are flow times (t' = 1 - t under "noise_at_1");
    vel_args / vel_out are velocities (u = -v).
    """

    args: tuple
    outputs: tuple
    kind: str = "value"
    time_args: tuple = ()
    vel_args: tuple = ()
    time_out: tuple = ()
    vel_out: tuple = ()
    int_out: tuple = ()


_S = ("chunk", "trace")
INTERFACE: dict[str, Fn] = {
    "endpoint": Fn(("rule", "d"), ("e",), int_out=("e",)),
    "prefix_weights": Fn(("H", "d", "e", "schedule", "parametrization"), ("weights",)),
    "weights": Fn(("H", "d", "window", "s"), ("weights",)),
    "hard_weights": Fn(("H", "d"), ("weights",)),
    "delay_probs": Fn(("dist", "d_min", "d_max", "decay"), ("probs",)),
    "sample_delay": Fn(("probs", "d_min", "u"), ("d",), int_out=("d",)),
    "corrupt": Fn(("actions", "noise", "weights", "tau"), ("x", "times"), "tuple",
                  time_args=("tau",), time_out=("times",)),
    "token_times": Fn(("weights", "t"), ("times",), time_args=("t",), time_out=("times",)),
    "loss": Fn(("pred", "actions", "noise", "weights"), ("loss",), vel_args=("pred",)),
    "batch_loss": Fn(("preds", "actions", "noise", "weights"), ("loss",), vel_args=("preds",)),
    "velocity": Fn(("field", "obs", "x", "t"), ("velocity",), time_args=("t",), vel_out=("velocity",)),
    "velocity_vjp": Fn(("field", "obs", "x", "t", "cotangent"), ("vjp",), time_args=("t",), vel_out=("vjp",)),
    "naive_sample": Fn(("field", "obs", "noise", "T"), _S, "sample"),
    "rtc_sample": Fn(("field", "obs", "noise", "prior", "weights", "T"), _S, "sample"),
    # [S-10] the training-time sampler with a named solver step; an adapter without it reports its cases
    # unsupported ([CF-9]), so adapters written before steps existed keep passing.
    "rtc_sample_step": Fn(("field", "obs", "noise", "prior", "weights", "T", "step"), _S, "sample"),
    "guided_sample": Fn(("field", "obs", "noise", "prior", "weights", "T", "max_guidance"), _S, "sample"),
    "method_weights": Fn(("method", "H", "s", "d", "window"), ("weights",)),
    "guidance_weights": Fn(("H", "s", "d", "variant"), ("weights",)),
    "guidance_weight": Fn(("t", "max_guidance"), ("lam",), time_args=("t",)),
    "shift_prior": Fn(("prev", "s"), ("prior",)),
    "execute_chunks": Fn(("chunks", "delays", "s"), ("actions", "chunk_index", "token_index"), "dict",
                         int_out=("chunk_index", "token_index")),
    "difference_norm": Fn(("actions", "order"), ("value",)),
    "action_delta": Fn(("actions",), ("value",)),
    "action_jerk": Fn(("actions",), ("value",)),
    "boundary_jump": Fn(("actions", "chunk_index"), ("value",)),
    "bootstrap_interval": Fn(("values", "indices", "confidence"), ("interval",)),
    "standard_error": Fn(("values",), ("value",)),
}

# Alternative forms of an interface function ([CF-27]): an adapter may provide the
# alternative instead of the function, or both (the function is tried first, the
# alternative when it is absent or raises NotImplementedError for the case). The
# alternative takes the case argument named by ``needs`` in place of others; a case
# without that argument cannot be run through it.
@dataclass(frozen=True)
class AltForm:
    name: str
    fn: Fn
    needs: str


GUIDANCE_KEYS = ("H", "s", "d", "variant", "schedule", "end", "max_guidance")
ALTERNATES: dict[str, AltForm] = {
    "guided_sample": AltForm("guided_sample_window",
                             Fn(("field", "obs", "noise", "prior", "guidance", "T"), _S, "sample"), "guidance"),
}


def forms(adapter, fname: str) -> list[tuple[str, Fn, str | None]]:
    """The adapter's callable forms of interface function ``fname``, in the order they are tried:
    ``(attribute name, Fn, needed case argument or None)`` ([CF-9], [CF-27])."""
    out = []
    if callable(getattr(adapter, fname, None)):
        out.append((fname, INTERFACE[fname], None))
    alt = ALTERNATES.get(fname)
    if alt is not None and callable(getattr(adapter, alt.name, None)):
        out.append((alt.name, alt.fn, alt.needs))
    return out


# Arguments that are arrays in the interface ([CF-7]); a list-valued ``t`` is one too. Everything else
# is passed as parsed from JSON ([CF-23]).
FLOAT_ARRAYS = frozenset({"actions", "noise", "weights", "pred", "preds", "obs", "x", "cotangent", "prior", "prev",
                          "chunks", "probs", "values"})
INT_ARRAYS = frozenset({"indices", "chunk_index", "delays"})

# The keys of a sampler trace step ([CF-11]).
TRACE_KEYS = {
    "naive_sample": ("state", "time", "velocity", "next_state"),
    "rtc_sample": ("state", "time", "velocity", "blended_state", "next_state"),
    "rtc_sample_step": ("state", "time", "velocity", "blended_state", "next_state"),
    "guided_sample": ("state", "time", "velocity", "denoised", "error", "vjp", "guidance_weight", "guided_velocity",
                      "next_state"),
}

# Keys of a sampler trace step that are flow times or velocities ([V-1]); the
# guidance pull-back "vjp" is taken through the denoiser x1, which both
# conventions share, so it is not negated.
TRACE_TIME_KEYS = ("time",)
TRACE_VEL_KEYS = ("velocity", "guided_velocity")


class AdapterError(Exception):
    """An adapter could not be loaded or is malformed; the message is one line."""


def _module_name(path: Path) -> str:
    """A module name no installed module uses, fixed per resolved path ([CF-12])."""
    digest = hashlib.sha256(str(path).encode("utf-8")).hexdigest()[:12]
    return f"_softrtc_adapter_{digest}_{_identifier(path.stem)}"


def _identifier(stem: str) -> str:
    return stem if stem.isidentifier() else re.sub(r"\W", "_", stem)


def _exec_file(modname: str, path: Path, package_dir: Path | None = None):
    """Execute ``path`` as module ``modname`` (a package when ``package_dir`` is given), registered in
    sys.modules for the duration of the run and removed again if it fails to import."""
    if modname in sys.modules:
        return sys.modules[modname]
    spec = importlib.util.spec_from_file_location(
        modname, path, submodule_search_locations=None if package_dir is None else [str(package_dir)])
    if spec is None or spec.loader is None:
        raise AdapterError(f"adapter file {path} cannot be imported as a Python module")
    module = importlib.util.module_from_spec(spec)
    sys.modules[modname] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        sys.modules.pop(modname, None)
        raise
    return module


def _import_path(path: Path):
    """Import an adapter file under a name of its own ([CF-12]).

    A file inside a package directory (one with ``__init__.py``) is imported as a submodule of that
    package, itself imported under a unique name, so its relative imports work; any other file is
    imported alone, its directory appended to the end of ``sys.path`` for helper modules beside it.
    The file's stem never decides which module is imported, so ``dir/random.py`` is not the
    standard ``random``.
    """
    path = path.resolve()
    if not path.is_file():
        raise AdapterError(f"adapter file {path} does not exist")
    pkg_dir = path.parent
    if (pkg_dir / "__init__.py").is_file():
        package = _exec_file(_module_name(pkg_dir), pkg_dir / "__init__.py", package_dir=pkg_dir)
        if path.name == "__init__.py":
            return package
        return _exec_file(f"{package.__name__}.{_identifier(path.stem)}", path)
    if str(pkg_dir) not in sys.path:
        sys.path.append(str(pkg_dir))
    return _exec_file(_module_name(path), path)


def _fatal(exc: BaseException) -> bool:
    """Whether ``exc`` must stop the run instead of being reported: only KeyboardInterrupt ([CF-18])."""
    return isinstance(exc, KeyboardInterrupt)


def load_adapter(spec: str):
    """Adapter object for a built-in name, ``module[:ATTR]`` or ``file.py[:ATTR]`` ([CF-12]).

    Raises AdapterError with a one-line message for anything that goes wrong, including a
    SystemExit or other BaseException raised while importing the adapter ([CF-16], [CF-18]);
    only KeyboardInterrupt passes through.
    """
    if not isinstance(spec, str) or not spec.strip():
        raise AdapterError("impl must be a non-empty string: a built-in name "
                           f"{tuple(BUILTIN)}, module[:ATTR] or path/file.py[:ATTR]")
    target = BUILTIN.get(spec, spec)
    mod_part, attr = target.rsplit(":", 1) if ":" in target else (target, "")
    try:
        if mod_part.endswith(".py") or "/" in mod_part or "\\" in mod_part:
            module = _import_path(Path(mod_part))
        else:
            module = importlib.import_module(mod_part)
    except AdapterError:
        raise
    except BaseException as exc:  # any import failure, SystemExit included, becomes one clear line
        if _fatal(exc):
            raise
        raise AdapterError(f"cannot import adapter module '{mod_part}' for impl '{spec}': "
                           f"{_describe(exc)}") from None
    if attr:
        if not hasattr(module, attr):
            raise AdapterError(f"adapter module '{mod_part}' has no attribute '{attr}'")
        adapter = getattr(module, attr)
    else:
        adapter = getattr(module, "ADAPTER", module)
    check_adapter(adapter)
    return adapter


def check_adapter(adapter) -> None:
    """Check the adapter's attributes ([CF-8]); raise AdapterError naming what is wrong."""
    name = getattr(adapter, "name", None)
    if not isinstance(name, str) or not name:
        raise AdapterError("adapter must have a non-empty string attribute 'name'")
    tc = getattr(adapter, "time_convention", "data_at_1")
    if tc not in TIME_CONVENTIONS:
        raise AdapterError(f"adapter.time_convention must be one of {TIME_CONVENTIONS}, got {tc!r}")
    for fname in list(INTERFACE) + [a.name for a in ALTERNATES.values()]:
        fn = getattr(adapter, fname, None)
        if fn is not None and not callable(fn):
            raise AdapterError(f"adapter.{fname} must be callable or absent, got {type(fn).__name__}")
    conv = getattr(adapter, "to_numpy", None)
    if conv is not None and not callable(conv):
        raise AdapterError("adapter.to_numpy must be callable or absent")


def supported_functions(adapter) -> list[str]:
    """Interface functions the adapter provides, itself or through an alternative form ([CF-9], [CF-27])."""
    return [f for f in INTERFACE if forms(adapter, f)]


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else ""


def _describe(exc: BaseException) -> str:
    """``Type: first line`` of an exception, or ``Type`` alone when it has no message (``sys.exit()``)."""
    line = _first_line(exc)[:300]
    return f"{type(exc).__name__}: {line}" if line else type(exc).__name__
