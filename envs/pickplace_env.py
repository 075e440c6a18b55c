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

import gymnasium as gym
import mujoco
import numpy as np

from lerobot_condground.core.conditions import ConditionSpec, check_task
from lerobot_condground.core.labels import PROMPT_SIZE, crop_entity

from . import robot
from .arm_env import ArmEnv
from .layout import Layout, check_fits, sample_layout
from .scene import (
    apply_layout,
    build_model,
    entity_body_name,
)
from .stages import StageTracker

logger = logging.getLogger(__name__)

DEFAULT_FPS = 20
_DIVERGENCE_WARNINGS = (
    mujoco.mjtWarning.mjWARN_BADQPOS,
    mujoco.mjtWarning.mjWARN_BADQVEL,
    mujoco.mjtWarning.mjWARN_BADQACC,
)


class PickPlaceEnv(ArmEnv):
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
        servo: str = "interpolated",
        camera_codec: str = "none",
        competitor_pool: str = "eval",
    ):
        check_task(task)
        self.condition = ConditionSpec.parse(condition)
        self._setup(obs_type, observation_height, observation_width, render_mode, fps, servo, camera_codec)
        check_fits(task, self.condition, counterbalanced, competitor_pool=competitor_pool)
        self.task = task
        self.counterbalanced = counterbalanced
        self.competitor_pool = competitor_pool
        self.wrist_camera = wrist_camera
        self.segmentation = segmentation
        self.prompts = prompts
        spaces = self._arm_spaces()
        if segmentation:
            spaces["segmentation"] = gym.spaces.Box(0, 255, (self.height, self.width), dtype=np.uint8)
        if prompts:
            crop = gym.spaces.Box(0, 255, (PROMPT_SIZE, PROMPT_SIZE, 3), dtype=np.uint8)
            spaces["prompt_object"] = crop
            spaces["prompt_receptacle"] = crop
        self.observation_space = gym.spaces.Dict(spaces)

        self.layout: Layout | None = None
        self._asset_key = None
        self._prompt_crops: dict[str, np.ndarray] = {}
        # A first layout so that attributes read before reset (task_description) are meaningful.
        self._load_layout(sample_layout(task, self.condition, counterbalanced, 0, competitor_pool))

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        layout_seed = int(self.np_random.integers(2**31 - 1))
        self._load_layout(
            sample_layout(self.task, self.condition, self.counterbalanced, layout_seed, self.competitor_pool)
        )
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
        resets_before = self._divergence_resets()
        self._actuate(action)
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

    # ------------------------------------------------------------------ read-outs
    @property
    def task_description(self) -> str:
        return self.layout.task_description()

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

    # ------------------------------------------------------------------ internals
    def _load_layout(self, layout: Layout) -> None:
        if layout.asset_key != self._asset_key:
            self._bind(build_model(layout))
            self._asset_key = layout.asset_key
        self.layout = layout
        self.tracker = StageTracker(self.model, layout)
        self.geom_label = self.tracker.geom_label

    def _observation(self) -> dict:
        obs = self._arm_observation()
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
