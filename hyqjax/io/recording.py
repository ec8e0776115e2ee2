"""Recorded trajectories on disk (``traces.npz``): the file format, and loading and choosing instances.

A batched rollout records a decimated trace of every instance it is asked to (``hyqjax stepdown
--record-instances ... --record-every TICKS``); the command writes it as ``DIR/traces.npz`` next to
``DIR/results.json``. :mod:`hyqjax.io.render` turns one recorded instance into a video,
``hyqjax view`` plays it in MuJoCo's viewer, and the figures are drawn from it.

File format
-----------
One ``numpy.savez_compressed`` archive (by default of a few instances per configuration,
``--record-instances few``: :func:`few_instances`). ``R`` is the number of recorded instances, ``N`` the
number of samples per instance (one every ``record_every`` control ticks, the first after
``record_every`` ticks). Frames: ``W`` is the world (x forward, off the platform edge at
``x = 0``; z up, the lower ground at ``z = 0``), ``B`` the trunk frame (x forward, y left, z up).
Legs are ordered ``(LF, RF, LH, RH)``; joint vectors of 12 are leg-major ``(HAA, HFE, KFE)``.

=====================  ==============  =======  ==========================================================
key                    shape           unit     meaning
=====================  ==============  =======  ==========================================================
``time``               (R, N)          s        simulated time of the sample
``qpos``               (R, N, 19)      m, rad   MuJoCo ``qpos``: trunk position in ``W`` (3), trunk
                                                quaternion ``W_q_B`` (w, x, y, z), 12 joint angles
``base_pos``           (R, N, 3)       m        trunk position in ``W``
``rpy``                (R, N, 3)       rad      trunk roll, pitch, yaw
``q``, ``qd``          (R, N, 12)      rad,     measured joint positions and velocities
                                       rad/s
``q_cmd``              (R, N, 12)      rad      commanded joint positions
``x_plan_b``           (R, N, 4, 3)    m        planned foot positions in ``B``
``x_cmd_b``            (R, N, 4, 3)    m        commanded foot positions in ``B`` (after the reflex)
``feet_world``         (R, N, 4, 3)    m        foot positions in ``W``
``foot_force``         (R, N, 4, 3)    N        ground reaction force on each foot in ``B``, estimated
                                                from joint torques (z > 0 pushes the foot up)
``reflex_active``      (R, N)          bool     the height reflex is extending the swing leg
``swing_down``         (R, N)          bool     the swing leg is in the downward part of its swing
``swing_leg``          (R, N)          int      index of the swinging leg (0..3)
``phase``              (R, N)          int      crawl state-machine phase
``damping``            (R, N, 12)      N m s    joint damping of the impedance controller
                                       /rad
``mobility``           (R, N, 4)       -        velocity transformation ratio per leg (Eq. 12)
``input_height``       (R,)            m        platform height of the instance
``input_reflex``       (R,)            bool     height reflex on
``input_instance``     (R,)            int      randomised instance number within its (height, reflex) group
``input_friction``     (R,)            -        ground friction coefficient
``input_payload_mass``  (R,)           kg       payload mass
``input_payload_com``  (R, 3)          m        payload centre of mass in ``B``
``input_start_distance`` (R,)          m        front feet distance from the platform edge at the start
``input_lateral_offset`` (R,)          m        initial lateral offset
``input_yaw``          (R,)            rad      initial heading
``instance_index``     (R,)            int      row of the instance in ``results.json["instances"]``
``record_every``       ()              ticks    decimation of the trace
``control_dt``         ()              s        control period (one tick)
=====================  ==============  =======  ==========================================================

Only ``qpos`` and ``time`` (or ``t``) are needed to render or view a trace; everything else is
optional and used when present (``foot_force`` for the force arrows, ``reflex_active`` for the
reflex strip, ``input_height`` for the platform). Files written before ``instance_index``,
``record_every`` and ``control_dt`` existed hold every instance in ``results.json`` order; the
loader fills these in.
"""
from __future__ import annotations

import dataclasses
import json
import os
from typing import Any

import numpy as np

