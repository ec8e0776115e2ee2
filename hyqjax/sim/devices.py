"""Which devices a batch runs on: every local device by default, or those a user picks (``--devices``).

A batch of instances runs over several devices of one host as ``split`` (:func:`hyqjax.sim.runner.run_on`): the
batch in N equal contiguous slices (the last padded by repeating the last instance), one single-device program per
device (the same static setup; on a GPU the persistent compilation cache, whose key leaves out the device, serves
devices 1..N-1 the program device 0 compiled), dispatched chunk by chunk in turn so that the devices run at once.

* MJX-JAX: each instance is computed by the same per-instance program whatever the layout. On host (CPU) devices
  the results of 1 and 4 devices are bitwise equal (``tests/test_multidevice.py``); a program sharded over a
  mesh (:func:`hyqjax.sim.runner.batch_mesh`, ``Rollout.run(mesh=...)``, still available) was not: XLA compiles
  the partitioned program differently and the same step-down rows differed by up to 3e-6 m in ``qpos`` after
  0.4 s, enough to change outcome columns.
* MuJoCo Warp keeps one contact buffer per batch (``naconmax`` over all worlds, not a per-instance field), which
  a sharded program would split along the wrong axis; each slice gets its own data and buffer, sized for the
  slice. Outcomes agree with a one-device run within the simulator's agreement (contact ordering in a buffer of
  another size), counted by ``benchmarks/bench_multi_gpu.py``.

The selection is a process-wide default (:func:`select`, set by the command line's ``--devices``) that
:func:`resolve` reads when a caller names no devices. Nothing here imports JAX at import time.
"""
from __future__ import annotations

import re

#: What ``--devices`` accepts, for messages.
DEVICES_HELP = "'all', a count N (the first N local devices) or a comma-separated list of device ids such as 0,2"

_SELECTED: object = None  # None: every local device; int: the first N; tuple: those ids


def parse(text) -> None | int | tuple[int, ...]:
    """``--devices`` as a selection: None (``all``), a count ``N >= 1`` or a tuple of distinct device ids.
    A malformed value is a ``ValueError`` naming the option and what it accepts (no JAX needed)."""
    if text is None:
        return None
    if isinstance(text, int) and not isinstance(text, bool):
        if text < 1:
            raise ValueError(f"--devices must be {DEVICES_HELP}; got {text}")
        return int(text)
    if isinstance(text, (tuple, list)):
        text = ",".join(str(x) for x in text)
    s = str(text).strip().lower()
    if s in ("all", ""):
        return None
    if re.fullmatch(r"[0-9]+", s):
        n = int(s)
        if n < 1:
            raise ValueError(f"--devices must be {DEVICES_HELP}; got {text!r}")
        return n
    if re.fullmatch(r"[0-9]+(,[0-9]+)+,?", s) or re.fullmatch(r"[0-9]+,", s):
        ids = tuple(int(x) for x in s.split(",") if x)
        if len(set(ids)) != len(ids):
            raise ValueError(f"--devices lists a device twice: {text!r}")
        return ids
    raise ValueError(f"--devices must be {DEVICES_HELP}; got {text!r}")


def resolve(selection=None) -> list:
    """The local JAX devices of ``selection`` (:func:`parse`'s forms, or a list of devices; None: the process's
    default, :func:`select`, itself every local device unless set). A count above the devices there, or an id that
    is not a local device, is a ``ValueError`` naming ``--devices`` and the devices there are."""
    import jax

    if selection is None:
        selection = _SELECTED
    if isinstance(selection, (list, tuple)) and selection and not isinstance(selection[0], (int, str)):
        return list(selection)  # devices already
    sel = parse(selection)
    local = jax.local_devices()
    have = f"this host has {len(local)} {local[0].platform} device(s), ids {[d.id for d in local]}"
    if sel is None:
        return list(local)
    if isinstance(sel, int):
        if sel > len(local):
            raise ValueError(f"--devices {sel}: {have}")
        return list(local[:sel])
    by_id = {d.id: d for d in local}
    missing = [i for i in sel if i not in by_id]
    if missing:
        raise ValueError(f"--devices {','.join(map(str, sel))}: no device {missing[0]}; {have}")
    return [by_id[i] for i in sel]


def select(selection) -> list:
    """Make ``selection`` the process's default (what :func:`resolve` gives without an argument) and return its
    devices (checked now)."""
    global _SELECTED
    devs = resolve(parse(selection) if not _is_devices(selection) else selection)
    _SELECTED = parse(selection) if not _is_devices(selection) else list(selection)
    return devs


def selected():
    """The process's default selection (None: every local device)."""
    return _SELECTED


def _is_devices(x) -> bool:
    return isinstance(x, (list, tuple)) and bool(x) and not isinstance(x[0], (int, str))


def layout(impl: str, n_devices: int) -> str:
    """How a batch of the resolved simulator ``impl`` runs over ``n_devices``: ``one`` (a single device, and C
    MuJoCo, which runs on the host's cores) or ``split`` (see the module docstring)."""
    if n_devices <= 1 or impl == "c":
        return "one"
    return "split"


def describe(devices) -> str:
    """``4 x gpu (ids 0,1,2,3)``."""
    devs = list(devices)
    return f"{len(devs)} x {devs[0].platform} (ids {','.join(str(d.id) for d in devs)})"


__all__ = ["DEVICES_HELP", "describe", "layout", "parse", "resolve", "select", "selected"]
