"""The teleoperators of `config_ur3e_teleops`; they act through the connected ur3e's arm."""

from __future__ import annotations

import contextlib
import math
import queue

import numpy as np
from lerobot.teleoperators.teleoperator import Teleoperator

from lerobot_condground.core.ur3e import MOTOR_NAMES

from .config_ur3e_teleops import UR3eExpertConfig, UR3eFreedriveConfig, UR3eKeyboardConfig


def _action(q, gripper: float) -> dict[str, float]:
    return {name: float(v) for name, v in zip(MOTOR_NAMES, [*q, gripper], strict=True)}


class _UR3eTeleop(Teleoperator):
    """What all three share: no calibration, no feedback, attach to the robot at the first action."""

    KEYS_HELP = ""

    def __init__(self, config):
        super().__init__(config)
        self.config = config
        self._connected = False
        self.robot = None

    @property
    def action_features(self) -> dict:
        return dict.fromkeys(MOTOR_NAMES, float)

    @property
    def feedback_features(self) -> dict:
        return {}

    @property
    def is_connected(self) -> bool:
        return self._connected

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        pass

    def configure(self) -> None:
        pass

    def send_feedback(self, feedback: dict) -> None:
        pass

    def connect(self, calibrate: bool = True) -> None:
        self._connected = True

    def _listen(self) -> None:
        """Key presses through LeRobot's own listener (X11 via pynput, else the terminal), queued."""
        from lerobot.utils.keyboard_input import create_key_listener

        self.pressed: queue.SimpleQueue[str] = queue.SimpleQueue()
        self.listener = create_key_listener(self.pressed.put, controls_help=self.KEYS_HELP)
        if self.listener is None:
            raise ConnectionError(
                f"{self.name} needs key presses, but there is no display and stdin is not a terminal; run it "
                "from an interactive terminal or a desktop session"
            )

    def _keys(self) -> list[str]:
        out = []
        with contextlib.suppress(queue.Empty):
            while True:
                out.append(self.pressed.get_nowait())
        return out

    def _stop_listening(self) -> None:
        if getattr(self, "listener", None) is not None:
            self.listener.stop()
            self.listener = None

    def _attach(self):
        from lerobot_condground.robots.ur3e import connected_ur3e

        if self.robot is None or not self.robot.is_connected:
            self.robot = connected_ur3e(getattr(self.config, "host", None))
            try:
                self._attached()
            except BaseException:
                self.robot = None  # refused: every later call reports it again
                raise
        return self.robot

    def _attached(self) -> None:
        pass

    def disconnect(self) -> None:
        self._connected = False


class UR3eFreedrive(_UR3eTeleop):
    config_class = UR3eFreedriveConfig
    name = "ur3e_freedrive"

    def connect(self, calibrate: bool = True) -> None:
        self.KEYS_HELP = f"{self.config.gripper_key}: toggle the gripper"
        self._listen()
        self.gripper = 0.0
        super().connect()

    def _attached(self) -> None:
        self.robot.arm.freedrive(True)
        print(
            "ur3e_freedrive: the arm is in freedrive; guide it by hand. "
            f"Key {self.config.gripper_key!r} toggles the gripper.",
            flush=True,
        )

    def get_action(self) -> dict[str, float]:
        robot = self._attach()
        if self.config.gripper_key in self._keys():
            self.gripper = 1.0 - self.gripper
        return _action(robot.arm.state().q + robot.offsets, self.gripper)

    def disconnect(self) -> None:
        try:
            if self.robot is not None and self.robot.is_connected:
                self.robot.arm.freedrive(False)
        finally:
            self._stop_listening()
            super().disconnect()


class UR3eKeyboard(_UR3eTeleop):
    """Tool jogging in the arm's base frame. The letters avoid LeRobot's recording keys (n, r, q, arrows,
    Esc), which the same listener backends deliver to lerobot-record."""

    config_class = UR3eKeyboardConfig
    name = "ur3e_keyboard"
    MOVES = {"w": (0, 1), "s": (0, -1), "a": (1, 1), "d": (1, -1), "i": (2, 1), "k": (2, -1)}
    YAW = {"j": 1, "l": -1}
    KEYS_HELP = "w/s: x, a/d: y, i/k: up/down, j/l: yaw, space: gripper"

    def connect(self, calibrate: bool = True) -> None:
        self._listen()
        super().connect()

    def _attached(self) -> None:
        from lerobot_condground.robots import kinematics

        self.q = self.robot.arm.state().q.copy()
        self.pos, self.rot = kinematics.forward(self.q)
        self.gripper = float(self.robot.arm.state().gripper > 0.5)

    def get_action(self) -> dict[str, float]:
        from lerobot_condground.robots import kinematics

        robot = self._attach()
        pos, yaw = self.pos.copy(), 0.0
        for key in self._keys():
            if key in self.MOVES:
                axis, sign = self.MOVES[key]
                pos[axis] += sign * self.config.step
            elif key in self.YAW:
                yaw += self.config.yaw_step * self.YAW[key]
            elif key == self.config.gripper_key:
                self.gripper = 1.0 - self.gripper
        c, s = math.cos(yaw), math.sin(yaw)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ self.rot
        if not np.allclose(pos, self.pos) or yaw:
            q = kinematics.solve_ik(self.q, pos, rot)
            reached, _ = kinematics.forward(q)
            # Keep the pose the arm can reach (near singularities IK falls short): no drift of the target.
            if np.linalg.norm(reached - pos) < 1e-3 and robot.safety.in_workspace(q):
                self.q, self.pos, self.rot = q, pos, rot
        return _action(self.q + robot.offsets, self.gripper)

    def disconnect(self) -> None:
        self._stop_listening()
        super().disconnect()


class UR3eExpert(_UR3eTeleop):
    """The scripted expert on the twin: one demonstration per scene; it restarts when the twin lays out
    a new scene (at each recorded episode) and holds its last pose when done."""

    config_class = UR3eExpertConfig
    name = "ur3e_expert"

    def _attached(self) -> None:
        from lerobot_condground.envs.expert import ScriptedExpert

        if self.robot.config.backend != "sim":
            raise ValueError("--teleop.type=ur3e_expert drives the twin; use it with --robot.backend=sim")
        self.expert = ScriptedExpert()
        self.scene = None

    def get_action(self) -> dict[str, float]:
        robot = self._attach()
        twin = robot.arm
        with twin.lock:
            if twin.scene != self.scene:
                self.expert.reset(twin.env)
                self.scene = twin.scene
            action = self.expert.act()
        return _action(action[:6] + robot.offsets, float(action[6]))
