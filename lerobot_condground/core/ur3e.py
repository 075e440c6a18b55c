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

# The UR3e's rated joint speeds (rad/s; Universal Robots' e-Series data sheet: 180 deg/s at base, shoulder and
# elbow, 360 deg/s at the wrists). The simulated arm's servos keep to them; the hardware path defaults to
# lower limits of its own (`--robot.max_joint_velocity`).
MAX_JOINT_VELOCITY = np.array([math.pi] * 3 + [2 * math.pi] * 3)

# How the simulated arm's position servos take a joint target. `interpolated`: as the UR3e's servoj stream
# (and the twin's ServoLoop), the set point moves along the line to the target over one control period,
# no faster than MAX_JOINT_VELOCITY. `direct`: the target is the set point at once and the torque-limited
# servos chase it as fast as they can (a jump between two action chunks can throw the cube off the table);
# what every run made before this setting existed measured.
SERVO_MODES = ("interpolated", "direct")
SERVO_BEFORE_THE_SETTING = "direct"  # what recordings and reproductions that do not name a mode ran with


def forward_kinematics(q, tcp_offset: float = FLANGE_TO_TCP) -> tuple[np.ndarray, np.ndarray]:
    """Tool-centre position (m) and rotation matrix in the base frame for joint angles q (rad): one
    configuration (6,) or many (..., 6) at once, from the DH table above."""
    q = np.asarray(q, dtype=float)
    ct, st = np.cos(q), np.sin(q)
    t = None
    for i in range(6):
        c, s = ct[..., i], st[..., i]
        ca, sa = math.cos(UR3E_DH_ALPHA[i]), math.sin(UR3E_DH_ALPHA[i])
        link = np.zeros((*q.shape[:-1], 4, 4))
        link[..., 0, 0], link[..., 0, 1], link[..., 0, 2], link[..., 0, 3] = (
            c,
            -s * ca,
            s * sa,
            UR3E_DH_A[i] * c,
        )
        link[..., 1, 0], link[..., 1, 1], link[..., 1, 2], link[..., 1, 3] = (
            s,
            c * ca,
            -c * sa,
            UR3E_DH_A[i] * s,
        )
        link[..., 2, 1], link[..., 2, 2], link[..., 2, 3], link[..., 3, 3] = sa, ca, UR3E_DH_D[i], 1.0
        t = link if t is None else t @ link
    return t[..., :3, 3] + t[..., :3, 2] * tcp_offset, t[..., :3, :3]


def check_servo(servo: str, name: str = "servo") -> None:
    if servo not in SERVO_MODES:
        raise ValueError(f"{name}={servo!r} is not allowed; allowed: {', '.join(SERVO_MODES)}")


def servo_setpoint(setpoint, start, goal, fraction: float, max_step, low, high) -> np.ndarray:
    """The next servo set point: `fraction` of the way along the line from `start` to `goal` (a policy target
    interpolated over one control period), at most `max_step` from the last set point, within the joint
    limits. What a UR's servoj stream does between two policy steps."""
    target = start + fraction * (goal - start)
    return np.clip(setpoint + np.clip(target - setpoint, -max_step, max_step), low, high)