TRACES_FILE = "traces.npz"
RESULTS_FILE = "results.json"
#: Keys of a trace archive that hold one value per instance rather than one per sample.
META_KEYS = ("instance_index", "record_every", "control_dt")
#: The per-instance input columns that ``--where`` can select on (``input_`` prefix dropped).
SELECTABLE = ("height", "reflex", "instance", "friction", "payload_mass", "start_distance", "lateral_offset", "yaw")


@dataclasses.dataclass(frozen=True)
class Recording:
    """A loaded trace archive.

    Attributes:
      path: the ``traces.npz`` it came from.
      arrays: every per-instance array of the archive (leading axis ``R``), ``time`` always present.
      instance_index: (R,) row of each recorded instance in ``results.json["instances"]``.
      record_every: decimation in control ticks (0 when unknown).
      control_dt: control period (s), or ``nan`` when unknown.
      results: the experiment's ``results.json`` when it lies next to the archive, else ``None``.
    """

    path: str
    arrays: dict[str, np.ndarray]
    instance_index: np.ndarray
    record_every: int
    control_dt: float
    results: dict | None

    @property
    def n_recorded(self) -> int:
        return int(self.instance_index.shape[0])

    @property
    def sample_dt(self) -> float:
        """Seconds between two samples."""
        t = self.arrays["time"]
        if t.shape[-1] >= 2:
            return float(np.median(np.diff(t[0])))
        if self.record_every and np.isfinite(self.control_dt):
            return self.record_every * self.control_dt
        return float("nan")

    def row_of(self, instance: int) -> int | None:
        """The archive row holding ``results.json`` instance ``instance``, or ``None`` if it was not recorded."""
        hit = np.nonzero(self.instance_index == instance)[0]
        return int(hit[0]) if hit.size else None

    def instance(self, row: int) -> dict[str, np.ndarray]:
        """All arrays of one recorded row (no leading axis)."""
        return {k: v[row] for k, v in self.arrays.items()}


def traces_path(path: str) -> str:
    """``path`` itself if it is a file, else ``path/traces.npz``."""
    return path if os.path.isfile(path) else os.path.join(path, TRACES_FILE)


def load_results(directory: str) -> dict | None:
    p = os.path.join(directory, RESULTS_FILE)
    if not os.path.isfile(p):
        return None
    with open(p) as f:
        return json.load(f)


def load(path: str) -> Recording:
    """Load ``path`` (an experiment directory or a ``.npz`` archive); raises ``FileNotFoundError`` /
    ``ValueError`` with the reason when it is missing or not a trace archive."""
    tp = traces_path(path)
    if not os.path.isfile(tp):
        raise FileNotFoundError(f"no trace archive at {tp} (run e.g. `hyqjax stepdown --out DIR` without "
                                f"--no-figures to record one)")
    with np.load(tp, allow_pickle=False) as z:
        raw = {k: z[k] for k in z.files}
    if "time" not in raw and "t" in raw:
        raw["time"] = raw.pop("t")
    if "time" not in raw:
        raise ValueError(f"{tp} has no 'time' array: not a hyqjax trace archive (keys: {sorted(raw)})")
    r = raw["time"].shape[0]
    index = np.asarray(raw.pop("instance_index", np.arange(r)), np.int64)
    record_every = int(raw.pop("record_every", 0))
    control_dt = float(raw.pop("control_dt", np.nan))
    arrays = {k: v for k, v in raw.items() if v.ndim >= 1 and v.shape[0] == r}
    return Recording(path=tp, arrays=arrays, instance_index=index, record_every=record_every, control_dt=control_dt,
                     results=load_results(os.path.dirname(os.path.abspath(tp))))


def save(path: str, trace: dict[str, np.ndarray], inputs: dict[str, np.ndarray], instances: np.ndarray,
         record_every: int, control_dt: float) -> None:
    """Write the rows ``instances`` of ``trace`` (and of the per-instance ``inputs`` table) in the format above
    (to a temporary file renamed into place: a reader never sees half an archive)."""
    idx = np.asarray(instances, np.int64)
    arrays = {k: np.asarray(v)[idx] for k, v in trace.items()}
    arrays.update({f"input_{k}": np.asarray(v)[idx] for k, v in inputs.items()})
    tmp = f"{path}.{os.getpid()}.tmp.npz"
    try:
        np.savez_compressed(tmp, **arrays, instance_index=idx, record_every=np.asarray(record_every),
                            control_dt=np.asarray(control_dt))
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


