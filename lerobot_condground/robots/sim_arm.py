"""The MuJoCo twin of the UR3e behind the same arm interface as the hardware (`--robot.backend=sim`).

The twin is the condground scene (`envs.pickplace_env`) with its UR3e-like arm, driven by the same
`ServoLoop` as the real arm: position servos take the set points at 500 Hz (the physics rate), the
same safety limits and stall watchdog apply. Its cameras are LeRobot cameras of type `ur3e_twin`.
"""

from __future__ import annotations

import logging
import threading
import time

import mujoco
import numpy as np

from lerobot_condground.cameras.ur3e_twin import TWINS
from lerobot_condground.envs import robot as sim_robot
from lerobot_condground.envs.scene import PHYSICS_DT

from .servo_loop import ServoLoop

logger = logging.getLogger(__name__)

TRACKER_EVERY = 5


class TwinBackend:
    """ArmBackend over the twin's MuJoCo state."""

    def __init__(self, env):
        self.env = env
        self.freedrive_on = False
        self.servo_stops = 0
        # Simulation time of the last servo stop, as a controller logs it.
        self.stopped_at: float | None = None

    def read(self):
        env = self.env
        dof = [env.model.joint(n).dofadr[0] for n in sim_robot.JOINT_NAMES]
        return env.joint_positions(), env.data.qvel[dof].copy(), env.gripper_closure(), 1

    def servo(self, q):
        self.env.data.ctrl[:6] = q

    def servo_stop(self):
        # Position servos held at the measured joints: the arm decelerates to standstill where it is.
        self.env.data.ctrl[:6] = self.env.joint_positions()
        self.servo_stops += 1
        self.stopped_at = float(self.env.data.time)

    def set_gripper(self, closure):
        self.env.data.ctrl[6] = float(np.clip(closure, 0.0, 1.0)) * sim_robot.FINGER_TRAVEL

    def freedrive(self, on):
        if on:
            raise ValueError(
                "Freedrive (teach mode) needs the real arm (--robot.backend=rtde); the twin has no hand to move it"
            )


class SimArm:
    def __init__(self, config, home):
        self.config = config
        self.home = np.asarray(home, dtype=float) - np.asarray(config.joint_offsets)  # the arm's own frame
        self.env = None
        self.loop: ServoLoop | None = None
        self.scene = -1  # scene counter: 0 for the first layout after connect
        self.lock = threading.RLock()
        self._thread = None
        self._running = False
        self._fault: BaseException | None = None
        self._dirty = False  # the arm moved since the scene was laid out

    @property
    def is_connected(self) -> bool:
        return self.env is not None

    def connect(self) -> None:
        from lerobot_condground.envs.pickplace_env import PickPlaceEnv

        cfg = self.config
        self.env = PickPlaceEnv(
            task=cfg.sim.task,
            condition=cfg.sim.condition,
            counterbalanced=cfg.sim.counterbalanced,
            obs_type="agent_pos",
            prompts=True,
            fps=int(cfg.control_hz),
        )
        self.backend = TwinBackend(self.env)
        self.clock = 0.0
        self._ticks = 0
        self.reset_scene()
        TWINS.append(self)
        if cfg.sim.realtime:
            self._running = True
            self._thread = threading.Thread(target=self._run_realtime, name="ur3e-twin-physics", daemon=True)
            self._thread.start()

    def reset_scene(self) -> None:
        """A new layout (seed `sim.seed + scene`), the arm at its home pose, the stream stopped."""
        with self.lock:
            self.scene += 1
            self.env.reset(seed=self.config.sim.seed + self.scene)
            if not np.allclose(self.home, sim_robot.HOME_QPOS):  # a calibrated home pose: scenes start there
                self.env.data.qpos[self.env._arm_qadr] = self.home
                self.env.data.ctrl[:6] = self.home
                mujoco.mj_forward(self.env.model, self.env.data)
            self.loop = ServoLoop(
                self.backend,
                control_period=1 / self.config.control_hz,
                servo_period=PHYSICS_DT,
                max_joint_velocity=np.array(self.config.max_joint_velocity),
                joint_min=np.array(self.config.joint_min),
                joint_max=np.array(self.config.joint_max),
                stall_periods=self.config.stall_periods,
            )
            self.loop.tick(self.clock)
            self._dirty = False

    def new_episode(self) -> None:
        """A recorded episode starts: lay out a fresh scene, unless this one is still untouched."""
        if self._dirty:
            self.reset_scene()

    def _step(self) -> None:
        self.loop.tick(self.clock)
        mujoco.mj_step(self.env.model, self.env.data)
        self.clock += PHYSICS_DT
        self._ticks += 1
        if self._ticks % TRACKER_EVERY == 0:  # stage flags (grasp, place) at 100 Hz are plenty
            self.env.tracker.update(self.env.data)

    def _run_realtime(self) -> None:
        start = time.perf_counter() - self.clock
        try:
            while self._running:
                with self.lock:
                    behind = (time.perf_counter() - start) - self.clock
                    # Catch up in bounded bursts so rendering and commands still get the lock.
                    for _ in range(min(int(behind / PHYSICS_DT), 50)):
                        self._step()
                time.sleep(0.001)
        except BaseException as exc:  # surfaced by the next call from the robot
            self._fault = exc

    def _check(self) -> None:
        if self._fault is not None:
            raise self._fault

    def state(self):
        self._check()
        with self.lock:
            # The last tick's reading (at most one physics step old): ticking here too would advance the
            # set point faster than the velocity limit allows.
            return self.loop.state

    def command(self, q, gripper: float) -> None:
        self._check()
        with self.lock:
            self.loop.command(q, gripper, self.clock)
            self._dirty = True
            if not self.config.sim.realtime:
                for _ in range(round(1 / (self.config.control_hz * PHYSICS_DT))):
                    self._step()

    def freedrive(self, on: bool) -> None:
        with self.lock:
            self.loop.set_freedrive(on)

    def stop(self) -> None:
        with self.lock:
            if self.loop is not None:
                self.loop.stop()

    def disconnect(self) -> None:
        try:
            self.stop()
        finally:
            self._running = False
            if self._thread is not None:
                self._thread.join(timeout=2)
            if self in TWINS:
                TWINS.remove(self)
            if self.env is not None:
                self.env.close()
            self.env = None
