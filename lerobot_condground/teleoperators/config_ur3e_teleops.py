"""Teleoperators of the `ur3e` robot. Each attaches to the connected ur3e of the same process (LeRobot
connects the teleoperator before the robot, so they attach at their first action).

- `ur3e_freedrive`: kinesthetic demonstrations. The arm is in freedrive (UR teach mode); the measured
  joints are the actions; a key toggles the gripper.
- `ur3e_keyboard`: end-effector jogging for arms without freedrive use: keys move the tool, IK turns
  the pose into joint targets.
- `ur3e_expert`: the scripted expert of the simulation, acting on the twin (`--robot.backend=sim`).

Keys come through LeRobot's own key listener (pynput on a desktop, else the terminal); a USB foot pedal
that types a key works the same way.
"""

from __future__ import annotations

from dataclasses import dataclass

from lerobot.teleoperators.config import TeleoperatorConfig


@TeleoperatorConfig.register_subclass("ur3e_freedrive")
@dataclass(kw_only=True)
class UR3eFreedriveConfig(TeleoperatorConfig):
    # The ur3e to attach to, when several are connected.
    host: str | None = None
    # Key that toggles the gripper between open and closed.
    gripper_key: str = "space"


@TeleoperatorConfig.register_subclass("ur3e_keyboard")
@dataclass(kw_only=True)
class UR3eKeyboardConfig(TeleoperatorConfig):
    host: str | None = None
    # Tool translation per key press (m) and yaw per key press (rad).
    step: float = 0.005
    yaw_step: float = 0.05
    gripper_key: str = "space"

    def __post_init__(self):
        if not 0 < self.step <= 0.02:
            raise ValueError(f"ur3e_keyboard step={self.step} m; allowed: (0, 0.02]")
        if not 0 < self.yaw_step <= 0.2:
            raise ValueError(f"ur3e_keyboard yaw_step={self.yaw_step} rad; allowed: (0, 0.2]")


@TeleoperatorConfig.register_subclass("ur3e_expert")
@dataclass(kw_only=True)
class UR3eExpertConfig(TeleoperatorConfig):
    pass
