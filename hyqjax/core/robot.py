"""HyQ's constants: leg and joint names, geometry, limits and the standing pose.

All numbers are read from IIT's ``hyq.urdf`` / ``hyq.srdf`` (iit-DLSLab/hyq-description,
Apache-2.0; see ``hyqjax/assets/NOTICE.md``) and checked against the MJCF in
``tests/test_model.py``. Frames: ``B`` is the trunk (base) frame, x forward, y left, z up.

Joint vectors of length 12 are ordered leg-major, ``(LF, RF, LH, RH) x (HAA, HFE, KFE)``,
the order of the MJCF's joints and actuators.
"""
from __future__ import annotations

import numpy as np

LEG_NAMES: tuple[str, ...] = ("lf", "rf", "lh", "rh")
JOINT_NAMES: tuple[str, ...] = ("haa", "hfe", "kfe")
N_LEGS = 4
N_JOINTS = 12

LF, RF, LH, RH = 0, 1, 2, 3
#: ``STANCE_LEGS[s]``: the three stance legs, in increasing index order, while leg ``s`` swings.
STANCE_LEGS: np.ndarray = np.array([[j for j in range(4) if j != s] for s in range(4)], dtype=np.int32)
HAA, HFE, KFE = 0, 1, 2

#: HAA joint positions in the trunk frame, ``B_p_HAA`` (m), shape (4, 3).
B_P_HIP = np.array(
    [[0.3735, 0.207, 0.0], [0.3735, -0.207, 0.0], [-0.3735, 0.207, 0.0], [-0.3735, -0.207, 0.0]]
)
#: Sign of the HAA axis along the trunk x axis: left legs rotate about -x, right legs about +x.
HAA_AXIS_SIGN = np.array([-1.0, 1.0, -1.0, 1.0])
#: Offset from the HAA axis to the HFE axis along the leg (m).
L_HAA_HFE = 0.08
#: Upper-leg (HFE to KFE) and lower-leg (KFE to foot centre) lengths (m).
L_UPPER = 0.35
L_LOWER = 0.341
#: Foot sphere radius (m).
FOOT_RADIUS = 0.02175
#: Knee direction: sign of the KFE angle (front knees bend with KFE < 0, hind with KFE > 0).
KNEE_SIGN = np.array([-1.0, -1.0, 1.0, 1.0])

#: Joint ranges (rad), shape (4, 3): HAA, HFE, KFE per leg.
Q_MIN_LEG = np.array(
    [
        [-1.2217304763960306, -0.8726646259971648, -2.443460952792061],
        [-1.2217304763960306, -0.8726646259971648, -2.443460952792061],
        [-1.2217304763960306, -1.2217304763960306, 0.3490658503988659],
        [-1.2217304763960306, -1.2217304763960306, 0.3490658503988659],
    ]
)
Q_MAX_LEG = np.array(
    [
        [0.4363323129985824, 1.2217304763960306, -0.3490658503988659],
        [0.4363323129985824, 1.2217304763960306, -0.3490658503988659],
        [0.4363323129985824, 0.8726646259971648, 2.443460952792061],
        [0.4363323129985824, 0.8726646259971648, 2.443460952792061],
    ]
)
Q_MIN = Q_MIN_LEG.reshape(-1)
Q_MAX = Q_MAX_LEG.reshape(-1)
#: Joint torque limit (N m) and velocity limit (rad/s), the URDF's ``effort`` and ``velocity``.
TORQUE_LIMIT = 150.0
VELOCITY_LIMIT = 12.0

#: SRDF ``standing`` pose, shape (12,).
Q_STANDING = np.array([-0.2, 0.75, -1.5, -0.2, 0.75, -1.5, -0.2, -0.75, 1.5, -0.2, -0.75, 1.5])
#: Trunk height above the foot centres in the standing pose, from the URDF kinematics (m).
#: (The SRDF states 0.5775 m; the URDF's link lengths give this value, 3.6 mm less.)
STANDING_HEIGHT = 0.573883
#: Trunk height above the ground in the standing keyframe (foot spheres touching the ground).
STANDING_BASE_Z = 0.5957

#: Total mass (kg): trunk 58.96 + 4 legs x (2.93 + 2.638 + 0.881).
TOTAL_MASS = 84.756
GRAVITY = 9.81

#: The trunk's free joint in MuJoCo's ``qpos`` / ``qvel``: position in ``W`` (m), orientation quaternion
#: ``W_q_B`` (w, x, y, z); linear velocity in ``W`` (m/s), angular velocity in ``B`` (rad/s). The 12 joints follow.
QPOS_BASE_POS = slice(0, 3)
QPOS_BASE_QUAT = slice(3, 7)
QVEL_BASE_LIN = slice(0, 3)
QVEL_BASE_ANG = slice(3, 6)
QPOS_JOINTS = slice(7, 19)
QVEL_JOINTS = slice(6, 18)
