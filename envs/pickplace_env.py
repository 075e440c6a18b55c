"""The pick-and-place gym environment with controlled look-alike competitors.

Action: 6 joint position targets (rad) + gripper command (0 open .. 1 closed).
Observation: `pixels` (scene camera `top`, optional `wrist`), `agent_pos` = 6 measured joint positions
+ measured gripper closure (0 open .. 1 closed); optionally `segmentation` (entity labels of the top
camera: 0 background and robot, 1 target object, 2 target receptacle, 3.. competitors) and the
positionless prompt crops `prompt_object`, `prompt_receptacle`.
Reward: the stage index reached so far (0 none, 1 pick, 2 lift, 3 place); `info["is_success"]` = place.
"""

from __future__ import annotations

import logging
import os

import gymnasium as gym
import mujoco
import numpy as np

from lerobot_condground.core.conditions import ConditionSpec, check_task
from lerobot_condground.core.labels import PROMPT_SIZE, crop_entity

from . import robot
from .layout import Layout, check_fits, sample_layout
from .scene import (
    MAX_RENDER_HEIGHT,
    MAX_RENDER_WIDTH,
    PHYSICS_DT,
    apply_layout,
    build_model,
    entity_body_name,
)
from .stages import StageTracker

logger = logging.getLogger(__name__)

DEFAULT_FPS = 20
MIN_RENDER_SIDE = 64
_DIVERGENCE_WARNINGS = (
    mujoco.mjtWarning.mjWARN_BADQPOS,
    mujoco.mjtWarning.mjWARN_BADQVEL,
    mujoco.mjtWarning.mjWARN_BADQACC,
)
# "agent_pos" renders nothing: for expert checks and physics benchmarks.
OBS_TYPES = ("pixels_agent_pos", "pixels", "agent_pos")


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


