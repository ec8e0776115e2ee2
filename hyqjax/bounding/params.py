"""Parameters of the bound: gait timing and geometry, feedback gains, module switches, the operator
command and the stored limit cycle, as frozen dataclass PyTrees (every number a leaf, so ``vmap``
gives each instance its own value and ``jacfwd`` reaches every gain), and the parameter sets built on the stored
limit cycle (:mod:`hyqjax.bounding.defaults`).

The parameter classes (:class:`GaitParams`, :class:`BoundingGains`, :class:`Switches`, :class:`BoundingCommand`,
:class:`BoundingParams`), with their ranges declared once and checked at construction, are defined in
:mod:`hyqjax.bounding.param_types`; the sagittal apex state :class:`Apex` ``(z, pitch, vx, vz, pitch_rate)`` in
:mod:`hyqjax.bounding.apex`. This module re-exports them (``from hyqjax.bounding.params import BoundingParams``)
and builds the parameter sets: the paper's bound (:func:`paper_params`, preset ``bound_paper``), the default bound
(:func:`default_params`, the preset :data:`DEFAULT_PRESET`) and a set from named amplitudes and gains
(:func:`params_of_values`).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.bounding.apex import APEX_NAMES, N_APEX, Apex  # noqa: F401  (re-exported)
from hyqjax.bounding.param_types import (  # noqa: F401  (re-exported)
    FRONT,
    HIND,
    LATERAL_SPEED_LIMIT,
    LEG_PAIR,
    LEG_SIDE,
    NOMINAL_FOOT_XY,
    PROFILES,
    BoundingCommand,
    BoundingGains,
    BoundingParams,
    GaitParams,
    Switches,
    _f32,
    check_field,
    check_range,
)
from hyqjax.core import robot
from hyqjax.core.params import ParameterError, param_ranges


def pair_amplitudes(a_front, a_hind) -> jax.Array:
    """(4, 3) per-leg amplitudes from pair values ``[a_x, a_y, a_z]`` (``a_y`` mirrored left/right)."""
    af, ah = jnp.asarray(a_front, jnp.float32), jnp.asarray(a_hind, jnp.float32)
    mirror = jnp.array([1.0, -1.0, 1.0], jnp.float32)
    return jnp.stack([af, af * mirror, ah, ah * mirror])


#: Default gains that are not part of the stored cycle data (hand-tuned; see docs/bounding.md).
DEFAULT_GAINS = dict(k_foot=0.05, k_lateral=150.0, k_yaw_rate=100.0, k_yaw=200.0, k_roll=600.0, k_roll_rate=60.0,
                     k_stance_z=8000.0, k_stance_zdot=300.0, k_stance_pitch=3000.0, k_stance_pitch_rate=300.0)


#: The names of the four cycle amplitudes of a stored parameter set (Eq. B1, N per leg), in ``cycle_amplitudes``
#: order.
AMPLITUDE_NAMES = ("a_fz", "a_hz", "a_fx", "a_hx")
#: The preset :func:`default_params` runs (``hyqjax.presets``).
DEFAULT_PRESET = "bound_robust"


def default_params(speed=0.0, yaw_rate=0.0, lateral_speed=0.0, ramp_time=1.0, kinematic_adjustment=True,
                   centrifugal=True, apex_feedback=True, stance_feedback=True, gait: GaitParams | None = None,
                   cycle_amplitudes=None, cycle_apex=None, reference=None, **gain_overrides) -> BoundingParams:
    """The default bound: the preset :data:`DEFAULT_PRESET` (``bound_robust``: CMA-ES's impulse amplitudes and
    gains optimised over commands, friction and payload, then refined at the fast corners of the command box with
    low friction and a payload; ``hyqjax presets bound_robust``) on the stored limit
    cycle, and the command. Arguments as for :func:`paper_params`, whose gains are the paper's
    (``hyqjax.presets.load("bound_paper")``); ``cycle_amplitudes`` and gain keywords override the preset's."""
    from hyqjax.presets import registry

    values = registry.get(DEFAULT_PRESET).values
    return params_of_values(dict(values.get("amplitudes", {}), **values.get("gains", {})), speed=speed,
                            yaw_rate=yaw_rate, lateral_speed=lateral_speed, ramp_time=ramp_time,
                            kinematic_adjustment=kinematic_adjustment, centrifugal=centrifugal,
                            apex_feedback=apex_feedback, stance_feedback=stance_feedback, gait=gait,
                            cycle_amplitudes=cycle_amplitudes, cycle_apex=cycle_apex, reference=reference,
                            **gain_overrides)


