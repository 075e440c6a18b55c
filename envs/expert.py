"""Scripted expert: reads privileged state, plans Cartesian waypoints, and tracks them with IK.

Phases: approach, descend, grasp, lift, transport, place, release, retreat. Phase label 0 (acquire
the object) covers approach..grasp; label 1 (transport and place) covers lift..retreat. A grasp that
does not hold the target is retried from the approach. `take_over` starts the expert from whatever state
a policy left the scene in (DAgger-style recovery data): the phase the world asks for next, planned from
the measured pose; `recover` (open the gripper while rising) comes first when the gripper is closed on
nothing or the tool is low away from the object.
"""

from __future__ import annotations

import math

import numpy as np

from . import robot
from .assets import FLOOR_THICKNESS, OBJECT_HEIGHT, OBJECT_SHAPES
from .layout import PREGRASP_MARGIN
from .robot import InverseKinematics

PHASES = (
    "recover",
    "approach",
    "descend",
    "grasp",
    "lift",
    "transport",
    "place",
    "release",
    "retreat",
    "done",
)
PHASE_LABEL = {p: (0 if p in ("recover", "approach", "descend", "grasp") else 1) for p in PHASES}
SPEED = 0.35  # m/s of the tool along a segment
YAW_SPEED = 2.5  # rad/s
JOINT_SPEED = 1.0  # rad/s of the joint that moves most, in joint-space moves
CARRY_HEIGHT = 0.13  # tool height while moving above the table
RELEASE_CLEARANCE = 0.022  # object bottom above the receptacle's floor when released
MAX_RETRIES = 2
# Taking over: the tool counts as above a point within this distance (m) in the plane, and as low below
# CARRY_HEIGHT by more than this.
TAKEOVER_NEAR = 0.015
TAKEOVER_LOW = 0.02


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def _arc_interpolate(p0: np.ndarray, p1: np.ndarray, s: float) -> np.ndarray:
    """Interpolates radius, azimuth and height about the base axis, so that moves across the table
    sweep around the robot instead of cutting through its base."""
    r0, r1 = math.hypot(p0[0], p0[1]), math.hypot(p1[0], p1[1])
    if min(r0, r1) < 1e-3 or np.allclose(p0[:2], p1[:2]):
        return p0 + s * (p1 - p0)
    a0 = math.atan2(p0[1], p0[0])
    a1 = a0 + _wrap(math.atan2(p1[1], p1[0]) - a0)
    r, a = r0 + s * (r1 - r0), a0 + s * (a1 - a0)
    return np.array([r * math.cos(a), r * math.sin(a), p0[2] + s * (p1[2] - p0[2])])


class WaypointExpert:
    """Drives the tool along smooth segments, one phase after another: Cartesian ones tracked with IK, or
    joint-space ones. Subclasses plan each phase (`_start`) and choose the next (`_advance`).
    Call `reset(env)` after each `env.reset()`, then `act()` once per step."""

    def __init__(self):
        self.env = None

    def reset(self, env) -> None:
        self.env = env.unwrapped  # what the initial grip depends on
        self._measure(env, self._initial_grip())
        self._start(self._first_phase())

    def _measure(self, env, grip: float) -> None:
        """Starts planning from the env's measured joints and tool pose."""
        self.env = env.unwrapped
        if getattr(self, "_model", None) is not self.env.model:
            self._model = self.env.model
            self.ik = InverseKinematics(self.env.model)
        self.q_cmd = self.env.joint_positions()
        pos, rot = self.env.tcp_pose()
        self.tool_pos = pos
        self.tool_yaw = math.atan2(rot[1, 0], rot[0, 0])
        self.grip = grip
        self.retries = 0

    def _initial_grip(self) -> float:
        return 0.0

    def _first_phase(self) -> str:
        raise NotImplementedError

    def _start(self, phase: str) -> None:
        raise NotImplementedError

    def _advance(self) -> None:
        raise NotImplementedError

    def _segment(self, goal, yaw, grip, speed=SPEED, min_steps=None):
        dt = 1.0 / self.env.fps
        dist = float(np.linalg.norm(np.asarray(goal) - self.tool_pos))
        dyaw = _wrap(yaw - self.tool_yaw)
        steps = max(int(math.ceil(max(dist / speed, abs(dyaw) / YAW_SPEED) / dt)), min_steps or 3)
        self.seg = (
            self.tool_pos.copy(),
            np.asarray(goal, dtype=float),
            self.tool_yaw,
            self.tool_yaw + dyaw,
            self.grip,
            grip,
            steps,
        )
        self.joint_goal = None

    def _joint_segment(self, q_goal: np.ndarray, grip: float, speed: float = JOINT_SPEED) -> None:
        """A move in joint space (to a joint pose rather than a tool pose), at `speed` rad/s on the joint
        that moves most."""
        dt = 1.0 / self.env.fps
        steps = max(int(math.ceil(float(np.max(np.abs(q_goal - self.q_cmd))) / speed / dt)), 3)
        self._segment(self.tool_pos, self.tool_yaw, grip, min_steps=steps)
        self.joint_goal = (self.q_cmd.copy(), np.asarray(q_goal, dtype=float))

    def act(self, obs=None) -> np.ndarray:
        p0, p1, y0, y1, g0, g1, steps = self.seg
        self.step_in_phase += 1
        a = min(self.step_in_phase / steps, 1.0)
        s = a * a * (3 - 2 * a)  # smoothstep: no velocity jumps between segments
        self.grip = g0 + a * (g1 - g0)
        if self.joint_goal is not None:
            q0, q1 = self.joint_goal
            self.q_cmd = q0 + s * (q1 - q0)
            self.tool_pos, self.tool_yaw = self.ik.forward(self.q_cmd)
        else:
            self.tool_pos = _arc_interpolate(p0, p1, s)
            self.tool_yaw = y0 + s * (y1 - y0)
            self.q_cmd = self.ik.solve(self.q_cmd, self.tool_pos, self.tool_yaw)
        action = np.concatenate([self.q_cmd, [self.grip]]).astype(np.float32)
        if self.step_in_phase >= steps:
            self._advance()
        return action