class PickPlaceEnv(gym.Env):
    metadata = {"render_modes": ["rgb_array"], "render_fps": DEFAULT_FPS}

    def __init__(
        self,
        task: str = "PickPlaceRandomBin-v0",
        condition: str | ConditionSpec = "clean",
        counterbalanced: bool = False,
        obs_type: str = "pixels_agent_pos",
        observation_height: int = 240,
        observation_width: int = 320,
        wrist_camera: bool = False,
        segmentation: bool = False,
        prompts: bool = False,
        render_mode: str | None = "rgb_array",
        fps: int = DEFAULT_FPS,
    ):
        check_task(task)
        self.condition = ConditionSpec.parse(condition)
        check_resolution(observation_height, observation_width)
        if obs_type not in OBS_TYPES:
            raise ValueError(f"Unknown obs_type {obs_type!r}; allowed: {', '.join(OBS_TYPES)}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"Unknown render_mode {render_mode!r}; allowed: rgb_array or None")
        check_fps(fps)
        check_fits(task, self.condition, counterbalanced)
        self.task = task
        self.counterbalanced = counterbalanced
        self.obs_type = obs_type
        self.height, self.width = observation_height, observation_width
        self.wrist_camera = wrist_camera
        self.segmentation = segmentation
        self.prompts = prompts
        self.render_mode = render_mode
        self.fps = fps
        self.n_substeps = round(1 / (fps * PHYSICS_DT))
        self.metadata = {**self.metadata, "render_fps": fps}

        low = np.concatenate([robot.JOINT_RANGE[:, 0], [0.0]]).astype(np.float32)
        high = np.concatenate([robot.JOINT_RANGE[:, 1], [1.0]]).astype(np.float32)
        self.action_space = gym.spaces.Box(low, high, dtype=np.float32)
        image = gym.spaces.Box(0, 255, (self.height, self.width, 3), dtype=np.uint8)
        cams = {"top": image, **({"wrist": image} if wrist_camera else {})}
        spaces: dict[str, gym.Space] = {"pixels": gym.spaces.Dict(cams)} if obs_type != "agent_pos" else {}
        if obs_type != "pixels":
            spaces["agent_pos"] = gym.spaces.Box(-np.inf, np.inf, (7,), dtype=np.float64)
        if segmentation:
            spaces["segmentation"] = gym.spaces.Box(0, 255, (self.height, self.width), dtype=np.uint8)
        if prompts:
            crop = gym.spaces.Box(0, 255, (PROMPT_SIZE, PROMPT_SIZE, 3), dtype=np.uint8)
            spaces["prompt_object"] = crop
            spaces["prompt_receptacle"] = crop
        self.observation_space = gym.spaces.Dict(spaces)

        self.model: mujoco.MjModel | None = None
        self.data: mujoco.MjData | None = None
        self.layout: Layout | None = None
        self._asset_key = None
        self._renderer: mujoco.Renderer | None = None
        self._prompt_crops: dict[str, np.ndarray] = {}
        self._last_frame: np.ndarray | None = None
        # A first layout so that attributes read before reset (task_description) are meaningful.
        self._load_layout(sample_layout(task, self.condition, counterbalanced, 0))

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        layout_seed = int(self.np_random.integers(2**31 - 1))
        self._load_layout(sample_layout(self.task, self.condition, self.counterbalanced, layout_seed))
        mujoco.mj_resetData(self.model, self.data)
        apply_layout(self.model, self.data, self.layout)
        self.data.qpos[self._arm_qadr] = robot.HOME_QPOS
        self.data.ctrl[:6] = robot.HOME_QPOS
        self.data.ctrl[6] = 0.0
        mujoco.mj_forward(self.model, self.data)
        # Let objects settle on the table before the first observation.
        mujoco.mj_step(self.model, self.data, nstep=50)
        self.tracker.reset()
        self.tracker.update(self.data)
        self._prompt_crops = self._render_prompt_crops() if self.prompts else {}
        return self._observation(), self._info()

    def step(self, action):
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (7,) or not np.all(np.isfinite(action)):
            raise ValueError(
                f"Action must be 7 finite numbers (6 joint targets in rad + gripper 0..1); got shape "
                f"{action.shape} with values {np.array2string(action, precision=3)}"
            )
        action = np.clip(action, self.action_space.low, self.action_space.high)
        self.data.ctrl[:6] = action[:6]
        self.data.ctrl[6] = action[6] * robot.FINGER_TRAVEL
        resets_before = self._divergence_resets()
        mujoco.mj_step(self.model, self.data, nstep=self.n_substeps)
        # MuJoCo answers a diverging simulation by resetting the state in place; the episode cannot go
        # on from there, so it is truncated and flagged instead of continuing from a teleported scene.
        unstable = self._divergence_resets() > resets_before
        if unstable:
            logger.warning(
                "Physics diverged at t=%.2f s (%s, %s); truncating the episode",
                self.data.time,
                self.task,
                self.condition.name,
            )
        self.tracker.update(self.data)
        terminated = self.tracker.place
        return self._observation(), float(self.tracker.stage), terminated, unstable, self._info(unstable)

    def render(self):
        if self._last_frame is None:
            self._last_frame = self._render_rgb("top")
        return self._last_frame

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    # ------------------------------------------------------------------ read-outs
    @property
    def task_description(self) -> str:
        return self.layout.task_description()

    def joint_positions(self) -> np.ndarray:
        return self.data.qpos[self._arm_qadr].copy()

    def gripper_closure(self) -> float:
        return float(self.data.qpos[self._finger_qadr] / robot.FINGER_TRAVEL)

    def tcp_pose(self) -> tuple[np.ndarray, np.ndarray]:
        sid = self.model.site("tcp").id
        return self.data.site_xpos[sid].copy(), self.data.site_xmat[sid].reshape(3, 3).copy()

    def entity_pose(self, label: int) -> tuple[np.ndarray, np.ndarray]:
        body = self.model.body(entity_body_name(label)).id
        return self.data.xpos[body].copy(), self.data.xquat[body].copy()

    def entity_table(self) -> list[dict]:
        return [
            {
                "label": e.label,
                "role": e.asset.role,
                "match": e.match,
                "shape": e.asset.shape,
                "color": e.asset.color,
            }
            for e in self.layout.entities
        ]

    def swap_prompt(self, role: str, label: int) -> np.ndarray:
        """Make the `role` prompt (object or receptacle) show entity `label` instead of the target, until
        the next reset: the prompt-swap probe's intervention. The crop is rendered like the target's and
        returned, for the observation already handed out."""
        if role not in ("object", "receptacle"):
            raise ValueError(f"Unknown prompt role {role!r}; allowed: object, receptacle")
        entity = next((e for e in self.layout.entities if e.label == label), None)
        if entity is None or entity.asset.role != role:
            allowed = [e.label for e in self.layout.entities if e.asset.role == role]
            raise ValueError(f"Entity {label!r} is not a {role} of this scene; {role} labels here: {allowed}")
        rgb, labels = self._unoccluded_view()
        crop = self._prompt_crops[f"prompt_{role}"] = crop_entity(rgb, labels == label)
        return crop.copy()

    def render_segmentation(
        self, camera: str = "top", scene_option: mujoco.MjvOption | None = None
    ) -> np.ndarray:
        """Entity labels per pixel (uint8), from MuJoCo's segmentation rendering."""
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
        labels[is_geom] = self.tracker.geom_label[ids[is_geom]]
        return labels

    # ------------------------------------------------------------------ internals
    def _load_layout(self, layout: Layout) -> None:
        if layout.asset_key != self._asset_key:
            if self._renderer is not None:
                self._renderer.close()
                self._renderer = None
            self.model = build_model(layout)
            self.data = mujoco.MjData(self.model)
            self._asset_key = layout.asset_key
            self._arm_qadr = np.array([self.model.joint(n).qposadr[0] for n in robot.JOINT_NAMES])
            self._finger_qadr = self.model.joint("left_finger").qposadr[0]
        self.layout = layout
        self.tracker = StageTracker(self.model, layout)

    def _get_renderer(self) -> mujoco.Renderer:
        if self._renderer is None:
            os.environ.setdefault("MUJOCO_GL", "egl")
            self._renderer = mujoco.Renderer(self.model, self.height, self.width)
        return self._renderer

    def _render_rgb(self, camera: str, scene_option: mujoco.MjvOption | None = None) -> np.ndarray:
        r = self._get_renderer()
        r.update_scene(self.data, camera=camera, scene_option=scene_option)
        return r.render()

    def _observation(self) -> dict:
        obs: dict = {}
        self._last_frame = None
        if self.obs_type != "agent_pos":
            self._last_frame = self._render_rgb("top")
            obs["pixels"] = {"top": self._last_frame}
            if self.wrist_camera:
                obs["pixels"]["wrist"] = self._render_rgb("wrist")
        if self.obs_type != "pixels":
            obs["agent_pos"] = np.concatenate([self.joint_positions(), [self.gripper_closure()]])
        if self.segmentation:
            obs["segmentation"] = self.render_segmentation()
        if self.prompts:
            obs.update({key: crop.copy() for key, crop in self._prompt_crops.items()})
        return obs

    def _divergence_resets(self) -> int:
        return sum(self.data.warning[w].number for w in _DIVERGENCE_WARNINGS)

    def _info(self, physics_unstable: bool = False) -> dict:
        return {**self.tracker.info(self.data), "physics_unstable": physics_unstable}

    def _unoccluded_view(self) -> tuple[np.ndarray, np.ndarray]:
        """RGB and entity labels of the scene camera with the robot hidden."""
        option = mujoco.MjvOption()
        option.geomgroup[robot.ARM_GROUP] = 0
        option.geomgroup[robot.GRIPPER_GROUP] = 0
        return self._render_rgb("top", option), self.render_segmentation("top", option)

    def _render_prompt_crops(self) -> dict[str, np.ndarray]:
        """Positionless appearance crops of the two targets, rendered with the robot hidden so they are
        never occluded: a square box around the entity's mask, resized to PROMPT_SIZE."""
        rgb, labels = self._unoccluded_view()
        return {
            "prompt_object": crop_entity(rgb, labels == 1),
            "prompt_receptacle": crop_entity(rgb, labels == 2),
        }