class BackgroundSave:
    """:func:`save` in a background thread (zlib releases the GIL, so the archive is compressed while the command
    summarises and draws); :meth:`join` waits for it, raises its error and returns the seconds it took."""

    def __init__(self, *args, **kwargs):
        import threading
        import time

        self.seconds = 0.0
        self._error: BaseException | None = None

        def work():
            t0 = time.perf_counter()
            try:
                save(*args, **kwargs)
            except BaseException as e:  # noqa: BLE001  (raised again by join)
                self._error = e
            self.seconds = time.perf_counter() - t0

        self._thread = threading.Thread(target=work, name="hyqjax-traces")
        self._thread.start()

    def join(self) -> float:
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self.seconds


#: ``--record-instances``' default: a few instances of each configuration (:func:`few_instances`).
FEW = "few"
#: Instances of each configuration that ``few`` records: the first ones, and as many failed ones.
FEW_PER_GROUP = 3


def few_instances(groups: np.ndarray, failed: np.ndarray, per_group: int = FEW_PER_GROUP) -> np.ndarray:
    """The rows ``--record-instances few`` records: the first ``per_group`` instances of each configuration
    (``groups``: one label per instance) and its first ``per_group`` failed ones (``failed``: one bool per
    instance), so ``hyqjax render DIR --worst`` has a failure to show when there is one."""
    groups, failed = np.asarray(groups), np.asarray(failed, bool)
    keep: list[int] = []
    for g in dict.fromkeys(groups.tolist()):
        rows = np.nonzero(groups == g)[0]
        keep += rows[:per_group].tolist() + rows[failed[rows]][:per_group].tolist()
    return np.unique(np.asarray(keep, np.int64))


def parse_instances(spec: str, n: int, option: str = "--record-instances") -> np.ndarray | None:
    """Instance indices from ``"all"``, ``"none"`` or a comma list of indices and ranges (``"0,3,5-7"``); None
    for ``"few"`` (chosen after the run, :func:`few_instances`).

    Raises ``ValueError`` naming ``option`` and the allowed range ``[0, n-1]`` on a bad entry.
    """
    s = spec.strip().lower()
    if s == FEW:
        return None
    if s == "all":
        return np.arange(n)
    if s == "none":
        return np.zeros(0, np.int64)
    out: list[int] = []
    for part in s.split(","):
        part = part.strip()
        try:
            lo, hi = (part.split("-", 1) + [None])[:2] if "-" in part[1:] else (part, None)
            lo_i = int(lo)
            hi_i = int(hi) if hi is not None else lo_i
        except ValueError:
            raise ValueError(f"{option}: cannot read {part!r}; use 'few', 'all', 'none' or indices like 0,3,5-7"
                             ) from None
        if not (0 <= lo_i <= hi_i < n):
            raise ValueError(f"{option}: {part!r} is outside the instances [0, {n - 1}]")
        out.extend(range(lo_i, hi_i + 1))
    return np.unique(np.asarray(out, np.int64))


def instance_failed(row: dict[str, Any]) -> bool:
    """A ``results.json`` instance row is a failure (step-down ``success`` false, bounding ``result`` not ok)."""
    if "success" in row:
        return not bool(row["success"])
    if "result" in row:
        return row["result"] != "ok"
    return False


def result_rows(results: dict | None) -> list[dict]:
    """Per-instance rows of a ``results.json``, in instance order (step-down ``instances`` or bounding ``groups``)."""
    if not results:
        return []
    if isinstance(results.get("instances"), list):
        return results["instances"]
    rows: list[dict] = []
    for g in (results.get("groups") or {}).values():
        rows.extend(g.get("instances", []))
    return rows


