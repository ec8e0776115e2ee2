"""Results on disk: atomic files, strict JSON, and the command, versions, seed and date that produced them.

Atomic write: ``atomic_write(path, write)`` fills a uniquely named temporary file beside ``path``
(``.NAME.tmp-<pid>-<random>``), syncs it and ``os.replace``s it over ``path``, so a reader, or a run
resumed after a kill at any instant, sees the old file or the new one, never a part. A kill before the
rename leaves the temporary behind; :func:`clean_temporaries` removes those of dead writers.

Strict JSON: :func:`to_jsonable` maps NumPy scalars and arrays to Python values and non-finite floats
(NaN, +-inf) to ``null``, so every file written by :func:`write_json` is valid JSON (RFC 8259) that any
parser reads.
"""
from __future__ import annotations

import datetime
import json
import math
import os
import platform
import secrets
import sys

import numpy as np

TMP_MARK = ".tmp-"


def program(path: str | None = None) -> str:
    """How the running program is started, for a result's recorded command: ``python -m experiments.reach_map`` for
    a module of the repository's ``experiments`` or ``benchmarks`` (``sys.argv[0]`` is then its file), ``hyqjax``
    for the command line tool."""
    path = sys.argv[0] if path is None else path
    parts = os.path.normpath(path).split(os.sep)
    if path.endswith(".py") and len(parts) >= 2 and parts[-2] == "experiments":
        return f"python -m experiments.{parts[-1][:-3]}"
    if path.endswith(".py") and len(parts) >= 2 and parts[-2] == "benchmarks":
        return f"python benchmarks/{parts[-1]}"
    return "hyqjax"


def provenance(argv: list[str] | None = None, seed: int | None = None) -> dict:
    import jax
    import mujoco

    try:
        from importlib.metadata import version

        mjx_version = version("mujoco-mjx")
    except Exception:  # pragma: no cover
        mjx_version = "unknown"
    import hyqjax

    return {
        "command": " ".join([program(), *(sys.argv[1:] if argv is None else argv)]),
        "seed": seed,
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "hyqjax": hyqjax.__version__,
        "jax": jax.__version__,
        "mujoco": mujoco.__version__,
        "mujoco_mjx": mjx_version,
        "python": platform.python_version(),
        "devices": [str(d) for d in jax.devices()],
    }


def to_jsonable(o):
    """``o`` as plain JSON values: arrays to lists, NumPy scalars to Python, non-finite floats to None."""
    if isinstance(o, dict):
        return {str(k): to_jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [to_jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return to_jsonable(o.tolist())
    if isinstance(o, (np.bool_, bool)):
        return bool(o)
    if isinstance(o, (np.integer, int)):
        return int(o)
    if isinstance(o, (np.floating, float)):
        f = float(o)
        return f if math.isfinite(f) else None
    if o is None or isinstance(o, str):
        return o
    return str(o)


def dumps(obj, indent: int | None = 1) -> str:
    """Strict JSON text of ``obj`` (see :func:`to_jsonable`)."""
    return json.dumps(to_jsonable(obj), indent=indent, allow_nan=False)


def temporary_name(path: str) -> str:
    d, base = os.path.split(os.path.abspath(path))
    return os.path.join(d, f".{base}{TMP_MARK}{os.getpid()}-{secrets.token_hex(4)}")


def atomic_write(path: str, write) -> None:
    """Write a file so that a reader (or a resumed run after a kill) sees the old or the new one, never a part:
    ``write(f)`` fills a temporary binary file beside ``path``, which is synced and renamed over it."""
    tmp = temporary_name(path)
    try:
        with open(tmp, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def write_json(path: str, obj) -> None:
    """Atomic strict JSON (non-finite floats written as null)."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    text = dumps(obj).encode()
    atomic_write(path, lambda f: f.write(text))


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def clean_temporaries(directory: str, all_writers: bool = False) -> list[str]:
    """Remove the temporaries :func:`atomic_write` left in ``directory`` when its writer died (pid not alive on
    this host; every writer's with ``all_writers``, for a caller holding the directory's exclusive lock);
    returns the removed paths. Also removes the ``*.tmp<pid>`` files of earlier versions."""
    removed = []
    if not os.path.isdir(directory):
        return removed
    for name in os.listdir(directory):
        pid = None
        if TMP_MARK in name and name.startswith("."):
            head = name.rsplit(TMP_MARK, 1)[1].split("-", 1)[0]
            pid = int(head) if head.isdigit() else None
        elif ".tmp" in name:
            tail = name.rsplit(".tmp", 1)[1]
            pid = int(tail) if tail.isdigit() else (-1 if tail == "" else None)
        if pid is None or pid == os.getpid() or (not all_writers and pid > 0 and _pid_alive(pid)):
            continue
        p = os.path.join(directory, name)
        try:
            os.remove(p)
            removed.append(p)
        except FileNotFoundError:
            pass
    return removed


def check_writable_dir(path: str, option: str = "--out") -> str:
    """Create directory ``path`` (and parents) and check that a file can be written there.

    Raises ``ValueError`` naming ``option`` when ``path`` is a file, lies under a file, or is not writable.
    Called by every command before anything is compiled, so a run never simulates and then fails to save.
    """
    p = os.path.abspath(path)
    probe = p
    while not os.path.exists(probe):
        parent = os.path.dirname(probe)
        if parent == probe:
            break
        probe = parent
    if os.path.exists(probe) and not os.path.isdir(probe):
        raise ValueError(f"{option} {path}: {probe} is a file, not a directory; give a directory path")
    try:
        os.makedirs(p, exist_ok=True)
        tmp = temporary_name(os.path.join(p, "write-check"))
        with open(tmp, "wb") as f:
            f.write(b"")
        os.remove(tmp)
    except OSError as e:
        raise ValueError(f"{option} {path}: directory not writable ({e.strerror})") from None
    return p
