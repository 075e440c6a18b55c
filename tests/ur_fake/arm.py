"""The simulated arm: the mode codes the controller reports, and the kinematics that keep actual_TCP_pose
in step with actual_q."""

from __future__ import annotations

import math

ROBOT_MODES = {
    -1: "NO_CONTROLLER",
    0: "DISCONNECTED",
    1: "CONFIRM_SAFETY",
    2: "BOOTING",
    3: "POWER_OFF",
    4: "POWER_ON",
    5: "IDLE",
    6: "BACKDRIVE",
    7: "RUNNING",
    8: "UPDATING_FIRMWARE",
}
SAFETY_MODES = {
    1: "NORMAL",
    2: "REDUCED",
    3: "PROTECTIVE_STOP",
    4: "RECOVERY",
    5: "SAFEGUARD_STOP",
    6: "SYSTEM_EMERGENCY_STOP",
    7: "ROBOT_EMERGENCY_STOP",
    8: "VIOLATION",
    9: "FAULT",
    10: "VALIDATE_JOINT_ID",
    11: "UNDEFINED_SAFETY_MODE",
    12: "AUTOMATIC_MODE_SAFEGUARD_STOP",
    13: "SYSTEM_THREE_POSITION_ENABLING_STOP",
}
RUNTIME_STATES = {"STOPPING": 0, "STOPPED": 1, "PLAYING": 2, "PAUSING": 3, "PAUSED": 4, "RESUMING": 5}
EMERGENCY_STOPS = (6, 7)

# e-Series DH parameters (Universal Robots' published kinematics), so actual_TCP_pose agrees with actual_q.
DH = {
    "UR3": ([0.15185, 0, 0, 0.13105, 0.08535, 0.0921], [0, -0.24355, -0.2132, 0, 0, 0]),
    "UR5": ([0.1625, 0, 0, 0.1333, 0.0997, 0.0996], [0, -0.425, -0.3922, 0, 0, 0]),
    "UR10": ([0.1807, 0, 0, 0.17415, 0.11985, 0.11655], [0, -0.6127, -0.57155, 0, 0, 0]),
    "UR16": ([0.1807, 0, 0, 0.17415, 0.11985, 0.11655], [0, -0.4784, -0.36, 0, 0, 0]),
}
DH_ALPHA = [math.pi / 2, 0, 0, math.pi / 2, -math.pi / 2, 0]


def _matmul(a, b):
    return [[sum(a[i][k] * b[k][j] for k in range(4)) for j in range(4)] for i in range(4)]


def _rotvec_to_matrix(rx, ry, rz):
    angle = math.sqrt(rx * rx + ry * ry + rz * rz)
    if angle < 1e-12:
        return [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    x, y, z = rx / angle, ry / angle, rz / angle
    c, s, v = math.cos(angle), math.sin(angle), 1 - math.cos(angle)  # v: versine
    return [
        [c + x * x * v, x * y * v - z * s, x * z * v + y * s],
        [y * x * v + z * s, c + y * y * v, y * z * v - x * s],
        [z * x * v - y * s, z * y * v + x * s, c + z * z * v],
    ]


def _matrix_to_rotvec(r):
    cos_a = max(-1.0, min(1.0, (r[0][0] + r[1][1] + r[2][2] - 1) / 2))
    angle = math.acos(cos_a)
    if angle < 1e-9:
        return [0.0, 0.0, 0.0]
    if math.pi - angle < 1e-6:  # axis from the diagonal; sin(angle) is ~0
        x = math.sqrt(max(0.0, (r[0][0] + 1) / 2))
        y = math.copysign(math.sqrt(max(0.0, (r[1][1] + 1) / 2)), r[0][1] if x > 1e-6 else 1.0)
        z = math.copysign(math.sqrt(max(0.0, (r[2][2] + 1) / 2)), r[0][2] if x > 1e-6 else r[1][2])
        return [x * angle, y * angle, z * angle]
    k = angle / (2 * math.sin(angle))
    return [(r[2][1] - r[1][2]) * k, (r[0][2] - r[2][0]) * k, (r[1][0] - r[0][1]) * k]


def forward_kinematics(q, model: str = "UR3", tcp_offset=(0, 0, 0, 0, 0, 0)) -> list[float]:
    """TCP pose [x, y, z, rx, ry, rz] (base frame, rotation vector) as the controller reports it."""
    d, a = DH.get(model.upper().rstrip("E"), DH["UR3"])
    t = [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]
    for i in range(6):
        ct, st = math.cos(q[i]), math.sin(q[i])
        ca, sa = math.cos(DH_ALPHA[i]), math.sin(DH_ALPHA[i])
        t = _matmul(
            t,
            [
                [ct, -st * ca, st * sa, a[i] * ct],
                [st, ct * ca, -ct * sa, a[i] * st],
                [0, sa, ca, d[i]],
                [0, 0, 0, 1],
            ],
        )
    r = _rotvec_to_matrix(*tcp_offset[3:])
    tool = [r[0] + [tcp_offset[0]], r[1] + [tcp_offset[1]], r[2] + [tcp_offset[2]], [0, 0, 0, 1]]
    t = _matmul(t, tool)
    return [t[0][3], t[1][3], t[2][3]] + _matrix_to_rotvec([row[:3] for row in t[:3]])
