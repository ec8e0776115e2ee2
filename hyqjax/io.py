"""Results on disk: JSON with the command, versions, seed and date that produced it."""
from __future__ import annotations

import datetime
import json
import os
import platform
import sys

import numpy as np


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
        "command": " ".join(["hyqjax", *(sys.argv[1:] if argv is None else argv)]),
        "seed": seed,
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "hyqjax": hyqjax.__version__,
        "jax": jax.__version__,
        "mujoco": mujoco.__version__,
        "mujoco_mjx": mjx_version,
        "python": platform.python_version(),
        "devices": [str(d) for d in jax.devices()],
    }


def _default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    return str(o)


def atomic_write(path: str, write) -> None:
    """Write a file so that a reader (or a resumed run after a kill) sees the old or the new one, never a part:
    ``write(f)`` fills a temporary binary file beside ``path``, which is synced and renamed over it."""
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "wb") as f:
        write(f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def write_json(path: str, obj) -> None:
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=1, default=_default, allow_nan=True)
    os.replace(tmp, path)
