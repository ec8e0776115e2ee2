"""The axes of a sweep: every sweepable input with its allowed range (or options), unit and default.

:data:`AXES` names them (step height, rough terrain amplitude, friction, payload, initial pose, foot sequence,
joint PD gains, lateral push, sensor noise, control latency, reflex on/off and one axis per
:class:`hyqjax.reflex.params.ReflexParams` field, whose range, unit and default come from that class's
declaration); :func:`axis_value` validates one value of an axis. :mod:`hyqjax.studies.sweep.spec` builds a
:class:`~hyqjax.studies.sweep.spec.SweepSpec` from them.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from hyqjax.crawl import params as crawl  # CrawlParams, FOOT_SEQUENCES (not the controller)
from hyqjax.reflex import step as hreflex
from hyqjax.sim import model as hmodel

__all__ = ["AXES", "Axis", "SENSOR_AXES", "SpecError", "axis_value", "get_axis"]


class SpecError(ValueError):
    """A sweep specification is invalid (the message names the field and the allowed range)."""


@dataclasses.dataclass(frozen=True)
class Axis:
    """One sweepable input: allowed range ``[lo, hi]`` (or ``options``), unit, default."""

    name: str
    lo: float
    hi: float
    unit: str
    default: Any
    doc: str
    kind: str = "float"  # "float", "bool", "choice", "int"
    options: tuple = ()
    lo_open: bool = False
    hi_open: bool = False

    @property
    def range_text(self) -> str:
        return f"{'(' if self.lo_open else '['}{self.lo}, {self.hi}{')' if self.hi_open else ']'} {self.unit}".strip()


def _declared_axis(name: str, cls, field: str, doc: str) -> Axis:
    """An axis whose range, unit and default are those ``cls`` declares for ``field``."""
    from hyqjax.core.params import param_ranges

    r = param_ranges(cls)[field]
    return Axis(name, float(r.lo), float(r.hi), r.unit, float(np.asarray(r.default)), doc, lo_open=r.lo_open,
                hi_open=r.hi_open)


def _reflex_axes():
    """One axis per :class:`ReflexParams` field, with the range, unit and default declared there."""
    from hyqjax.core.params import param_ranges

    return [Axis(f"reflex_{n}", float(r.lo), float(r.hi), r.unit, float(np.asarray(r.default)),
                 f"ReflexParams.{n} (Table I default)", lo_open=r.lo_open, hi_open=r.hi_open)
            for n, r in param_ranges(hreflex.ReflexParams).items()]


_AXES_LIST = [
    Axis("height", 0.0, hmodel.MAX_PLATFORM_HEIGHT, "m", 0.21, "platform (step) height"),
    Axis("roughness", 0.0, 2 * hmodel.BLOCK_HALF_Z, "m", 0.0,
         "rough-terrain amplitude: block heights ~ U(0, roughness) per block (needs blocks > 0)"),
    Axis("friction", 0.05, 5.0, "", 0.8, "sliding friction of the terrain"),
    Axis("payload_mass", 0.0, 100.0, "kg", 0.0, "payload on the trunk"),
    Axis("payload_com_x", -0.5, 0.5, "m", 0.0, "payload CoM, trunk frame x"),
    Axis("payload_com_y", -0.5, 0.5, "m", 0.0, "payload CoM, trunk frame y"),
    Axis("payload_com_z", -0.5, 0.5, "m", 0.0, "payload CoM, trunk frame z"),
    Axis("start_distance", 0.0, 1.5, "m", 0.02, "front feet distance before the platform edge at the start"),
    Axis("lateral_offset", -0.5, 0.5, "m", 0.0, "initial lateral trunk offset"),
    Axis("yaw", -0.5, 0.5, "rad", 0.0, "initial heading"),
    _declared_axis("speed", crawl.CrawlParams, "forward_velocity",
                   "desired forward velocity (CrawlParams.forward_velocity)"),
    Axis("foot_sequence", 0, 0, "", "rh-rf-lh-lf", "crawl leg order (CrawlParams.foot_sequence)", "choice",
         tuple(sorted(crawl.FOOT_SEQUENCES))),
    Axis("kp_haa", 1.0, 5000.0, "N m/rad", 300.0, "joint PD stiffness, HAA"),
    Axis("kp_hfe", 1.0, 5000.0, "N m/rad", 300.0, "joint PD stiffness, HFE"),
    Axis("kp_kfe", 1.0, 5000.0, "N m/rad", 300.0, "joint PD stiffness, KFE"),
    Axis("kd_haa", 0.01, 200.0, "N m s/rad", 8.0, "joint PD damping, HAA"),
    Axis("kd_hfe", 0.01, 200.0, "N m s/rad", 8.0, "joint PD damping, HFE"),
    Axis("kd_kfe", 0.01, 200.0, "N m s/rad", 6.0, "joint PD damping, KFE"),
    Axis("push_force_x", -5000.0, 5000.0, "N", 0.0, "push on the trunk, world x"),
    Axis("push_force_y", -5000.0, 5000.0, "N", 0.0, "lateral push on the trunk, world y"),
    Axis("push_t_start", 0.0, 600.0, "s", 0.0, "push start time"),
    Axis("push_duration", 0.0, 10.0, "s", 0.0, "push duration"),
    Axis("noise_joint_pos", 0.0, 0.1, "rad", 0.0, "std of joint encoder noise"),
    Axis("noise_joint_vel", 0.0, 10.0, "rad/s", 0.0, "std of joint velocity noise"),
    Axis("noise_imu", 0.0, 0.1, "rad", 0.0, "std of IMU orientation noise (small random rotation)"),
    Axis("noise_gyro", 0.0, 2.0, "rad/s", 0.0, "std of IMU angular-rate noise"),
    Axis("noise_foot_force", 0.0, 200.0, "N", 0.0, "std of estimated foot force noise"),
    Axis("latency", 0.0, 0.05, "s", 0.0, "control latency (rounded to whole control ticks)"),
    Axis("reflex", 0, 1, "", True, "height reflex on/off", "bool"),
    *_reflex_axes(),
]
#: Every sweepable axis by name.
AXES: dict[str, Axis] = {a.name: a for a in _AXES_LIST}
SENSOR_AXES = ("noise_joint_pos", "noise_joint_vel", "noise_imu", "noise_gyro", "noise_foot_force", "latency")


def axis_value(axis: Axis, v, where: str):
    """Validate and normalise one value of ``axis`` (``where`` names it in errors)."""
    if axis.kind == "bool":
        if isinstance(v, str) and v.lower() in ("on", "off", "true", "false"):
            return v.lower() in ("on", "true")
        if isinstance(v, (bool, np.bool_)) or v in (0, 1):
            return bool(v)
        raise SpecError(f"{where}: {axis.name} must be true/false (or 'on'/'off'), got {v!r}")
    if axis.kind == "choice":
        if v not in axis.options:
            raise SpecError(f"{where}: {axis.name} must be one of {list(axis.options)}, got {v!r}")
        return str(v)
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise SpecError(f"{where}: {axis.name} must be a number in {axis.range_text}, got {v!r}")
    f = float(v)
    ok = math.isfinite(f) and (axis.lo < f if axis.lo_open else axis.lo <= f) and (
        f < axis.hi if axis.hi_open else f <= axis.hi)
    if not ok:
        raise SpecError(f"{where}: {axis.name}={v!r} out of range: must be in {axis.range_text}")
    return f


def get_axis(name: str, where: str) -> Axis:
    if name not in AXES:
        raise SpecError(f"{where}: unknown axis {name!r}; allowed axes: {sorted(AXES)}")
    return AXES[name]