class ScriptedExpert(WaypointExpert):
    """Pick and place: the phases of PHASES, in order."""

    def _first_phase(self) -> str:
        return "approach"

    @property
    def phase_label(self) -> int:
        return PHASE_LABEL[self.phase]

    def take_over(self, env, grip: float) -> None:
        """Goes on from the state `env` is in now (another controller drove it there, its gripper command
        `grip`): the phase the world asks for next, planned from the measured pose."""
        self._measure(env, float(np.clip(grip, 0.0, 1.0)))
        obj_pos, obj_yaw = self._target()
        self.grasp_yaw = self._grasp_yaw(obj_yaw)
        low = self.tool_pos[2] < CARRY_HEIGHT - TAKEOVER_LOW
        if self.env.tracker.held == 1:
            rec = self.env.layout.target_receptacle
            above_rec = np.linalg.norm(self.tool_pos[:2] - np.asarray(rec.xy)) < TAKEOVER_NEAR
            self._start("place" if above_rec else "lift" if low else "transport")
        elif self.grip > self._open_grip() + 0.05 or self.env.tracker.held:
            self._start("recover")  # closed on nothing, or on another object
        elif low and np.linalg.norm(self.tool_pos[:2] - obj_pos[:2]) >= TAKEOVER_NEAR:
            self._start("recover")  # moving sideways this low would push what stands on the table
        elif low:
            self._start("descend")
        else:
            self._start("approach")

    def _open_grip(self) -> float:
        shape = OBJECT_SHAPES[self.env.layout.target_object.asset.shape]
        return max(0.0, 1.0 - (shape.grasp_width + PREGRASP_MARGIN) / robot.GRIPPER_STROKE)

    @property
    def done(self) -> bool:
        return self.phase == "done"

    @property
    def drift_gain(self) -> float:
        """How much of a recording's drift (`JointDrift`) the arm carries now. Full while it moves freely;
        fading to none along the descent and the placing, so that the frames show the arm brought back onto
        the expert's path before the gripper closes or opens; none while it does."""
        if self.phase in ("recover", "approach", "lift", "transport", "retreat"):
            return 1.0
        if self.phase in ("descend", "place"):
            return 1.0 - min(self.step_in_phase / self.seg[-1], 1.0)
        return 0.0

    # -------------------------------------------------------------- planning
    def _target(self):
        pos, quat = self.env.entity_pose(1)
        yaw = 2 * math.atan2(quat[3], quat[0])
        return pos, yaw

    def _grasp_yaw(self, object_yaw: float) -> float:
        shape = OBJECT_SHAPES[self.env.layout.target_object.asset.shape]
        base = object_yaw + shape.grasp_offset
        if shape.grasp_period == 0:
            return self.tool_yaw
        k = round((self.tool_yaw - base) / shape.grasp_period)
        return base + k * shape.grasp_period

    def _start(self, phase: str) -> None:
        self.phase = phase
        self.step_in_phase = 0
        env = self.env
        open_grip = self._open_grip()
        rec = env.layout.target_receptacle
        if phase == "recover":
            self._segment(
                self.tool_pos + [0, 0, CARRY_HEIGHT - self.tool_pos[2]], self.tool_yaw, open_grip, speed=0.2
            )
        elif phase == "approach":
            obj_pos, obj_yaw = self._target()
            self.grasp_yaw = self._grasp_yaw(obj_yaw)
            self._segment(np.array([*obj_pos[:2], CARRY_HEIGHT]), self.grasp_yaw, open_grip)
        elif phase == "descend":
            obj_pos, _ = self._target()
            self._segment(np.array([*obj_pos[:2], obj_pos[2] + 0.002]), self.grasp_yaw, open_grip, speed=0.2)
        elif phase == "grasp":
            self._segment(self.tool_pos, self.tool_yaw, 1.0, min_steps=int(0.5 * env.fps))
        elif phase == "lift":
            self._segment(
                self.tool_pos + [0, 0, CARRY_HEIGHT - self.tool_pos[2]], self.tool_yaw, 1.0, speed=0.2
            )
        elif phase == "transport":
            self._segment(np.array([*rec.xy, CARRY_HEIGHT]), self.tool_yaw, 1.0)
        elif phase == "place":
            z = FLOOR_THICKNESS + RELEASE_CLEARANCE + OBJECT_HEIGHT / 2
            self._segment(np.array([*rec.xy, z]), self.tool_yaw, 1.0, speed=0.2)
        elif phase == "release":
            self._segment(self.tool_pos, self.tool_yaw, open_grip, min_steps=int(0.4 * env.fps))
        elif phase == "retreat":
            self._segment(
                self.tool_pos + [0, 0, CARRY_HEIGHT - self.tool_pos[2]], self.tool_yaw, open_grip, speed=0.25
            )
        elif phase == "done":
            self._segment(self.tool_pos, self.tool_yaw, open_grip, min_steps=1)

    def _advance(self) -> None:
        if self.phase == "done":
            return
        if self.phase == "lift" and self.env.tracker.held != 1 and self.retries < MAX_RETRIES:
            self.retries += 1
            self._start("approach")
            return
        self._start(PHASES[PHASES.index(self.phase) + 1])


