"""Derive ``hyq.xml`` (MJCF) from IIT's HyQ URDF.

This is the provenance record of :file:`hyq.xml`; hyqjax never runs it at import time.
Usage::

    python -m hyqjax.assets.derive_from_urdf --urdf PATH/TO/hyq.urdf --out hyqjax/assets/hyq.xml

MuJoCo compiles the URDF (mesh geometry stripped); at the zero configuration every
body frame of the clean MJCF is aligned with the trunk frame, so the world-frame
quantities MuJoCo computes (joint anchors and axes, link centres of mass, link
inertia tensors) are written directly as body positions, joint axes, ``inertial pos``
and ``fullinertia``. Collision geometry is primitive (see ``hyq.xml``'s header).
The URDF and SRDF are Apache-2.0 (iit-DLSLab/hyq-description); see NOTICE.md.
"""
from __future__ import annotations

import argparse
import re

import numpy as np

LEGS = ("lf", "rf", "lh", "rh")
LINKS = ("hipassembly", "upperleg", "lowerleg")
JOINTS = ("haa", "hfe", "kfe")


def _strip_meshes(urdf: str) -> str:
    urdf = re.sub(r"<visual>.*?</visual>", "", urdf, flags=re.S)
    urdf = re.sub(r"<collision[^>]*>(?:(?!</collision>).)*?<mesh(?:(?!</collision>).)*?</collision>",
                  "", urdf, flags=re.S)
    urdf = re.sub(r"<gazebo.*?</gazebo>", "", urdf, flags=re.S)
    return re.sub(r"<transmission.*?</transmission>", "", urdf, flags=re.S)


def _fmt(v) -> str:
    return " ".join(f"{x:.7g}" if abs(x) > 1e-12 else "0" for x in np.asarray(v, float).ravel())


HEADER = """<!--
  HyQ (IIT) for MuJoCo / MJX, derived by hyqjax/assets/derive_from_urdf.py from hyq.urdf and hyq.srdf of
  iit-DLSLab/hyq-description (Apache License 2.0; see NOTICE.md beside this file).
  Masses, centres of mass, inertias, joint anchors, axes and ranges are the URDF's, written in body frames
  that are aligned with the trunk frame at the zero configuration. Collision geometry is primitive:
  foot spheres (r = 0.02175 m, the URDF's), shin capsules (r = 0.02 m, the URDF's shin cylinder),
  one trunk capsule (hyqjax's choice, r = 0.1 m, covering the trunk between the hips), no self-collision.
  Contacts: robot geoms have contype 2 / conaffinity 1, terrain geoms contype 1 / conaffinity 2, so the robot
  touches only the terrain: feet carry the locomotion, shins and trunk make a shin strike or a fall visible.
-->
"""


def derive(urdf_path: str) -> str:
    """Return the HyQ MJCF text derived from the URDF at ``urdf_path``."""
    import mujoco

    urdf = _strip_meshes(open(urdf_path).read())
    urdf = urdf.replace('<robot name="hyq">', '<robot name="hyq"><mujoco><compiler fusestatic="false" '
                        'discardvisual="false" balanceinertia="true"/></mujoco>', 1)
    m = mujoco.MjModel.from_xml_string(urdf)
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)

    def body(name):
        return m.body(name).id

    def inertia_world(b):
        rot = d.ximat[b].reshape(3, 3)
        i = rot @ np.diag(m.body_inertia[b]) @ rot.T
        return [i[0, 0], i[1, 1], i[2, 2], i[0, 1], i[0, 2], i[1, 2]]

    tb = body("trunk")
    o = [HEADER, '<mujoco model="hyq">',
         '  <compiler angle="radian" autolimits="true"/>',
         '  <option timestep="0.002" iterations="4" ls_iterations="8">',
         '    <flag eulerdamp="disable"/>',
         '  </option>',
         '  <default>',
         '    <joint damping="0.1" armature="0.01"/>',
         '    <default class="haa"/>', '    <default class="hfe"/>', '    <default class="kfe"/>',
         '    <geom contype="2" conaffinity="1" condim="3" friction="0.8 0.02 0.01" solref="0.005 1"/>',
         '    <motor ctrllimited="true" ctrlrange="-150 150"/>',
         '  </default>',
         '  <worldbody>',
         '    <body name="trunk" pos="0 0 0.5957">',
         '      <freejoint name="root"/>',
         f'      <inertial pos="{_fmt(d.xipos[tb])}" mass="{m.body_mass[tb]:.7g}" '
         f'fullinertia="{_fmt(inertia_world(tb))}"/>',
         '      <geom name="trunk" type="capsule" fromto="-0.35 0 0 0.35 0 0" size="0.1" rgba="0.25 0.3 0.35 1"/>',
         '      <site name="imu" pos="0 0 0" size="0.01"/>']
    for leg in LEGS:
        parent = d.xpos[tb]
        depth = 0
        for link, jn in zip(LINKS, JOINTS):
            b = body(f"{leg}_{link}")
            j = m.joint(f"{leg}_{jn}_joint").id
            anchor, axis = d.xanchor[j], d.xaxis[j]
            lo, hi = m.jnt_range[j]
            ind = "      " + "  " * depth
            o.append(f'{ind}<body name="{leg}_{link}" pos="{_fmt(anchor - parent)}">')
            o.append(f'{ind}  <inertial pos="{_fmt(d.xipos[b] - anchor)}" mass="{m.body_mass[b]:.7g}" '
                     f'fullinertia="{_fmt(inertia_world(b))}"/>')
            o.append(f'{ind}  <joint name="{leg}_{jn}" class="{jn}" axis="{_fmt(axis)}" '
                     f'range="{lo:.10g} {hi:.10g}"/>')
            parent = anchor
            depth += 1
        ind = "      " + "  " * depth
        foot = d.xpos[body(f"{leg}_foot")] - parent
        o.append(f'{ind}<geom name="{leg}_shin" type="capsule" fromto="0 0 0 {_fmt(0.8 * foot)}" size="0.02" '
                 'rgba="0.6 0.6 0.6 1"/>')
        o.append(f'{ind}<geom name="{leg}_foot" type="sphere" pos="{_fmt(foot)}" size="0.02175" '
                 'friction="0.8 0.02 0.01" rgba="0.1 0.1 0.1 1"/>')
        o.append(f'{ind}<site name="{leg}_foot" pos="{_fmt(foot)}" size="0.005"/>')
        for k in range(depth - 1, -1, -1):
            o.append("      " + "  " * k + "</body>")
    o += ['    </body>', '  </worldbody>', '  <actuator>']
    o += [f'    <motor name="{leg}_{jn}" joint="{leg}_{jn}"/>' for leg in LEGS for jn in JOINTS]
    o += ['  </actuator>', '  <keyframe>']
    stand = {"lf": (-0.2, 0.75, -1.5), "rf": (-0.2, 0.75, -1.5), "lh": (-0.2, -0.75, 1.5), "rh": (-0.2, -0.75, 1.5)}
    q = " ".join(_fmt(stand[leg]) for leg in LEGS)
    o += [f'    <key name="standing" qpos="0 0 0.5957 1 0 0 0 {q}"/>', '  </keyframe>', '</mujoco>', '']
    return "\n".join(o)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--urdf", required=True, help="path to hyq.urdf (iit-DLSLab/hyq-description)")
    ap.add_argument("--out", default=None, help="write the body tree here (default: print)")
    args = ap.parse_args()
    text = derive(args.urdf)
    if args.out:
        open(args.out, "w").write(text)
    else:
        print(text)


if __name__ == "__main__":
    main()
