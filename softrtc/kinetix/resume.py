"""Resume files of the Kinetix training runs ([KP-7], [KP-12]): a training state and its metadata in one
``.npz``, written atomically, read back against a template of the same structure.

Every leaf of the state is stored as ``leaf_<i>`` (typed PRNG keys as their key data) and the metadata as
JSON, so a restarted run continues bitwise from the last block or epoch.
"""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from softrtc._files import write_atomic

__all__ = ["save_state", "load_state"]


def save_state(path: Path, state, meta: dict) -> None:
    """``state`` (a pytree of arrays) and ``meta`` (JSON) to ``path``, replacing it whole."""
    arrays = {}
    for i, leaf in enumerate(jax.tree.leaves(state)):
        if jnp.issubdtype(leaf.dtype, jax.dtypes.prng_key):
            leaf = jax.random.key_data(leaf)
        arrays[f"leaf_{i:05d}"] = np.asarray(leaf)
    arrays["meta"] = np.frombuffer(json.dumps(meta, sort_keys=True).encode(), np.uint8)
    write_atomic(path, lambda f: np.savez(f, **arrays), binary=True)


def load_state(path: Path, template, what: str) -> tuple:
    """``(state, meta)`` from a file of :func:`save_state`; a file whose leaves differ from ``template``'s in
    number, shape or dtype is a ValueError saying it does not match ``what`` (e.g. "this configuration")."""
    leaves, treedef = jax.tree.flatten(template)
    with np.load(path) as z:
        meta = json.loads(bytes(z["meta"]).decode())
        if len([k for k in z.files if k.startswith("leaf_")]) != len(leaves):
            raise ValueError(f"resume file {path} does not match {what} (leaf count differs)")
        out = []
        for i, t in enumerate(leaves):
            a = z[f"leaf_{i:05d}"]
            if jnp.issubdtype(t.dtype, jax.dtypes.prng_key):
                out.append(jax.random.wrap_key_data(jnp.asarray(a), impl=jax.random.key_impl(t)))
                continue
            if a.shape != t.shape or a.dtype != t.dtype:
                raise ValueError(f"resume file {path} does not match {what} "
                                 f"(leaf {i}: {a.dtype}{list(a.shape)} vs {t.dtype}{list(t.shape)})")
            out.append(jnp.asarray(a))
    return jax.tree.unflatten(treedef, out), meta
