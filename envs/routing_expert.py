"""Scripted expert of `InstrumentRouting-v0`: reads the instrument's state and pose, and runs the rest of
the procedure from wherever the episode starts.

Phases, with the procedure step each belongs to (`step`, the recorded `observation.phase`):
approach (0 approach); descend, grasp, lift (1 pick); inspect (2); route (3); lower, release (4 place);
retreat (5); home, done (6 home). A grasp that does not hold the instrument is retried from the approach.
"""

from __future__ import annotations

import numpy as np

from lerobot_condground.core.routing import STEPS

from . import robot
from .expert import CARRY_HEIGHT, WaypointExpert
from .routing_env import INSPECT_HOLD_S
from .routing_scene import GRASP_WIDTH, INSPECT_POINT, SORT_HEIGHT, release_height

PHASES = (
    "approach", "descend", "grasp", "lift", "inspect", "route", "lower", "release", "retreat", "home", "done",
)  # fmt: skip
STEP_OF_PHASE = {
    "approach": "approach", "descend": "pick", "grasp": "pick", "lift": "pick", "inspect": "inspect",
    "route": "route", "lower": "place", "release": "place", "retreat": "retreat", "home": "home", "done": "home",
}  # fmt: skip
FIRST_PHASE = {
    "procedure": "approach", "pick": "approach", "inspect": "inspect", "route": "route", "place": "route",
    "home": "home",
}  # fmt: skip
OPEN = max(0.0, 1.0 - (GRASP_WIDTH + 0.03) / robot.GRIPPER_STROKE)
MAX_RETRIES = 2


class RoutingExpert(WaypointExpert):
    @property
    def phase_label(self) -> int:
        return STEPS.index(STEP_OF_PHASE[self.phase])

    @property
    def done(self) -> bool:
        return self.phase == "done"

    def _first_phase(self) -> str:
        return FIRST_PHASE[self.env.episode]

    def _initial_grip(self) -> float:
        return 1.0 if self.env.episode in ("inspect", "route", "place") else 0.0

    def _start(self, phase: str) -> None:
        self.phase = phase
        self.step_in_phase = 0
        env = self.env
        fps = env.fps
        if phase == "approach":
            pos, yaw = env.instrument_pose()
            self.grasp_yaw = env.grasp_yaw(yaw, self.tool_yaw)
            self._segment(np.array([*pos[:2], CARRY_HEIGHT]), self.grasp_yaw, OPEN)
        elif phase == "descend":
            pos, _ = env.instrument_pose()
            self._segment(np.array([*pos[:2], pos[2] + 0.002]), self.grasp_yaw, OPEN, speed=0.2)
        elif phase == "grasp":
            self._segment(self.tool_pos, self.tool_yaw, 1.0, min_steps=int(0.5 * fps))
        elif phase == "lift":
            self._segment(np.array([*self.tool_pos[:2], SORT_HEIGHT]), self.tool_yaw, 1.0, speed=0.2)
        elif phase == "inspect":
            # Dwell there long enough for the inspection to count, with a margin.
            hold = int(np.ceil((INSPECT_HOLD_S + 0.3) * fps))
            self._segment(INSPECT_POINT, self.tool_yaw, 1.0, speed=0.25)
            self.seg = (*self.seg[:6], self.seg[6] + hold)
        elif phase == "route":
            above = np.array([*env.layout.containers[env.layout.destination], SORT_HEIGHT])
            self._segment(above, self.tool_yaw, 1.0, speed=0.25)
        elif phase == "lower":
            self._segment(np.array([*self.tool_pos[:2], release_height()]), self.tool_yaw, 1.0, speed=0.15)
        elif phase == "release":
            self._segment(self.tool_pos, self.tool_yaw, OPEN, min_steps=int(0.4 * fps))
        elif phase == "retreat":
            self._segment(np.array([*self.tool_pos[:2], SORT_HEIGHT]), self.tool_yaw, OPEN, speed=0.25)
        elif phase == "home":
            self._joint_segment(robot.HOME_QPOS, OPEN)
        elif phase == "done":
            self._segment(self.tool_pos, self.tool_yaw, self.grip, min_steps=1)
            self.joint_goal = (self.q_cmd.copy(), self.q_cmd.copy())

    def _advance(self) -> None:
        if self.phase == "done":
            return
        if self.phase == "lift" and not self.env.tracker.held and self.retries < MAX_RETRIES:
            self.retries += 1
            self._start("approach")
            return
        self._start(PHASES[PHASES.index(self.phase) + 1])
