"""The servo-rate loop between policy steps and the arm, shared by the hardware and the twin.

A policy sends one joint target per control period (e.g. 20 Hz); the arm wants a fresh set point every
servo tick (500 Hz on an e-Series, RTDE's rate). Each tick interpolates linearly from the previous
target to the newest one over one control period, so the arm moves smoothly and reaches the target one
period after it was sent; velocity and joint limits are enforced on every set point. If no new target
arrives for `stall_periods` control periods (policy crashed, process hung), the loop stops servoing
(servoStop on a UR) and waits for the next command, which restarts from the measured joints.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from lerobot_condground.core.ur3e import servo_setpoint

from .safety import check_safety_mode


@dataclass
class ArmState:
    q: np.ndarray  # measured joint positions (rad)
    qd: np.ndarray  # measured joint velocities (rad/s)
    gripper: float  # measured opening as closure 0 open .. 1 closed
    safety_mode: int = 1
    streaming: bool = False  # a servo stream is active (false after a stall or a stop)
    freedrive: bool = False
    stalls: int = 0  # times the watchdog stopped the arm
    time: float = 0.0  # the loop's clock (s)


class ArmBackend(Protocol):
    """What the loop needs from an arm: ur_rtde's calls on hardware, the MuJoCo twin in simulation."""

    def read(self) -> tuple[np.ndarray, np.ndarray, float, int]:  # q, qd, gripper closure, safety_mode
        ...

    def servo(self, q: np.ndarray) -> None:  # one set point, held until the next tick
        ...

    def servo_stop(self) -> None:  # decelerate to standstill and leave servo mode
        ...

    def set_gripper(self, closure: float) -> None: ...

    def freedrive(self, on: bool) -> None: ...


@dataclass
class ServoLoop:
    backend: ArmBackend
    control_period: float
    servo_period: float
    max_joint_velocity: np.ndarray
    joint_min: np.ndarray
    joint_max: np.ndarray
    stall_periods: float = 2.0
    state: ArmState | None = field(default=None, init=False)

    def __post_init__(self):
        self._from = self._to = self._setpoint = None
        self._t_command = -np.inf
        self._gripper_sent: float | None = None
        self._stalls = 0
        self._freedrive = False
        self.tick(0.0)

    @property
    def streaming(self) -> bool:
        return self._setpoint is not None

    def command(self, q, gripper: float, now: float) -> None:
        """A new policy target; it is reached one control period from `now`. q=None moves only the
        gripper (the arm is in freedrive)."""
        if self._gripper_sent is None or abs(gripper - self._gripper_sent) > 1e-3:
            self.backend.set_gripper(float(gripper))
            self._gripper_sent = float(gripper)
        if q is None or self._freedrive:  # a hand guides the arm: joint targets would fight it
            return
        if not self.streaming:
            # (Re)start from where the arm is: no jump toward a set point from before a stall.
            self._setpoint = self._from = self.state.q.copy()
        else:
            # Continue from where the interpolation is now, not from the old goal it may not have reached.
            self._from = self._setpoint.copy()
        self._to = np.clip(np.asarray(q, dtype=float), self.joint_min, self.joint_max)
        self._t_command = now

    def set_freedrive(self, on: bool) -> None:
        if on and self.streaming:
            self.stop()
        self.backend.freedrive(on)
        self._freedrive = on

    def stop(self) -> None:
        """Stop servoing now; the next command restarts from the measured joints."""
        if self.streaming:
            self._setpoint = None
            self.backend.servo_stop()

    def tick(self, now: float) -> ArmState:
        q, qd, gripper, safety_mode = self.backend.read()
        self.state = ArmState(
            q=np.asarray(q, dtype=float),
            qd=np.asarray(qd, dtype=float),
            gripper=float(gripper),
            safety_mode=int(safety_mode),
            streaming=self.streaming,
            freedrive=self._freedrive,
            stalls=self._stalls,
            time=now,
        )
        try:
            check_safety_mode(safety_mode)
        except Exception:
            self._setpoint = None  # the controller already stopped the arm; never resume by itself
            raise
        if not self.streaming:
            return self.state
        if now - self._t_command > self.stall_periods * self.control_period:
            self._stalls += 1
            self.stop()
            self.state.streaming, self.state.stalls = False, self._stalls
            return self.state
        self._setpoint = servo_setpoint(
            self._setpoint,
            self._from,
            self._to,
            min(max((now - self._t_command) / self.control_period, 0.0), 1.0),
            self.max_joint_velocity * self.servo_period,
            self.joint_min,
            self.joint_max,
        )
        self.backend.servo(self._setpoint)
        return self.state
