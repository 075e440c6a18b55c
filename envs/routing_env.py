"""`InstrumentRouting-v0`: a seven-step instrument-handling procedure whose destination depends on the
instrument's visible state (the paper's VLA case study, in simulation).

Procedure steps (`observation.phase` of a recording): 0 approach, 1 pick, 2 inspect, 3 route, 4 place,
5 retreat, 6 home. Five subgoals are evaluated, each from its own initial state:

| subgoal | starts from | succeeds when |
| --- | --- | --- |
| pick | the home pose | the instrument is held, its bottom 4 cm above the table |
| inspect | the instrument held above where it lay | it is held within 3 cm of the inspection point for 0.5 s |
| route | the instrument held at the inspection point | it is held above the correct container, over its rim |
| place | the instrument held above the containers' midpoint | it rests in the correct container, let go |
| home | the instrument in the correct container, the open gripper above it | the arm is home, gripper open |

`route` and `place` are the routing subgoals: their start says nothing about the destination, only the
instrument's mark does. `subgoal="procedure"` runs the whole procedure from the home pose (success: every
subgoal in order); a comma-separated list draws one entry per episode from the episode's seed.

Observation: `pixels` (`top`, and `wrist` unless turned off), `agent_pos` (6 joints + gripper closure);
optionally `segmentation` / `segmentation_wrist` (labels of `core/routing.py`) and `destination`
(0 left, 1 right: what the explicit instruction names). `cue=True` sends the segmentations for the
`condground_rgb_cue` step to highlight the destination, `cue=False` sends them empty (evaluated without
the cue). `task_description` is the instruction of the subgoal in progress, in the form `instruction`
(generic or explicit).
Reward: 1 on the step the episode's goal is reached. An instrument let go in the wrong container ends the
episode (`terminated`, not a success).
"""

from __future__ import annotations

import math

import gymnasium as gym
import mujoco
import numpy as np

from lerobot_condground.core.conditions import ROUTING_TASK
from lerobot_condground.core.routing import (
    INSTRUCTION_FORMS,
    SIDES,
    SUBGOALS,
    instruction,
    parse_episodes,
)

from . import robot
from .arm_env import ArmEnv
from .assets import RECEPTACLE_SHAPES
from .routing_scene import (
    CONTAINER,
    GRASP_WIDTH,
    HANDLE_HALF,
    INSPECT_POINT,
    SORT_HEIGHT,
    apply_routing_layout,
    build_routing_model,
    geom_labels,
    sample_routing_layout,
)
from .scene import FLOOR_THICKNESS, inside_receptacle

LIFT_HEIGHT = 0.04
INSPECT_TOLERANCE, INSPECT_HOLD_S = 0.03, 0.5
HOME_TOLERANCE = 0.1  # rad, every joint
# Gripper closure below which the jaw is open wider than the handle (holding it closes to 0.69).
OPEN_CLOSURE = 0.6
REST_SPEED = 0.03  # m/s


