"""`--robot.type=ur3e`: a Universal Robots UR3e driven through ur_rtde, or its MuJoCo twin.

    lerobot-record --robot.type=ur3e --robot.host=192.168.1.10 \
        --robot.cameras='{top: {type: opencv, index_or_path: 0, width: 640, height: 480, fps: 30}}' ...
    lerobot-record --robot.type=ur3e --robot.backend=sim --teleop.type=ur3e_expert ...

Observations and actions use the simulation's layout (`<joint>.pos` for the six joints in rad, then
`gripper.pos` 0 open .. 1 closed), so policies trained on either side line up.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from lerobot.cameras import CameraConfig
from lerobot.robots.config import RobotConfig

from lerobot_condground.core.configs import ConfigError
from lerobot_condground.labelling.segmenters import DEFAULT_SAM2_MODEL, SEGMENTERS

BACKENDS = ("rtde", "sim")
GRIPPERS = ("robotiq", "digital_output", "none")
PROMPT_SEGMENTERS = ("privileged", *SEGMENTERS)  # privileged: the twin's exact crops


@dataclass
class UR3eSimConfig:
    """The MuJoCo twin (`--robot.backend=sim`): the condground scene with the UR3e-like arm."""

    task: str = "PickPlaceRandomBin-v0"
    condition: str = "clean"
    counterbalanced: bool = False
    # Scene k of a session uses layout seed `seed + k`.
    seed: int = 0
    # true: physics runs in its own thread at wall-clock speed, like the arm (a hung policy stalls the
    # stream and the watchdog stops the arm). false: each action advances exactly one control period,
    # so recordings are reproducible whatever the machine's load.
    realtime: bool = True


@dataclass
class UR3ePromptsConfig:
    """Visual prompts as virtual cameras `prompt_object` / `prompt_receptacle` (64x64 RGB crops).

    segmenter: none (off), privileged (the twin's exact crops, sim only), color or sam2 (tracked on
    `camera` from a click/box given here, or picked in a window with interactive=true).
    """

    segmenter: str | None = None
    camera: str = "top"
    # "x,y" (a click) or "x0,y0,x1,y1" (a box) on the first frame of `camera`.
    object: str | None = None
    receptacle: str | None = None
    interactive: bool = False
    sam2_model_id: str = DEFAULT_SAM2_MODEL
    device: str = "cpu"


def _default_joint_min() -> list[float]:
    return [-2 * math.pi, -2 * math.pi, -math.pi, -2 * math.pi, -2 * math.pi, -2 * math.pi]


@RobotConfig.register_subclass("ur3e")
@dataclass(kw_only=True)
class UR3eConfig(RobotConfig):
    # rtde: the arm through ur_rtde (host required); sim: the MuJoCo twin.
    backend: str = "rtde"
    host: str | None = None
    cameras: dict[str, CameraConfig] = field(default_factory=dict)

    # Policy steps per second; set it to the recording's --dataset.fps. Targets are interpolated at
    # `servo_hz` in between (500 Hz: the e-Series RTDE rate).
    control_hz: float = 20.0
    servo_hz: float = 500.0
    # servoJ smoothing: lookahead 0.03..0.2 s (longer = smoother, more lag), gain 100..2000 (higher =
    # stiffer tracking). UR's defaults are 0.1 s and 300.
    servoj_lookahead_time: float = 0.1
    servoj_gain: float = 300.0

    gripper: str = "robotiq"
    # Robotiq URCap socket port, and speed/force 0..255.
    gripper_port: int = 63352
    gripper_speed: int = 128
    gripper_force: int = 64
    # Tool digital output driving a plain pneumatic or electric gripper (gripper=digital_output).
    gripper_output: int = 0

    # The dashboard server's `get robot model` answer this robot accepts (an e-Series UR3e says UR3).
    expected_model: str = "UR3"
    # Read the arm and check every command, but send none: try a policy against the real state.
    dry_run: bool = False
    connect_timeout_s: float = 10.0

    # Calibration: added to the measured joints to give the policy's joints (and subtracted from
    # commands), e.g. when the arm's base is mounted turned against the frame the policy learned in.
    joint_offsets: list[float] = field(default_factory=lambda: [0.0] * 6)
    # Move to the home pose (`lerobot-calibrate` stores it; default: the simulation's) at 0.5 rad/s after
    # connecting, so that episodes start where demonstrations did (lerobot-rollout returns to the pose it
    # found at start-up between episodes).
    move_home_on_connect: bool = False

    # Safety, always on. Joint limits (rad); largest change of a joint target per control period (rad);
    # joint speed limits (rad/s) applied at the servo rate; the box (m, base frame) the tool centre must
    # stay in; a command stream silent for `stall_periods` control periods stops the arm.
    joint_min: list[float] = field(default_factory=_default_joint_min)
    joint_max: list[float] = field(default_factory=lambda: [-v for v in _default_joint_min()])
    max_joint_step: float = 0.15
    max_joint_velocity: list[float] = field(default_factory=lambda: [2.0, 2.0, 2.0, 3.0, 3.0, 3.0])
    workspace_min: list[float] = field(default_factory=lambda: [-0.5, -0.5, 0.005])
    workspace_max: list[float] = field(default_factory=lambda: [0.5, 0.5, 0.5])
    stall_periods: float = 2.0

    sim: UR3eSimConfig = field(default_factory=UR3eSimConfig)
    prompts: UR3ePromptsConfig = field(default_factory=UR3ePromptsConfig)

    def __post_init__(self):
        if self.backend == "sim" and not self.cameras:
            from lerobot_condground.cameras.config_ur3e_twin import UR3eTwinCameraConfig

            self.cameras = {
                "top": UR3eTwinCameraConfig(camera="top", width=320, height=240, fps=int(self.control_hz))
            }
        super().__post_init__()
        problems = []
        if self.backend not in BACKENDS:
            problems.append(f"backend={self.backend!r}; allowed: {', '.join(BACKENDS)}")
        if self.backend == "rtde" and not self.host:
            problems.append(
                "host is required with backend=rtde (the controller's IP address, e.g. --robot.host=192.168.1.10)"
            )
        if self.gripper not in GRIPPERS:
            problems.append(f"gripper={self.gripper!r}; allowed: {', '.join(GRIPPERS)}")
        for name in ("joint_offsets", "joint_min", "joint_max", "max_joint_velocity"):
            value = getattr(self, name)
            if len(value) != 6 or not all(math.isfinite(v) for v in value):
                problems.append(f"{name}={value}: 6 finite numbers, one per joint")
        for name in ("workspace_min", "workspace_max"):
            value = getattr(self, name)
            if len(value) != 3 or not all(math.isfinite(v) for v in value):
                problems.append(f"{name}={value}: 3 finite numbers x, y, z in metres")
        if not problems:
            if any(lo >= hi for lo, hi in zip(self.joint_min, self.joint_max, strict=True)):
                problems.append(f"joint_min={self.joint_min} must be below joint_max={self.joint_max}")
            if any(lo >= hi for lo, hi in zip(self.workspace_min, self.workspace_max, strict=True)):
                problems.append(
                    f"workspace_min={self.workspace_min} must be below workspace_max={self.workspace_max}"
                )
            if any(v <= 0 for v in self.max_joint_velocity):
                problems.append(f"max_joint_velocity={self.max_joint_velocity} must be positive")
        if not 0 < self.max_joint_step <= 0.5:
            problems.append(f"max_joint_step={self.max_joint_step} rad; allowed: (0, 0.5]")
        if not 1 <= self.control_hz <= self.servo_hz / 2:
            problems.append(f"control_hz={self.control_hz}; allowed: 1 .. servo_hz/2 ({self.servo_hz / 2:g})")
        if self.backend == "sim" and self.servo_hz != 500:
            problems.append(f"servo_hz={self.servo_hz}; the twin runs its physics at 500 Hz")
        if not 0.03 <= self.servoj_lookahead_time <= 0.2:
            problems.append(
                f"servoj_lookahead_time={self.servoj_lookahead_time}; allowed: 0.03..0.2 s (UR's range)"
            )
        if not 100 <= self.servoj_gain <= 2000:
            problems.append(f"servoj_gain={self.servoj_gain}; allowed: 100..2000 (UR's range)")
        if not 1 <= self.stall_periods <= 50:  # also refuses NaN and inf: a watchdog that never fires
            problems.append(f"stall_periods={self.stall_periods}; allowed: 1..50")
        if self.prompts.segmenter not in (None, *PROMPT_SEGMENTERS):
            problems.append(
                f"prompts.segmenter={self.prompts.segmenter!r}; allowed: {', '.join(PROMPT_SEGMENTERS)} (or unset)"
            )
        elif self.prompts.segmenter == "privileged" and self.backend != "sim":
            problems.append(
                "prompts.segmenter=privileged reads the twin's ground truth; it needs backend=sim"
            )
        elif self.prompts.segmenter in SEGMENTERS:
            if self.prompts.camera not in self.cameras:
                problems.append(
                    f"prompts.camera={self.prompts.camera!r} is not a camera of this robot; cameras: {', '.join(self.cameras) or 'none'}"
                )
            if not self.prompts.interactive and not (self.prompts.object and self.prompts.receptacle):
                problems.append(
                    "prompts.object and prompts.receptacle (x,y or x0,y0,x1,y1) are needed unless prompts.interactive=true"
                )
        if problems:
            raise ConfigError("Invalid ur3e robot config: " + "; ".join(problems))
        if self.backend == "sim":
            from lerobot_condground.core.conditions import ConditionSpec, check_task

            check_task(self.sim.task)
            ConditionSpec.parse(self.sim.condition)
