"""Output files and folders shared by every writer of the package ([N-7], [N-11]).

Standard library only. ``check_out_dir`` is the one up-front check of a
folder a function will write into; ``write_atomic`` writes a file whole or
not at all (temporary file in the same folder, then rename).
"""

from __future__ import annotations

import json
import os
import tempfile
from importlib import resources
from pathlib import Path
from typing import Callable, IO


def package_data_dir(package: str, name: str) -> Path:
    """The folder ``name`` shipped as package data of ``package``, found through ``importlib.resources``
    so that an installed wheel finds it wherever it lies (an unpacked install; an archive is refused)."""
    root = resources.files(package).joinpath(name)
    if not isinstance(root, Path):
        raise OSError(f"{package}'s data folder {name} is inside an archive ({root}); install softrtc unpacked")
    return root


def check_out_dir(name: str, value, files: tuple = ()) -> Path:
    """``value`` as a Path to a folder that exists or can be created, under a writable folder, holding no
    folder named like one of ``files`` (the files the caller will write). Raises ValueError naming ``name``."""
    if not isinstance(value, (str, os.PathLike)) or not isinstance(os.fspath(value), str) or not os.fspath(value):
        raise ValueError(f"{name} must be a non-empty str or PathLike folder path, got {value!r}")
    out = Path(value)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{name} must be a directory (or a path to create), but {out} is a file")
    reason = unwritable_reason(out)
    if reason:
        raise ValueError(f"{name} {out} {reason}")
    for f in files:
        if (out / f).is_dir():
            raise ValueError(f"{name} must not hold a directory named {f}: {out / f}")
    return out


def check_out_file(name: str, value, suffix: str) -> str:
    """``value`` as the path of a file to write: a str or PathLike ending in ``suffix``, not a folder, in an
    existing writable folder. Raises ValueError naming ``name``."""
    if not isinstance(value, (str, os.PathLike)) or not isinstance(os.fspath(value), str) \
            or not os.fspath(value).endswith(suffix):
        raise ValueError(f"{name} must be a str or PathLike ending in {suffix!r}, got {value!r}")
    parent = os.path.dirname(os.path.abspath(os.fspath(value)))
    if not os.path.isdir(parent):
        raise ValueError(f"{name}'s folder {parent!r} does not exist")
    if os.path.isdir(value):
        raise ValueError(f"{name} {os.fspath(value)!r} is a folder, expected a {suffix} file name")
    if not os.access(parent, os.W_OK):
        raise ValueError(f"{name}'s folder {parent!r} is not writable")
    return os.fspath(value)


def unwritable_reason(folder) -> str | None:
    """None when ``folder``, or its nearest existing ancestor (the rest is created), takes new files; else why not,
    as the end of a sentence that starts with the folder's name ("cannot be written: /x is a file").

    ``os.access`` trusts permission bits (and root passes them everywhere, a
    read-only mount included), so the check creates and removes a scratch file.
    """
    base = Path(folder).absolute()
    while not base.exists() and base != base.parent:
        base = base.parent
    if not base.is_dir():
        return f"cannot be created: {base} is a file"
    if not os.access(base, os.W_OK | os.X_OK):
        return f"cannot be written: {base} is not a writable directory"
    try:
        with tempfile.TemporaryFile(dir=base):
            pass
    except OSError as exc:
        return f"cannot be written: {base} does not take new files ({exc.strerror or exc})"
    return None


def write_atomic(path, write: Callable[[IO], None], *, binary: bool = False, prefix: str = ".softrtc-") -> None:
    """Call ``write(f)`` on a temporary file next to ``path``, then rename it to ``path``.

    A failure (or an interrupt) leaves an existing ``path`` untouched and no
    temporary file behind. The new file gets the mode any new file has under
    the umask (``mkstemp`` would leave it owner-only).
    """
    parent = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=".tmp", dir=parent)
    try:
        with os.fdopen(fd, "wb" if binary else "w") as f:
            write(f)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


CACHE_ENV = "SOFTRTC_JAX_CACHE"
_CACHE_OFF = ("", "0", "off", "none", "false", "no")


def default_cache_dir() -> Path | None:
    """The folder of compiled JAX programs ([KC-1], [CF-17]): ``$SOFTRTC_JAX_CACHE`` (``None`` when it says
    ``off``, ``0``, ``none``, ``false``, ``no`` or is empty), else ``$XDG_CACHE_HOME/softrtc/jax``, else
    ``~/.cache/softrtc/jax``. JAX's own persistent cache lives in its ``xla`` subfolder."""
    env = os.environ.get(CACHE_ENV)
    if env is not None:
        return None if env.strip().lower() in _CACHE_OFF else Path(env.strip()).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base).expanduser() / "softrtc" / "jax"


def write_json(path, obj, *, prefix: str = ".softrtc-", allow_nan: bool = False) -> None:
    """``obj`` as indented JSON with sorted keys, written whole or not at all; its folder is made if missing."""
    text = json.dumps(obj, indent=1, sort_keys=True, allow_nan=allow_nan) + "\n"
    os.makedirs(os.path.dirname(os.path.abspath(os.fspath(path))), exist_ok=True)
    write_atomic(path, lambda f: f.write(text), prefix=prefix)


def read_json(path, what: str = "file"):
    """The JSON value of the existing file ``path`` (``what`` names it in the error) ([N-7])."""
    if not isinstance(path, (str, os.PathLike)) or not os.path.isfile(path):
        raise ValueError(f"path must name an existing {what}, got {path!r}")
    with open(path, encoding="utf-8") as f:
        return json.load(f)