class RoutingTracker:
    """Which subgoals the episode reached, in order from where it started, read off contacts and poses."""

    def __init__(self, env: InstrumentRoutingEnv, start: str):
        self.env = env
        first = SUBGOALS.index("pick" if start == "procedure" else start)
        self.order = SUBGOALS[first:] if start == "procedure" else (start,)
        self.reset()

    def reset(self) -> None:
        self.reached: list[str] = []
        self.route_choice = "none"  # the first container the held instrument was carried over
        self.placed_in = "none"  # where the instrument came to rest after being let go
        self.inspect_steps = 0
        self.held = False

    @property
    def current(self) -> str | None:
        return self.order[len(self.reached)] if len(self.reached) < len(self.order) else None

    @property
    def success(self) -> bool:
        return self.current is None

    @property
    def misrouted(self) -> bool:
        return self.placed_in not in ("none", "elsewhere", self.env.layout.destination)

    def update(self) -> None:
        env, data = self.env, self.env.data
        touching = env.finger_contacts()
        self.held = touching == {1, 2}
        center = env.instrument_pose()[0]
        bottom = center[2] - HANDLE_HALF[2]
        over = self._container_under(center, bottom) if self.held else None
        if over and self.route_choice == "none":
            self.route_choice = over
        speed = float(np.linalg.norm(data.cvel[env.instrument_body][3:]))
        if not touching and speed < REST_SPEED:
            resting = self._container_holding(center)
            if resting or bottom < 0.01:  # in a container, or lying on the table
                self.placed_in = resting or "elsewhere"
        near_inspect = self.held and np.linalg.norm(center - INSPECT_POINT) < INSPECT_TOLERANCE
        self.inspect_steps = self.inspect_steps + 1 if near_inspect else 0
        goal = self.current
        if goal is None:
            return
        destination = env.layout.destination
        done = {
            "pick": self.held and bottom > LIFT_HEIGHT,
            "inspect": self.inspect_steps >= math.ceil(INSPECT_HOLD_S * env.fps),
            "route": over == destination,
            "place": self.placed_in == destination,
            "home": not touching
            and env.gripper_closure() < OPEN_CLOSURE
            and bool(np.all(np.abs(env.joint_positions() - robot.HOME_QPOS) < HOME_TOLERANCE)),
        }[goal]
        if done:
            self.reached.append(goal)

    def _local(self, side: str, xy: np.ndarray) -> np.ndarray:
        return np.asarray(xy[:2]) - np.array(self.env.layout.containers[side])

    def _container_under(self, center: np.ndarray, bottom: float) -> str | None:
        rim = FLOOR_THICKNESS + RECEPTACLE_SHAPES[CONTAINER.shape].wall_height
        for side in SIDES:
            if bottom > rim and inside_receptacle(CONTAINER.shape, self._local(side, center), margin=0.02):
                return side
        return None

    def _container_holding(self, center: np.ndarray) -> str | None:
        rim = FLOOR_THICKNESS + RECEPTACLE_SHAPES[CONTAINER.shape].wall_height
        for side in SIDES:
            if center[2] < rim + HANDLE_HALF[2] and inside_receptacle(
                CONTAINER.shape, self._local(side, center)
            ):
                return side
        return None

    def info(self) -> dict:
        layout = self.env.layout
        return {
            "is_success": self.success,
            "subgoal": self.env.episode,
            "reached": ",".join(self.reached),
            "stage": len(self.reached),
            **{name: name in self.reached for name in SUBGOALS},
            "contaminated": layout.contaminated,
            "destination": layout.destination,
            "route_choice": self.route_choice,
            "placed_in": self.placed_in,
        }


