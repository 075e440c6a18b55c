"""What every task env of the workcell shares: the arm's action, its read-outs, and rendering.

A task env builds its MuJoCo model (`workcell_spec` plus its own bodies), calls `_bind(model)`, and
maps geoms to its segmentation labels in `geom_label`.
"""

from __future__ import annotations

import os

import gymnasium as gym
import mujoco
import numpy as np

from lerobot_condground.core.codec import check_camera_codec, video_roundtrip
from lerobot_condground.core.ur3e import MAX_JOINT_VELOCITY, check_servo, servo_setpoint

from . import robot
from .scene import MAX_RENDER_HEIGHT, MAX_RENDER_WIDTH, PHYSICS_DT

SERVO_MAX_STEP = MAX_JOINT_VELOCITY * PHYSICS_DT

MIN_RENDER_SIDE = 64
# "agent_pos" renders nothing: for expert checks and physics benchmarks. "state" is its name in LeRobot's
# env tests and gym-pusht.
OBS_TYPES = ("pixels_agent_pos", "pixels", "agent_pos", "state")


def check_obs_type(obs_type: str) -> str:
    """The observation type, LeRobot's `state` spelled as this env's `agent_pos`."""
    if obs_type not in OBS_TYPES:
        raise ValueError(f"Unknown obs_type {obs_type!r}; allowed: {', '.join(OBS_TYPES)}")
    return "agent_pos" if obs_type == "state" else obs_type


def check_resolution(height: int, width: int) -> None:
    for name, value, limit in (("height", height, MAX_RENDER_HEIGHT), ("width", width, MAX_RENDER_WIDTH)):
        if isinstance(value, bool) or not isinstance(value, int) or not MIN_RENDER_SIDE <= value <= limit:
            raise ValueError(
                f"Image {name} {value!r} cannot be rendered; allowed: integers {MIN_RENDER_SIDE}..{limit} "
                f"(up to {MAX_RENDER_HEIGHT}x{MAX_RENDER_WIDTH})"
            )


def check_fps(fps: int) -> None:
    if (
        not isinstance(fps, int)
        or not 1 <= fps <= 100
        or round(1 / (fps * PHYSICS_DT)) * fps * PHYSICS_DT != 1
    ):
        raise ValueError(f"Control rate fps={fps!r} is not allowed; allowed: divisors of 500 from 5 to 100")


