"""`ur3e`: a LeRobot Robot over an arm backend (ur_rtde hardware or the MuJoCo twin), cameras, and
optional visual-prompt virtual cameras.

Every action passes the safety layer before it reaches an arm: one clear error for malformed actions,
clipping to joint limits, per-period step and workspace box; the arm's servo loop adds velocity limits
and the stall watchdog. `disconnect()` always stops the arm first, also when LeRobot's scripts unwind
after an exception or Ctrl-C.
"""

from __future__ import annotations

import itertools
import json
import logging
import numbers
import time
from functools import cached_property

import numpy as np
from lerobot.cameras.utils import make_cameras_from_configs
from lerobot.robots.robot import Robot

from lerobot_condground.core.labels import PROMPT_SIZE
from lerobot_condground.core.ur3e import HOME_QPOS, MOTOR_NAMES

from .config_ur3e import UR3eConfig
from .episodes import recording_episode
from .safety import SafetyLimits

logger = logging.getLogger(__name__)

PROMPT_KEYS = ("prompt_object", "prompt_receptacle")
HOMING_SPEED = 0.5  # rad/s of the fastest joint while moving home
_CONNECTED: list[UR3e] = []


def connected_ur3e(host: str | None = None) -> UR3e:
    """The connected ur3e of this process (teleoperators that drive its arm attach to it)."""
    robots = [r for r in _CONNECTED if host is None or r.config.host == host]
    if len(robots) != 1:
        where = f" with host {host}" if host else ""
        raise RuntimeError(
            f"{len(robots)} ur3e robots{where} are connected in this process; this teleoperator drives the arm "
            "of exactly one connected --robot.type=ur3e (set --teleop.host when there are several)"
        )
    return robots[0]


def _is_real(value) -> bool:
    """A real scalar: Python's and numpy's, or a 0-d array or tensor (what LeRobot's converters hand over)."""
    if isinstance(value, bool | str | bytes):
        return False
    return isinstance(value, numbers.Real) or (
        getattr(value, "ndim", None) == 0 and not hasattr(value, "keys")
    )


