"""Command checks that run before anything reaches the arm, whichever backend drives it.

Bad input (wrong length, NaN) is an error: the policy or teleoperator is broken and the arm must not
guess. Out-of-range but finite targets are clipped, because a policy's small excursions past a limit are
normal and stopping the run for them would make the safety layer unusable: to the joint limits, to at
most `max_joint_step` from the last accepted target, and back along the step until the tool stays in
the workspace box. Velocity limits and the stall watchdog act later, at the servo rate (`servo_loop`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import kinematics

# RTDE safety_mode values (UR's SafetyMode enum) that stop the arm and need a person.
SAFETY_MODES = {
    1: "normal",
    2: "reduced",
    3: "protective stop",
    4: "recovery",
    5: "safeguard stop",
    6: "system emergency stop",
    7: "robot emergency stop",
    8: "violation",
    9: "fault",
    10: "validate joint id",
    11: "undefined",
    12: "automatic mode safeguard stop",
    13: "system three position enabling stop",
}
MOVABLE_SAFETY_MODES = (1, 2)


class ArmFault(RuntimeError):  # noqa: N818  (the arm's own word: a UR fault)
    """The arm stopped itself (protective or emergency stop, fault) or lost its controller. It is never
    resumed silently: a person clears the cause on the teach pendant, then reconnects."""


def check_safety_mode(mode: int) -> None:
    if mode not in MOVABLE_SAFETY_MODES:
        name = SAFETY_MODES.get(mode, f"unknown safety mode {mode}")
        raise ArmFault(
            f"The arm reports {name} (safety_mode={mode}) and has stopped. Clear it on the teach pendant "
            "and make the cell safe, then reconnect; the robot never resumes on its own."
        )


@dataclass
class SafetyLimits:
    joint_min: np.ndarray
    joint_max: np.ndarray
    max_joint_step: float
    workspace_min: np.ndarray
    workspace_max: np.ndarray

    def check_action(self, action) -> np.ndarray:
        """7 finite numbers (6 joints in rad + gripper 0..1) or a clear error naming what came."""
        a = np.asarray(action, dtype=float).reshape(-1)
        if a.shape != (7,) or not np.all(np.isfinite(a)):
            raise ValueError(
                f"A ur3e action is 7 finite numbers (6 joint targets in rad, then the gripper 0 open..1 "
                f"closed); got {a.size} values {np.array2string(a, precision=3)}. Nothing was sent to the arm."
            )
        return a

    def in_workspace(self, q) -> bool:
        pos, _ = kinematics.forward(q)
        return bool(np.all(pos >= self.workspace_min) and np.all(pos <= self.workspace_max))

    def _box_distance(self, q) -> float:
        pos, _ = kinematics.forward(q)
        return float(
            np.linalg.norm(np.maximum(self.workspace_min - pos, 0) + np.maximum(pos - self.workspace_max, 0))
        )

    def clip(self, target, previous) -> np.ndarray:
        """The joint target actually sent, given the last accepted one."""
        previous = np.asarray(previous, dtype=float)
        q = np.clip(np.asarray(target, dtype=float), self.joint_min, self.joint_max)
        q = np.clip(q, previous - self.max_joint_step, previous + self.max_joint_step)
        if self.in_workspace(q):
            return q
        if not self.in_workspace(previous):
            # Started outside (the arm was parked there): only moves that approach the box are taken.
            return q if self._box_distance(q) <= self._box_distance(previous) else previous
        lo, hi = 0.0, 1.0  # largest fraction of the step that keeps the tool inside
        for _ in range(12):
            mid = (lo + hi) / 2
            lo, hi = (mid, hi) if self.in_workspace(previous + mid * (q - previous)) else (lo, mid)
        return previous + lo * (q - previous)