class InstrumentRoutingEnv(ArmEnv):
    def __init__(
        self,
        subgoal: str = "procedure",
        obs_type: str = "pixels_agent_pos",
        observation_height: int = 240,
        observation_width: int = 320,
        wrist_camera: bool = True,
        segmentation: bool = False,
        destination: bool = False,
        cue: bool | None = None,
        instruction: str = "generic",
        render_mode: str | None = "rgb_array",
        fps: int = 20,
        servo: str = "interpolated",
        camera_codec: str = "none",
    ):
        self.task = ROUTING_TASK  # LeRobot's eval asks sub-envs for it
        self.episodes = parse_episodes(subgoal)
        self._setup(obs_type, observation_height, observation_width, render_mode, fps, servo, camera_codec)
        if instruction not in INSTRUCTION_FORMS:
            raise ValueError(
                f"Unknown instruction form {instruction!r}; allowed: {', '.join(INSTRUCTION_FORMS)}"
            )
        if segmentation and cue is False:
            raise ValueError(
                "segmentation=True and cue=False contradict each other: cue=False sends empty label maps"
            )
        self.wrist_camera, self.with_destination = wrist_camera, destination
        self.segmentation = segmentation or cue is not None
        self.blank_labels = cue is False
        self.instruction_form = instruction

        labels = gym.spaces.Box(0, 255, (self.height, self.width), dtype=np.uint8)
        spaces = self._arm_spaces()
        if self.segmentation:
            spaces["segmentation"] = labels
            if wrist_camera:
                spaces["segmentation_wrist"] = labels
        if destination:
            spaces["destination"] = gym.spaces.Box(0, 1, (1,), dtype=np.int64)
        self.observation_space = gym.spaces.Dict(spaces)

        self._bind(build_routing_model())
        self._finger_qadrs = [self.model.joint(f"{s}_finger").qposadr[0] for s in ("left", "right")]
        self._instrument_qadr = self.model.joint("instrument_free").qposadr[0]
        self._instrument_dofadr = self.model.joint("instrument_free").dofadr[0]
        self.instrument_body = self.model.body("instrument").id
        self._finger_of_geom = np.zeros(self.model.ngeom, dtype=np.int8)
        for code, side in ((1, "left_finger"), (2, "right_finger")):
            bid = self.model.body(side).id
            adr = self.model.body_geomadr[bid]
            self._finger_of_geom[adr : adr + self.model.body_geomnum[bid]] = code
        self._ik = robot.InverseKinematics(self.model)
        self.episode = self.episodes[0]
        self.layout = sample_routing_layout(0)
        self.geom_label = geom_labels(self.model, self.layout)
        self.tracker = RoutingTracker(self, self.episode)

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        layout_seed = int(self.np_random.integers(2**31 - 1))
        self.episode = self.episodes[int(self.np_random.integers(len(self.episodes)))]
        self.layout = sample_routing_layout(layout_seed)
        self.geom_label = geom_labels(self.model, self.layout)
        mujoco.mj_resetData(self.model, self.data)
        apply_routing_layout(self.model, self.data, self.layout)
        self._set_start(self.episode)
        self.tracker = RoutingTracker(self, self.episode)
        self.tracker.update()
        return self._observation(), self._info()

    def step(self, action):
        self._actuate(action)
        self.tracker.update()
        success = self.tracker.success
        terminated = success or self.tracker.misrouted
        return self._observation(), float(success), terminated, False, self._info()

    # ------------------------------------------------------------------ read-outs
    @property
    def subgoal(self) -> str:
        """The subgoal in progress (the episode's last one once it succeeded)."""
        return self.tracker.current or self.tracker.order[-1]

    @property
    def task_description(self) -> str:
        return instruction(self.subgoal, self.instruction_form, self.layout.destination)

    def explicit_instruction(self) -> str:
        return instruction(self.subgoal, "explicit", self.layout.destination)

    def entity_table(self) -> list[dict]:
        """What each segmentation label is in this episode (the recording's provenance)."""
        layout = self.layout
        return [
            {"label": 1, "role": "instrument", "contaminated": layout.contaminated,
             "xy": list(layout.instrument_xy), "yaw": layout.instrument_yaw},
            {"label": 2, "role": "destination", "side": layout.destination, "xy": list(layout.containers[layout.destination])},
            {"label": 3, "role": "other_container", "side": layout.other, "xy": list(layout.containers[layout.other])},
            {"label": 4, "role": "state_region"},
        ]  # fmt: skip

    def instrument_pose(self) -> tuple[np.ndarray, float]:
        """Centre of the handle and the instrument's yaw."""
        quat = self.data.xquat[self.instrument_body]
        return self.data.xpos[self.instrument_body].copy(), 2 * math.atan2(quat[3], quat[0])

    def finger_contacts(self) -> set[int]:
        """Which fingers (1 left, 2 right) touch the instrument."""
        n = self.data.ncon
        g1, g2 = self.data.contact.geom1[:n], self.data.contact.geom2[:n]
        label = self.geom_label
        fingers = np.concatenate(
            [self._finger_of_geom[g1][label[g2] == 1], self._finger_of_geom[g2][label[g1] == 1]]
        )
        return set(fingers[fingers > 0].tolist())

    def grasp_yaw(self, instrument_yaw: float, near: float) -> float:
        """Tool yaw that closes the jaw across the handle, of the two (half a turn apart) the nearer `near`."""
        base = instrument_yaw + math.pi / 2
        return base + math.pi * round((near - base) / math.pi)

    def render_segmentation(self, camera: str = "top", scene_option=None) -> np.ndarray:
        if self.blank_labels:  # evaluated without the cue: nothing marked
            return np.zeros((self.height, self.width), dtype=np.uint8)
        return super().render_segmentation(camera, scene_option)

    # ------------------------------------------------------------------ internals
    def _set_start(self, episode: str) -> None:
        """Puts arm, gripper and instrument where the episode's first subgoal begins."""
        home_pos, home_yaw = self._ik.forward(robot.HOME_QPOS)
        layout = self.layout
        if episode in ("procedure", "pick"):
            self._place_arm(robot.HOME_QPOS, grip=0.0)
            mujoco.mj_step(self.model, self.data, nstep=50)  # the instrument settles on the table
            return
        yaw = self.grasp_yaw(layout.instrument_yaw, home_yaw)
        if episode == "home":
            destination = np.array(layout.containers[layout.destination])
            self._place_instrument([*destination, FLOOR_THICKNESS + HANDLE_HALF[2] + 1e-3], yaw - math.pi / 2)
            self._place_arm(self._ik_at([*destination, SORT_HEIGHT], yaw), grip=0.0)
            mujoco.mj_step(self.model, self.data, nstep=50)
            return
        tool = {
            "inspect": np.array([*layout.instrument_xy, SORT_HEIGHT]),
            "route": INSPECT_POINT,
            "place": layout.sort_point,
        }[episode]
        self._place_arm(self._ik_at(tool, yaw), grip=1.0)
        mujoco.mj_forward(self.model, self.data)
        tcp = self.tcp_pose()[0]
        self._place_instrument(tcp - [0, 0, 0.002], yaw - math.pi / 2)
        # Close the jaw on the handle with gravity off, so the instrument is held before it can fall.
        gravity = self.model.opt.gravity.copy()
        self.model.opt.gravity[:] = 0
        jaw = robot.FINGER_TRAVEL - 0.002 - GRASP_WIDTH / 2
        self.data.qpos[self._finger_qadrs] = jaw - 0.001
        mujoco.mj_step(self.model, self.data, nstep=100)
        self.model.opt.gravity[:] = gravity
        mujoco.mj_step(self.model, self.data, nstep=50)

    def _ik_at(self, pos, yaw: float) -> np.ndarray:
        return self._ik.solve_from(robot.HOME_QPOS, np.asarray(pos, dtype=float), yaw)

    def _place_arm(self, q: np.ndarray, grip: float) -> None:
        self.data.qpos[self._arm_qadr] = q
        self.data.ctrl[:6] = q
        self.data.ctrl[6] = grip * robot.FINGER_TRAVEL

    def _place_instrument(self, pos, yaw: float) -> None:
        adr, dof = self._instrument_qadr, self._instrument_dofadr
        self.data.qpos[adr : adr + 7] = [*pos, math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)]
        self.data.qvel[dof : dof + 6] = 0

    def _observation(self) -> dict:
        obs = self._arm_observation()
        if self.segmentation:
            obs["segmentation"] = self.render_segmentation("top")
            if self.wrist_camera:
                obs["segmentation_wrist"] = self.render_segmentation("wrist")
        if self.with_destination:
            obs["destination"] = np.array([SIDES.index(self.layout.destination)], dtype=np.int64)
        return obs

    def _info(self) -> dict:
        return self.tracker.info()