class JointDrift:
    """Recovery data after DART (Laskey et al., 2017): the arm is sent the expert's joint targets plus a smooth
    random offset (Ornstein-Uhlenbeck: `std` rad on each arm joint, correlation time `time_constant` s), while
    the frames keep the expert's own target as the action. The states leave the expert's path by about `std`
    and each frame's action is the way back to it; the gripper is never perturbed."""

    def __init__(self, std: float, time_constant: float, fps: int, seed: int):
        self.std = std
        self.decay = math.exp(-1.0 / (fps * time_constant))
        self.rng = np.random.default_rng(seed)
        self.offset = np.zeros(6)
        self.largest = 0.0  # rad, the largest offset sent to a joint: what the provenance records

    def __call__(self, action: np.ndarray, gain: float) -> np.ndarray:
        kick = self.rng.standard_normal(6) * self.std * math.sqrt(1.0 - self.decay**2)
        self.offset = self.decay * self.offset + kick
        sent = action.copy()
        sent[:6] += (gain * self.offset).astype(sent.dtype)
        self.largest = max(self.largest, float(np.max(np.abs(gain * self.offset))))
        return sent


def run_expert_episode(
    env,
    expert,
    seed: int,
    max_steps: int,
    on_step=None,
    drift: JointDrift | None = None,
    driver=None,
    takeover_step: int = 0,
) -> dict:
    """One expert episode; `on_step(obs, action, phase_label)` sees every observation before its action (the
    expert's target, also when `drift` moves the arm off it).

    With a `driver` (`reset(env)`, then `driver(obs) -> action`: a policy), the driver acts for the first
    `takeover_step` steps, unseen by `on_step`, and the expert takes over from the state it left
    (`ScriptedExpert.take_over`). The info's `taken_over` is false when the episode ended before that."""
    obs, info = env.reset(seed=seed)
    if driver is None:
        expert.reset(env)
    else:
        driver.reset(env)
        grip = 0.0
        for _ in range(takeover_step):
            action = driver(obs)
            grip = float(action[6])
            obs, _, terminated, truncated, info = env.step(action)
            if terminated or truncated:
                return {**info, "taken_over": False}
        expert.take_over(env, grip)
        info = {**info, "taken_over": True}
    for _ in range(max_steps - (takeover_step if driver is not None else 0)):
        action = expert.act(obs)
        if on_step is not None:
            on_step(obs, action, expert.phase_label)
        sent = action if drift is None else drift(action, expert.drift_gain)
        obs, _, terminated, truncated, step_info = env.step(sent)
        info = {**info, **step_info}
        if terminated or truncated:
            break
    return info


def expert_stages(
    task: str,
    condition: str,
    episodes: int,
    counterbalanced: bool = False,
    seed: int = 0,
    progress: bool = True,
) -> list[int]:
    """Stage index reached in each of `episodes` closed-loop expert episodes (seeds seed .. seed+episodes-1),
    without rendering: the oracle check of the environment."""
    from tqdm import tqdm

    from .pickplace_env import PickPlaceEnv

    env = PickPlaceEnv(task=task, condition=condition, counterbalanced=counterbalanced, obs_type="agent_pos")
    expert = ScriptedExpert()
    stages = []
    for k in tqdm(
        range(episodes), desc=f"expert {task} {condition}", unit="ep", disable=not progress, leave=False
    ):
        info = run_expert_episode(env, expert, seed + k, max_steps=300)
        stages.append(int(info["stage"]))
    env.close()
    return stages