class UR3e(Robot):
    config_class = UR3eConfig
    name = "ur3e"

    def __init__(self, config: UR3eConfig):
        super().__init__(config)
        self.config = config
        self.cameras = make_cameras_from_configs(config.cameras)
        self.arm = None
        self.offsets = np.asarray(config.joint_offsets, dtype=float)
        self.safety = SafetyLimits(
            joint_min=np.asarray(config.joint_min, float),
            joint_max=np.asarray(config.joint_max, float),
            max_joint_step=config.max_joint_step,
            workspace_min=np.asarray(config.workspace_min, float),
            workspace_max=np.asarray(config.workspace_max, float),
        )
        self.home = np.asarray(self.calibration.get("home", HOME_QPOS), dtype=float)
        self._target: np.ndarray | None = None
        self._prompts = None
        self._prompt_crops: dict | None = None
        self._episode = None

    # ------------------------------------------------------------------ features
    @cached_property
    def observation_features(self) -> dict:
        features: dict = dict.fromkeys(MOTOR_NAMES, float)
        for name, cam in self.config.cameras.items():
            features[name] = (cam.height, cam.width, 3)
        if self.config.prompts.segmenter:
            features |= dict.fromkeys(PROMPT_KEYS, (PROMPT_SIZE, PROMPT_SIZE, 3))
        return features

    @cached_property
    def action_features(self) -> dict:
        return dict.fromkeys(MOTOR_NAMES, float)

    # ------------------------------------------------------------------ calibration
    @property
    def is_calibrated(self) -> bool:
        return True  # UR arms are calibrated at the factory; the home pose is optional

    def _load_calibration(self, fpath=None) -> None:
        with open(fpath or self.calibration_fpath) as f:
            self.calibration = json.load(f)

    def _save_calibration(self, fpath=None) -> None:
        with open(fpath or self.calibration_fpath, "w") as f:
            json.dump(self.calibration, f, indent=2)

    def calibrate(self) -> None:
        """`lerobot-calibrate --robot.type=ur3e --robot.host=... --robot.id=NAME`: move the arm (freedrive)
        to the home pose episodes start from, press Enter; it is stored in the calibration file."""
        if self.arm is None:
            raise RuntimeError("Connect the ur3e before calibrating")
        self.arm.freedrive(True)
        try:
            input("Move the arm to its home pose (freedrive is on), then press Enter...")
            q = self.arm.state().q + self.offsets
        finally:
            self.arm.freedrive(False)
        self.calibration = {"home": [float(v) for v in q]}
        self.home = q
        self._save_calibration()
        logger.info("Home pose %s saved to %s", np.round(q, 4).tolist(), self.calibration_fpath)

    def configure(self) -> None:
        pass

    # ------------------------------------------------------------------ connection
    @property
    def is_connected(self) -> bool:
        return self.arm is not None and self.arm.is_connected

    def connect(self, calibrate: bool = True) -> None:
        if self.is_connected:
            raise RuntimeError(f"{self} is already connected")
        if self.config.backend == "sim":
            from .sim_arm import SimArm

            arm = SimArm(self.config, self.home)
        else:
            from .rtde_arm import RTDEArm

            arm = RTDEArm(self.config)
        arm.connect()
        self.arm = arm
        try:
            for name, cam in self.cameras.items():
                try:
                    cam.connect()
                except Exception as exc:
                    raise ConnectionError(
                        f"Camera {name!r} ({self.config.cameras[name].type}) could not be opened: {exc}. "
                        f"Check that it is plugged in and its settings ({self.config.cameras[name]}); "
                        "`lerobot-find-cameras` lists the cameras this machine sees."
                    ) from exc
            self._start_prompts()
            self._target = None
            _CONNECTED.append(self)
            if self.config.move_home_on_connect:
                self.move_to(self.home)
        except BaseException:
            self.disconnect()
            raise

    def move_to(self, q, speed: float = HOMING_SPEED, tolerance: float = 0.01, settle_s: float = 3.0) -> None:
        """Moves the joints to `q` (policy frame) along a straight joint-space line at `speed`, through the
        same safety layer as every action, and holds the target until the arm is there; the gripper keeps
        its state."""
        state = self.arm.state()
        start, gripper = state.q + self.offsets, state.gripper
        q = np.asarray(q, dtype=float)
        steps = max(1, int(np.ceil(np.abs(q - start).max() / speed * self.config.control_hz)))
        deadline = None
        for k in itertools.count(1):
            t0 = time.perf_counter()
            self.send_action(
                dict(zip(MOTOR_NAMES, [*(start + (q - start) * min(k / steps, 1.0)), gripper], strict=True))
            )
            if k >= steps:
                deadline = deadline or t0 + settle_s
                error = np.abs(self.arm.state().q + self.offsets - q).max()
                if error < tolerance:
                    return
                if t0 > deadline:
                    raise RuntimeError(
                        f"The arm did not reach {np.round(q, 3).tolist()} within {settle_s} s "
                        f"(still {error:.3f} rad away); is something in its way?"
                    )
            time.sleep(max(0.0, 1 / self.config.control_hz - (time.perf_counter() - t0)))

    def disconnect(self) -> None:
        try:
            if self.arm is not None:
                self.arm.disconnect()  # stops the arm first, whatever else fails below
        finally:
            self.arm = None
            if self in _CONNECTED:
                _CONNECTED.remove(self)
            for cam in self.cameras.values():
                if cam.is_connected:
                    cam.disconnect()

    # ------------------------------------------------------------------ prompts
    def _start_prompts(self) -> None:
        cfg = self.config.prompts
        if cfg.segmenter in (None, "privileged"):
            return
        from lerobot_condground.labelling.prompt_tracker import PromptTracker
        from lerobot_condground.labelling.segmenters import make_segmenter, parse_prompt

        if not cfg.interactive:
            cam = self.config.cameras[cfg.camera]
            for role in ("object", "receptacle"):  # a click outside the image fails here, before any motion
                try:
                    parse_prompt(getattr(cfg, role), (cam.height, cam.width))
                except ValueError as exc:
                    raise ValueError(f"--robot.prompts.{role}={getattr(cfg, role)}: {exc}") from exc
        kwargs = {"model_id": cfg.sam2_model_id, "device": cfg.device} if cfg.segmenter == "sam2" else {}
        self._prompts = PromptTracker(make_segmenter(cfg.segmenter, **kwargs))

    def _prompt_observation(self, frames: dict) -> dict:
        """The episode's prompt crops. They are positionless appearance crops, fixed for the episode (see
        `prompt_tracker`), so the segmenter runs once, on the episode's first frame, not on every frame:
        live use costs one segmentation per episode."""
        cfg = self.config.prompts
        if cfg.segmenter == "privileged":
            crops = self.arm.env._prompt_crops
        else:
            if self._prompt_crops is None:
                frame = frames[cfg.camera]
                if cfg.interactive:
                    from lerobot_condground.labelling.prompt_tracker import annotate_interactively

                    object_prompt, receptacle_prompt = annotate_interactively(frame)
                else:
                    object_prompt, receptacle_prompt = cfg.object, cfg.receptacle
                result = self._prompts.start(frame, object_prompt, receptacle_prompt)
                self._prompt_crops = {
                    "prompt_object": result.object_crop,
                    "prompt_receptacle": result.receptacle_crop,
                }
            crops = self._prompt_crops
        return {key: crops[key].copy() for key in PROMPT_KEYS}

    def new_episode(self) -> None:
        """An episode starts: the twin lays out a fresh scene (if the last one was used) and the prompts are
        annotated again on the next frame. LeRobot's recording loops trigger this by themselves."""
        if self.config.backend == "sim":
            self.arm.new_episode()
        self._prompt_crops = None

    # ------------------------------------------------------------------ I/O
    def _require_connected(self) -> None:
        if not self.is_connected:
            raise RuntimeError(f"{self} is not connected; call connect() first")

    def get_observation(self) -> dict:
        self._require_connected()
        episode = recording_episode()
        if episode is not None and episode != self._episode:
            self._episode = episode
            self.new_episode()
        state = self.arm.state()
        q = state.q + self.offsets
        obs = {name: float(v) for name, v in zip(MOTOR_NAMES, [*q, state.gripper], strict=True)}
        frames = {name: cam.async_read() for name, cam in self.cameras.items()}
        obs |= frames
        if self.config.prompts.segmenter:
            obs |= self._prompt_observation(frames)
        return obs

    def send_action(self, action: dict) -> dict:
        self._require_connected()
        missing = [k for k in MOTOR_NAMES if k not in action]
        extra = [k for k in action if k not in MOTOR_NAMES]
        if missing or extra:
            raise ValueError(
                f"A ur3e action needs exactly the keys {list(MOTOR_NAMES)}; missing {missing}, unknown {extra}. "
                "Nothing was sent to the arm."
            )
        # numpy would read "0.5" or a one-element list as a number: a value of another type is a bug upstream.
        odd = {k: type(v).__name__ for k, v in action.items() if not _is_real(v)}
        if odd:
            raise ValueError(
                f"A ur3e action value is one real number per key; got {odd}. Nothing was sent to the arm."
            )
        a = self.safety.check_action([action[k] for k in MOTOR_NAMES])
        state = self.arm.state()
        gripper = float(np.clip(a[6], 0.0, 1.0))
        if state.freedrive:
            q = state.q  # the hand moves the arm; only the gripper follows commands
            self.arm.command(None, gripper)
        else:
            previous = self._target if (state.streaming and self._target is not None) else state.q
            q = self.safety.clip(a[:6] - self.offsets, previous)
            self.arm.command(q, gripper)
            self._target = q
        return {name: float(v) for name, v in zip(MOTOR_NAMES, [*(q + self.offsets), gripper], strict=True)}