def params_of_values(values: dict, cycle_amplitudes=None, **kw) -> BoundingParams:
    """:func:`paper_params` (``kw``: command, switches, gain overrides) with the amplitudes (``a_fz, a_hz, a_fx,
    a_hx``) and gains (:class:`BoundingGains` fields) of ``values`` in place of the paper's; ``cycle_amplitudes``
    and gain keywords in ``kw`` win over ``values``. Names outside those are refused; ranges are the parameter
    classes' (a :class:`ParameterError` naming the field)."""
    from hyqjax.bounding import defaults as bdef

    known = set(AMPLITUDE_NAMES) | set(param_ranges(BoundingGains))
    for k, v in values.items():
        if k not in known:
            raise ParameterError("BoundingParams", k, v, f"one of {sorted(known)}", problem="is unknown")
        if not np.isfinite(float(v)):
            raise ParameterError("BoundingParams", k, v, "finite")
    amp = np.array(bdef.stored().amplitudes, np.float64)
    for i, k in enumerate(AMPLITUDE_NAMES):
        if k in values:
            amp[i] = float(values[k])
    if cycle_amplitudes is not None:
        amp = cycle_amplitudes
    gains = {k: float(v) for k, v in values.items() if k not in AMPLITUDE_NAMES}
    gains.update(kw)
    return paper_params(cycle_amplitudes=amp, **gains)


def paper_params(speed=0.0, yaw_rate=0.0, lateral_speed=0.0, ramp_time=1.0, kinematic_adjustment=True,
                 centrifugal=True, apex_feedback=True, stance_feedback=True, gait: GaitParams | None = None,
                 cycle_amplitudes=None, cycle_apex=None, reference=None, **gain_overrides) -> BoundingParams:
    """The paper's bound (preset ``bound_paper``): the stored limit cycle (:mod:`hyqjax.bounding.defaults`), the
    hand-set gains (:data:`DEFAULT_GAINS` and the cycle's apex gains), the command.

    ``cycle_amplitudes`` (4,) = ``(a_fz, a_hz, a_fx, a_hx)``, ``cycle_apex`` (5,) (:class:`Apex` order) and
    ``reference`` (N, 4) override the stored cycle. Other keyword arguments override :class:`BoundingGains` fields.
    """
    from hyqjax.bounding import defaults as bdef

    stored = bdef.stored()
    gait = gait or GaitParams.make()
    amp = np.asarray(stored.amplitudes if cycle_amplitudes is None else cycle_amplitudes, np.float64)
    apex = np.asarray(stored.apex if cycle_apex is None else cycle_apex, np.float64)
    ref = np.asarray(stored.reference if reference is None else reference, np.float64)
    if amp.shape != (4,):
        raise ValueError(f"cycle_amplitudes must have shape (4,), got {amp.shape}")
    if apex.shape != (N_APEX,):
        raise ValueError(f"cycle_apex must have shape ({N_APEX},), got {apex.shape}")
    if ref.ndim != 2 or ref.shape[1] != 4 or ref.shape[0] < 2 or np.any(~np.isfinite(ref)):
        raise ValueError(f"reference must be a finite (N >= 2, 4) table, got shape {ref.shape}")
    check_range("paper_params", "cycle_amplitudes[:2] (vertical)", amp[:2], 0.0, 1500.0)
    check_range("paper_params", "cycle_amplitudes[2:] (horizontal)", amp[2:], -500.0, 500.0)
    s0 = Apex.of(apex)
    check_range("paper_params", "cycle_apex z", s0.z, 0.35, 0.8)
    gkw = dict(stored.apex_gains, **DEFAULT_GAINS)
    gkw.update(gain_overrides)
    a = pair_amplitudes([amp[2], 0.0, amp[0]], [amp[3], 0.0, amp[1]])
    return BoundingParams(
        gait=gait, amplitudes=a, apex_ref=Apex.of(_f32(apex)), reference=_f32(ref),
        gains=BoundingGains.make(**gkw),
        switches=Switches.make(kinematic_adjustment, centrifugal, apex_feedback, stance_feedback),
        command=BoundingCommand.make(speed, yaw_rate, lateral_speed, ramp_time),
        init_estimate=_f32([s0.z, s0.vx, 0.0, s0.vz]), mass=_f32(robot.TOTAL_MASS))
