"""UR3e forward and inverse kinematics from the published DH table, in the robot's base frame.

The workspace check runs on every command, and the spatial teleoperator solves IK at its control
rate, so this stays in numpy: no MuJoCo model, no robot connection. The simulated arm is built from
the same table (`core.ur3e`), so poses agree between the twin and the hardware, up to the twin's
base being turned 180 deg about z in its world.
"""

from __future__ import annotations

import numpy as np

from lerobot_condground.core.ur3e import forward_kinematics

# Forward kinematics lives with the DH table: the diagnosis measures tool positions with it too.
forward = forward_kinematics


def _pose_error(q, pos, rot) -> np.ndarray:
    p, r = forward(q)
    # Orientation error as the rotation vector of r^T rot, expressed in the base frame (small-angle form).
    e = r.T @ rot
    w = 0.5 * np.array([e[2, 1] - e[1, 2], e[0, 2] - e[2, 0], e[1, 0] - e[0, 1]])
    return np.concatenate([pos - p, r @ w])


def solve_ik(q0, pos, rot, iters: int = 50, damping: float = 1e-3, tol: float = 1e-5) -> np.ndarray:
    """Damped least squares from `q0` toward the pose (pos, rot); returns the joints reached.

    Starting from the current joints keeps the solution on the same branch (elbow up, wrist as it is),
    which is what jogging needs: small, continuous steps.
    """
    q = np.asarray(q0, dtype=float).copy()
    pos, rot = np.asarray(pos, float), np.asarray(rot, float)
    eps = 1e-6
    for _ in range(iters):
        err = _pose_error(q, pos, rot)
        if np.linalg.norm(err) < tol:
            break
        jac = np.empty((6, 6))
        for j in range(6):
            dq = q.copy()
            dq[j] += eps
            jac[:, j] = (err - _pose_error(dq, pos, rot)) / eps
        q += jac.T @ np.linalg.solve(jac @ jac.T + damping * np.eye(6), err)
    return q