def parse_where(items: list[str]) -> dict[str, float]:
    """``["height=0.24", "reflex=on"]`` -> ``{"height": 0.24, "reflex": 1.0}``; raises ``ValueError`` on bad input."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        key = key.strip().replace("-", "_")
        if not sep or key not in SELECTABLE:
            raise ValueError(f"--where: expected KEY=VALUE with KEY one of {', '.join(SELECTABLE)}, got {item!r}")
        v = value.strip().lower()
        if v in ("on", "true", "yes"):
            out[key] = 1.0
        elif v in ("off", "false", "no"):
            out[key] = 0.0
        else:
            try:
                out[key] = float(v)
            except ValueError:
                raise ValueError(f"--where: {key} needs a number (or on/off), got {value!r}") from None
    return out


def choose_row(rec: Recording, instance: int | None = None, worst: bool = False,
               where: dict[str, float] | None = None) -> int:
    """The archive row to show: ``results.json`` instance ``instance``, the first failed recorded instance
    (``worst``), or the first recorded instance whose inputs match ``where``; row 0 when nothing is asked.

    Raises ``ValueError`` with the option name and the allowed values when the choice is impossible.
    """
    if instance is not None:
        allowed = _ranges(rec.instance_index)
        if instance < 0:
            raise ValueError(f"--instance must be >= 0; recorded instances: {allowed}")
        row = rec.row_of(instance)
        if row is None:
            raise ValueError(f"--instance {instance} was not recorded in {rec.path}; recorded instances: {allowed}")
        return row
    if worst:
        rows = result_rows(rec.results)
        if not rows:
            raise ValueError(f"--worst needs {RESULTS_FILE} next to {rec.path} (with per-instance results)")
        failed = [i for i, r in enumerate(rows) if instance_failed(r)]
        if not failed:
            raise ValueError(f"--worst: no instance failed (all {len(rows)} succeeded); pick one with --instance")
        for i in failed:
            row = rec.row_of(i)
            if row is not None:
                return row
        raise ValueError(f"--worst: the failed instances {_ranges(np.asarray(failed))} were not recorded; "
                         f"recorded instances: {_ranges(rec.instance_index)}")
    if where:
        mask = np.ones(rec.n_recorded, bool)
        for key, value in where.items():
            col = rec.arrays.get(f"input_{key}")
            if col is None:
                raise ValueError(f"--where {key}=...: the archive has no input_{key}")
            mask &= np.isclose(np.asarray(col, np.float64), value, atol=1e-6)
        hit = np.nonzero(mask)[0]
        if not hit.size:
            raise ValueError(f"--where {where}: no recorded instance matches; recorded inputs: {describe_inputs(rec)}")
        return int(hit[0])
    return 0


def describe_inputs(rec: Recording) -> str:
    """Distinct values of the heights / reflex settings recorded, for error messages."""
    parts = []
    for key in ("height", "reflex", "instance"):
        col = rec.arrays.get(f"input_{key}")
        if col is not None:
            parts.append(f"{key} in {sorted(set(np.asarray(col).tolist()))}")
    return "; ".join(parts) or "none"


def label(rec: Recording, row: int) -> str:
    """A one-line description of a recorded instance, e.g. ``instance 7: h = 0.24 m, reflex on, failed (tilt)``."""
    a = rec.arrays
    i = int(rec.instance_index[row])
    parts = [f"instance {i}"]
    if "input_height" in a:
        parts.append(f"h = {float(a['input_height'][row]):.2f} m")
    if "input_reflex" in a:
        parts.append(f"reflex {'on' if bool(a['input_reflex'][row]) else 'off'}")
    rows = result_rows(rec.results)
    if i < len(rows):
        r = rows[i]
        if instance_failed(r):
            from hyqjax.studies.stepdown_outcome import failure_labels  # boolean reason columns

            why = ", ".join(failure_labels(r)) or r.get("failure_reason") or r.get("result") or ""
            parts.append(f"failed ({why})" if why else "failed")
        elif "success" in r or "result" in r:
            parts.append("succeeded")
    return ", ".join(parts[:1]) + (": " + ", ".join(parts[1:]) if len(parts) > 1 else "")


def _ranges(idx: np.ndarray) -> str:
    """``[0, 1, 2, 5]`` -> ``"0-2, 5"``."""
    idx = sorted(set(int(i) for i in np.asarray(idx).reshape(-1)))
    if not idx:
        return "none"
    out, start, prev = [], idx[0], idx[0]
    for i in idx[1:] + [None]:
        if i is not None and i == prev + 1:
            prev = i
            continue
        out.append(f"{start}" if start == prev else f"{start}-{prev}")
        if i is not None:
            start = prev = i
    return ", ".join(out)
