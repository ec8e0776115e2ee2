"""Contacts from distance: a backward-only virtual spring between each foot and the terrain before touchdown.

A rigid contact gives a pathwise gradient only once it is active: while a searching foot is still above the
ground, ``d(loss) / d(theta)`` sees nothing of the ground it is about to meet, and a parameter that would bring the
foot down earlier or later gets no signal until the contact switches (Suh et al. 2022: the bias of first-order
estimates at contact events). DiffMJX (Paulus et al. 2025) softens contacts in the *backward* pass only, "contacts
from distance"; this module writes that idea for HyQ's feet on MJX-JAX.

Per control tick, after ``mjx.step`` (whose ``Data`` still holds the kinematics of the state it started from), for
each foot ``i`` with sphere-to-terrain clearance ``c_i > 0`` (:func:`hyqjax.sim.contacts.foot_clearance`; 0 or
less: touching, the real contact acts), a virtual normal force

.. math:: f_i = k\\, s\\, \\mathrm{softplus}\\big((\\delta - c_i) / s\\big)\\, \\mathbf 1[c_i > 0], \\qquad
          F_i = f_i\\, \\hat n_i,\\quad \\hat n_i = \\nabla_p\\, c(p)\\big|_{p_i}

(``k`` stiffness, ``delta`` reach, ``s`` softness; ``n_i`` the outward normal of the nearest terrain surface, the
gradient of the signed distance at the foot centre) gives the velocity change of one step

.. math:: \\Delta v = \\Delta t\\, M(q)^{-1} \\sum_i J_i(q)^\\top F_i

(``J_i`` the translational Jacobian of the foot centre on its body, ``M`` the joint-space inertia), and the next
velocity becomes

.. math:: v_{t+1} \\leftarrow v_{t+1} + \\Delta v - \\mathrm{stop\\_gradient}(\\Delta v)

(written as a custom derivative rule, :func:`with_derivative_of`, so that the value is exactly ``v_{t+1}``):

its value is MJX's exactly (the forward pass, every outcome and every loss value are unchanged), its derivative
carries ``d(Delta v)``: the derivative of the state that a spring of stiffness ``k`` acting from ``delta`` above
the ground would add. The term enters the velocity after the position update of the same step, so it reaches the
positions one step later (semi-implicit Euler's order).

For gradients only (``impl="jax"``), never for forward runs; :class:`ContactsFromDistance` with ``stiffness`` 0
returns the data unchanged, in value and derivative.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.sim import contacts


@dataclasses.dataclass(frozen=True)
class ContactsFromDistance:
    """The virtual spring of the module docstring: ``stiffness`` ``k`` (N/m, 0: off), ``reach`` ``delta`` (m, the
    clearance at which it reaches ``k s log 2``) and ``softness`` ``s`` (m)."""

    stiffness: float = 0.0
    reach: float = 0.02
    softness: float = 0.005

    def __post_init__(self):
        if not 0.0 <= float(self.stiffness) <= 1e6:
            raise ValueError(f"stiffness must be in [0, 1e6] N/m, got {self.stiffness}")
        if not 0.0 <= float(self.reach) <= 0.2:
            raise ValueError(f"reach must be in [0, 0.2] m, got {self.reach}")
        if not 0.0 < float(self.softness) <= 0.1:
            raise ValueError(f"softness must be in (0, 0.1] m, got {self.softness}")

    @property
    def active(self) -> bool:
        return float(self.stiffness) > 0.0


def virtual_forces(cfd: ContactsFromDistance, ci: contacts.ContactIds, d) -> tuple[jax.Array, jax.Array]:
    """``(F (4, 3), c (4,))``: the virtual force on each foot (world frame, N) and its clearance (m)."""
    feet = d.geom_xpos[np.asarray(ci.foot_geoms)]
    c = contacts.foot_clearance(ci, d)
    normal = jax.grad(lambda f: jnp.sum(contacts.clearance_of_points(ci, f, d)))(feet)  # row i: foot i's
    normal = normal / jnp.maximum(jnp.linalg.norm(normal, axis=-1, keepdims=True), 1e-9)
    s = jnp.asarray(cfd.softness, c.dtype)
    f = cfd.stiffness * s * jax.nn.softplus((cfd.reach - c) / s) * (c > 0)
    return f[:, None] * normal, c


def velocity_change(cfd: ContactsFromDistance, mx, ci: contacts.ContactIds, foot_bodies, d, dt: float) -> jax.Array:
    """``Delta v = dt M^-1 sum_i J_i^T F_i`` (nv,) of the module docstring for the kinematics held in ``d``."""
    from mujoco.mjx._src import smooth, support

    forces, _ = virtual_forces(cfd, ci, d)
    feet = d.geom_xpos[np.asarray(ci.foot_geoms)]
    qfrc = jnp.zeros_like(d.qvel)
    for i, body in enumerate(foot_bodies):
        jacp, _ = support.jac(mx, d, feet[i], int(body))
        qfrc = qfrc + jacp @ forces[i]
    return dt * smooth.solve_m(mx, d, qfrc)


def foot_bodies(m, ci: contacts.ContactIds) -> tuple[int, ...]:
    """Body id of each foot geom (static, from the ``mujoco.MjModel``)."""
    return tuple(int(m.geom_bodyid[g]) for g in ci.foot_geoms)


def apply(cfd: ContactsFromDistance, mx, ci: contacts.ContactIds, bodies, d_next, dt: float):
    """``d_next`` (the result of ``mjx.step``) with the backward-only velocity term (module docstring): its value
    unchanged, its derivative that of the virtual springs. ``cfd`` off: ``d_next`` itself."""
    if not cfd.active:
        return d_next
    dv = velocity_change(cfd, mx, ci, bodies, d_next, dt)
    return d_next.replace(qvel=with_derivative_of(d_next.qvel, dv))


@jax.custom_jvp
def with_derivative_of(x, dv):
    """``x`` in value, ``x + dv`` in derivative: ``x + dv - stop_gradient(dv)`` with the value exactly ``x`` (a
    compiler may round the two copies of ``dv`` differently; here the value never involves ``dv``)."""
    del dv
    return x


@with_derivative_of.defjvp
def _with_derivative_of_jvp(primals, tangents):
    x, _ = primals
    x_dot, dv_dot = tangents
    return x, x_dot + dv_dot
