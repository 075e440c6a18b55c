"""The UR3e's kinematic spec and names, shared by the MuJoCo twin (`envs.robot`) and the hardware path.

Plain numbers only: the hardware code (`robots/`, `teleoperators/`) imports this without MuJoCo.
"""

from __future__ import annotations

import math

import numpy as np

# Universal Robots' published standard DH parameters for the UR3e (metres, radians).
UR3E_DH_D = (0.15185, 0.0, 0.0, 0.13105, 0.08535, 0.0921)
UR3E_DH_A = (0.0, -0.24355, -0.2132, 0.0, 0.0, 0.0)
UR3E_DH_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)

JOINT_NAMES = (
    "shoulder_pan",
    "shoulder_lift",
    "elbow",
    "wrist_1",
    "wrist_2",
    "wrist_3",
)
GRIPPER_NAME = "gripper"
# Names of observation.state / action entries, in order ("<joint>.pos" as LeRobot robots name them).
MOTOR_NAMES = tuple(f"{n}.pos" for n in JOINT_NAMES) + (f"{GRIPPER_NAME}.pos",)

# Elbow-up, tool pointing down above the workspace.
HOME_QPOS = np.array([0.0, -1.75, 1.9, -1.72, -1.5708, 0.0])

# Robotiq 2F-85-like jaw: 85 mm stroke, each finger travels half of it.
GRIPPER_STROKE = 0.085
FLANGE_TO_TCP = 0.155  # flange to the middle of the finger pads