class ArmEnv(gym.Env):
    """Action: 6 joint position targets (rad) + gripper command (0 open .. 1 closed)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def _setup(
        self,
        obs_type: str,
        height: int,
        width: int,
        render_mode: str | None,
        fps: int,
        servo: str,
        camera_codec: str = "none",
    ) -> None:
        """Checks and keeps the settings every task has; called first in a task's `__init__`."""
        check_resolution(height, width)
        check_fps(fps)
        check_servo(servo)
        check_camera_codec(camera_codec, "camera_codec", height, width)
        self.servo, self.camera_codec = servo, camera_codec
        obs_type = check_obs_type(obs_type)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"Unknown render_mode {render_mode!r}; allowed: rgb_array or None")
        self.obs_type, self.height, self.width = obs_type, height, width
        self.render_mode, self.fps = render_mode, fps
        self.n_substeps = round(1 / (fps * PHYSICS_DT))
        self.metadata = {**self.metadata, "render_fps": fps}
        low = np.concatenate([robot.JOINT_RANGE[:, 0], [0.0]]).astype(np.float32)
        high = np.concatenate([robot.JOINT_RANGE[:, 1], [1.0]]).astype(np.float32)
        self.action_space = gym.spaces.Box(low, high, dtype=np.float32)
        self.model: mujoco.MjModel | None = None
        self.data: mujoco.MjData | None = None
        self.geom_label = np.zeros(0, dtype=np.int32)
        self._renderer: mujoco.Renderer | None = None
        self._last_frame: np.ndarray | None = None

    def _arm_spaces(self) -> dict[str, gym.Space]:
        """Observation spaces of the cameras (`top`, and `wrist` if `self.wrist_camera`) and the state."""
        spaces: dict[str, gym.Space] = {}
        if self.obs_type != "agent_pos":
            image = gym.spaces.Box(0, 255, (self.height, self.width, 3), dtype=np.uint8)
            spaces["pixels"] = gym.spaces.Dict(
                {"top": image, **({"wrist": image} if self.wrist_camera else {})}
            )
        if self.obs_type != "pixels":
            spaces["agent_pos"] = gym.spaces.Box(-np.inf, np.inf, (7,), dtype=np.float64)
        return spaces

    def _arm_observation(self) -> dict:
        """The camera frames and `agent_pos` (6 joint positions + gripper closure)."""
        obs: dict = {}
        self._last_frame = None
        if self.obs_type != "agent_pos":
            obs["pixels"] = {"top": self._render_rgb("top")}
            if self.wrist_camera:
                obs["pixels"]["wrist"] = self._render_rgb("wrist")
            if self.camera_codec == "video":
                # Each frame as its own stream: a rollout's frames arrive one at a time.
                obs["pixels"] = {
                    name: video_roundtrip(frame[None], self.fps)[0] for name, frame in obs["pixels"].items()
                }
            self._last_frame = obs["pixels"]["top"]
        if self.obs_type != "pixels":
            obs["agent_pos"] = np.concatenate([self.joint_positions(), [self.gripper_closure()]])
        return obs

    def _bind(self, model: mujoco.MjModel) -> None:
        """Makes `model` the env's (a new one closes the renderer of the old)."""
        self.close()
        self.model = model
        self.data = mujoco.MjData(model)
        self._arm_qadr = np.array([model.joint(n).qposadr[0] for n in robot.JOINT_NAMES])
        self._finger_qadr = model.joint("left_finger").qposadr[0]

    def _actuate(self, action) -> None:
        """Checks the action (joint targets are clipped to the joint ranges) and runs one control period of
        physics toward it, the servos fed as `self.servo` says."""
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (7,) or not np.all(np.isfinite(action)):
            raise ValueError(
                f"Action must be 7 finite numbers (6 joint targets in rad + gripper 0..1); got shape "
                f"{action.shape} with values {np.array2string(action, precision=3)}"
            )
        action = np.clip(action, self.action_space.low, self.action_space.high)
        self.data.ctrl[6] = action[6] * robot.FINGER_TRAVEL
        if self.servo == "direct":
            self.data.ctrl[:6] = action[:6]
            mujoco.mj_step(self.model, self.data, nstep=self.n_substeps)
            return
        start, low, high = self.data.ctrl[:6].copy(), robot.JOINT_RANGE[:, 0], robot.JOINT_RANGE[:, 1]
        for k in range(1, self.n_substeps + 1):  # one set point per physics step: the servo rate is 500 Hz
            self.data.ctrl[:6] = servo_setpoint(
                self.data.ctrl[:6], start, action[:6], k / self.n_substeps, SERVO_MAX_STEP, low, high
            )
            mujoco.mj_step(self.model, self.data)

    def render(self):
        if self._last_frame is None:
            self._last_frame = self._render_rgb("top")
        return self._last_frame

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def joint_positions(self) -> np.ndarray:
        return self.data.qpos[self._arm_qadr].copy()

    def gripper_closure(self) -> float:
        return float(self.data.qpos[self._finger_qadr] / robot.FINGER_TRAVEL)

    def tcp_pose(self) -> tuple[np.ndarray, np.ndarray]:
        sid = self.model.site("tcp").id
        return self.data.site_xpos[sid].copy(), self.data.site_xmat[sid].reshape(3, 3).copy()

    def render_segmentation(
        self, camera: str = "top", scene_option: mujoco.MjvOption | None = None
    ) -> np.ndarray:
        """Labels per pixel (uint8, `geom_label` of each geom), from MuJoCo's segmentation rendering."""
        r = self._get_renderer()
        r.enable_segmentation_rendering()
        try:
            r.update_scene(self.data, camera=camera, scene_option=scene_option)
            seg = r.render()
        finally:
            r.disable_segmentation_rendering()
        ids, types = seg[..., 0], seg[..., 1]
        labels = np.zeros(ids.shape, dtype=np.uint8)
        is_geom = (types == int(mujoco.mjtObj.mjOBJ_GEOM)) & (ids >= 0)
        labels[is_geom] = self.geom_label[ids[is_geom]]
        return labels

    def _get_renderer(self) -> mujoco.Renderer:
        if self._renderer is None:
            os.environ.setdefault("MUJOCO_GL", "egl")
            self._renderer = mujoco.Renderer(self.model, self.height, self.width)
        return self._renderer

    def _render_rgb(self, camera: str, scene_option: mujoco.MjvOption | None = None) -> np.ndarray:
        r = self._get_renderer()
        r.update_scene(self.data, camera=camera, scene_option=scene_option)
        return r.render()
