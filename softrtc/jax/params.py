"""The policy's parameter tree as the public release stores it: pure dicts and pickled checkpoints ([P-7], [P-8])."""

from __future__ import annotations

import os
import pickle
from typing import Any, Mapping

import flax.nnx as nnx
import jax
import jax.numpy as jnp
import numpy as np

from .policy import FlowPolicy

__all__ = ["state_pure_dict", "load_pure_dict", "load_checkpoint"]


def _to_pure_dict(state: Any) -> dict:
    # flax >= 0.12 deprecates the State method in favour of the module-level function.
    fn = getattr(nnx, "to_pure_dict", None)
    return fn(state) if fn is not None else state.to_pure_dict()


def _replace_by_pure_dict(state: Any, pure: dict) -> None:
    fn = getattr(nnx, "replace_by_pure_dict", None)
    if fn is not None:
        fn(state, pure)
    else:
        state.replace_by_pure_dict(pure)


def state_pure_dict(model: FlowPolicy) -> dict:
    """``nnx.state(model).to_pure_dict()``: the dict the public release pickles per policy [P-8]."""
    if not isinstance(model, FlowPolicy):
        raise ValueError(f"model must be a FlowPolicy, got {type(model).__name__}")
    return _to_pure_dict(nnx.state(model))


def _flatten(tree: Any, prefix: tuple = ()) -> dict[tuple, Any]:
    out: dict[tuple, Any] = {}
    for k, v in tree.items():
        path = prefix + (k,)
        if isinstance(v, Mapping):
            out.update(_flatten(v, path))
        else:
            out[path] = v
    return out


def _path_str(path: tuple) -> str:
    return "/".join(str(p) for p in path)


def load_pure_dict(model: FlowPolicy, pure_dict: Mapping) -> FlowPolicy:
    """Validates ``pure_dict`` against ``model``'s parameter tree and loads it in place [P-8].

    ``pure_dict`` is a nested dict as written by ``nnx.state(model).to_pure_dict()``
    (layer indices as ints; digit strings are accepted too). Every key path must
    match, with the exact shape and a floating dtype and finite values; leaves are
    cast to the model's dtype and must still be finite after the cast (a float64
    ``1e39`` is rejected, as it would become ``inf`` in float32). Raises ``ValueError`` naming the key path (e.g.
    ``mlp_stack/0/adaln_1/kernel``) and the expected shape. Returns ``model``.
    """
    if not isinstance(model, FlowPolicy):
        raise ValueError(f"model must be a FlowPolicy, got {type(model).__name__}")
    if not isinstance(pure_dict, Mapping):
        raise ValueError(f"pure_dict must be a nested mapping of arrays, got {type(pure_dict).__name__}")
    state = nnx.state(model)
    expected = _flatten(_to_pure_dict(state))
    by_name = {tuple(str(p) for p in path): path for path in expected}

    given: dict[tuple, Any] = {}
    for path, leaf in _flatten(pure_dict).items():
        key = tuple(str(p) for p in path)
        if key not in by_name:
            # A leaf where the model has a subtree is also "unexpected" at this path.
            raise ValueError(f"pure_dict has unexpected key '{_path_str(key)}' (not a parameter of this FlowPolicy)")
        if key in given:  # e.g. layer 0 given both as 0 and as "0"
            raise ValueError(f"pure_dict gives key '{_path_str(key)}' twice (as {path!r} and another spelling)")
        given[key] = leaf
    for key, path in by_name.items():
        if key not in given:
            shape = tuple(expected[path].shape)
            raise ValueError(f"pure_dict is missing key '{_path_str(key)}' (expected shape {shape})")

    loaded: dict[tuple, jax.Array] = {}
    for key, path in by_name.items():
        ref = expected[path]
        name = f"pure_dict['{_path_str(key)}']"
        try:
            arr = np.asarray(given[key])
        except Exception as exc:  # noqa: BLE001 - any non-array leaf is a format error
            raise ValueError(f"{name} must be an array of shape {tuple(ref.shape)}") from exc
        if tuple(arr.shape) != tuple(ref.shape):
            raise ValueError(f"{name} has shape {tuple(arr.shape)}, expected shape {tuple(ref.shape)}")
        if not np.issubdtype(arr.dtype, np.floating):
            raise ValueError(f"{name} must have a floating dtype, got {arr.dtype}")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} must contain only finite values")
        # Finite in float64 may still overflow the parameter dtype (1e39 -> inf in float32): check after the cast.
        with np.errstate(over="ignore"):
            cast = arr.astype(ref.dtype)
        if not np.all(np.isfinite(cast)):
            raise ValueError(f"{name} must contain only finite values within the range of {np.dtype(ref.dtype)} "
                             f"(the parameter dtype)")
        loaded[path] = jnp.asarray(cast)

    nested: dict = {}
    for path, arr in loaded.items():
        node = nested
        for p in path[:-1]:
            node = node.setdefault(p, {})
        node[path[-1]] = arr
    _replace_by_pure_dict(state, nested)
    nnx.update(model, state)
    return model


def load_checkpoint(model: FlowPolicy, path: str | os.PathLike) -> FlowPolicy:
    """Loads a public-format ``bc`` checkpoint (a pickled pure dict) into ``model`` [P-8].

    The file is unpickled, so only load files you trust. Public layout:
    ``<run>/<epoch>/policies/<level_name>.pkl``, e.g. ``worlds_l_grasp_easy.pkl``.
    """
    if not isinstance(path, (str, os.PathLike)) or not os.path.isfile(path):
        raise ValueError(f"path must name an existing checkpoint file, got {path!r}")
    try:
        with open(path, "rb") as f:
            pure = pickle.load(f)
    except (pickle.UnpicklingError, EOFError, AttributeError, ImportError, IndexError, TypeError) as exc:
        raise ValueError(f"{os.fspath(path)}: not a readable pickled checkpoint ({type(exc).__name__}: {exc})") from exc
    return load_pure_dict(model, pure)
