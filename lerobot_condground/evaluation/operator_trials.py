"""InstrumentRouting-v0 trials on the real arm, scored by an operator: the start pose comes from the simulation,
the scene from the operator, the actions from the policy, the outcome from the operator's `y` or `n`.

A trial's start is the simulated env's reset with the trial's layout seed, so the real trial starts where
the simulated one does: the arm's joints (the subgoal's start pose, solved by the env's own inverse
kinematics), the gripper (closed when the subgoal starts with the instrument held), and the scene the
operator is asked to lay out (the instrument's state, which decides its destination, and where things lie
in the robot's base frame).
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np

from lerobot_condground.core.routing import instruction
from lerobot_condground.core.ur3e import MOTOR_NAMES
from lerobot_condground.evaluation.checkpoints import LoadedPolicy

GRIP_S = 1.0  # how long the gripper is given to open or close before the policy starts


@dataclass(frozen=True)
class StartState:
    subgoal: str
    q: np.ndarray  # the six joints (rad)
    grip: float  # gripper command: 1 holds the instrument, 0 open
    contaminated: bool
    destination: str
    instrument_xy: tuple[float, float]
    instrument_yaw: float
    containers: dict[str, tuple[float, float]]

    def task(self, form: str) -> str:
        """The trial's instruction in the given form (generic or explicit)."""
        return instruction(self.subgoal, form, self.destination)

    def setup(self) -> str:
        """What the operator lays out before the trial."""
        x, y = self.instrument_xy
        state = "marked (contaminated)" if self.contaminated else "clean (unmarked)"
        where = {
            "pick": f"lies on the table at x={x:.3f} m, y={y:.3f} m, turned {np.degrees(self.instrument_yaw):.0f} deg",
            "inspect": "is held by the gripper, above where it lay",
            "route": "is held by the gripper at the inspection point",
            "place": "is held by the gripper above the middle between the containers",
            "home": f"lies in the {self.destination} container, the open gripper above it",
        }[self.subgoal]
        containers = ", ".join(
            f"{side} at x={cx:.3f} m, y={cy:.3f} m" for side, (cx, cy) in self.containers.items()
        )
        text = (
            f"the instrument is {state}, so it belongs in the {self.destination} container; it {where}. "
            f"Containers (robot base frame): {containers}."
        )
        if self.grip:
            text += " Put the instrument between the open fingers: Enter closes the gripper on it."
        return text


def start_states(subgoal: str, seeds: list[int]) -> list[StartState]:
    """The simulated starts of one subgoal's trials (one env reset per layout seed)."""
    from lerobot_condground.envs.routing_env import OPEN_CLOSURE, InstrumentRoutingEnv

    env = InstrumentRoutingEnv(subgoal=subgoal, obs_type="agent_pos", wrist_camera=False, render_mode=None)
    states = []
    try:
        for seed in seeds:
            obs, _ = env.reset(seed=int(seed))
            layout = env.layout
            states.append(
                StartState(
                    subgoal=subgoal,
                    q=np.asarray(obs["agent_pos"][:6], dtype=float),
                    grip=1.0 if obs["agent_pos"][6] > OPEN_CLOSURE else 0.0,
                    contaminated=layout.contaminated,
                    destination=layout.destination,
                    instrument_xy=tuple(layout.instrument_xy),
                    instrument_yaw=float(layout.instrument_yaw),
                    containers={side: tuple(xy) for side, xy in layout.containers.items()},
                )
            )
    finally:
        env.close()
    return states


@contextlib.contextmanager
def interrupt_sets(event: threading.Event):
    """Ctrl-C sets `event` instead of raising: it ends a trial between two steps, never inside a command
    to the arm, and the command goes on with the next trial."""
    previous = signal.signal(signal.SIGINT, lambda signum, frame: event.set())
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def read_line(prompt: str) -> str:
    """`input(prompt)` whose Ctrl-C is never lost. From a pipe (a script or a test playing the operator),
    `input` writes the prompt and then blocks in read(); a SIGINT taken after Python's last check on that
    way, or by another thread, only sets Python's flag, and its KeyboardInterrupt waits for the next line.
    Waiting in short selects returns to Python often enough to raise it. Bytes are read one at a time, so
    nothing past the line is consumed."""
    if sys.stdin.isatty():
        return input(prompt)
    print(prompt, end="", flush=True)
    fd, line = sys.stdin.fileno(), bytearray()
    while True:
        if not select.select([fd], [], [], 0.2)[0]:
            continue
        byte = os.read(fd, 1)
        if byte in (b"", b"\n"):
            if not byte and not line:
                raise EOFError
            return line.decode(errors="replace")
        line += byte


def ask(prompt: str, answers: dict[str, object]):
    """The operator's answer; asked again until it is one of `answers`. End of input stops the command
    (EOFError), with what was scored so far already written."""
    while True:
        text = read_line(prompt).strip().lower()
        if text in answers:
            return answers[text]
        print(f"Please answer {' or '.join(answers)}.", flush=True)


def _hold(robot, q: np.ndarray, grip: float, seconds: float) -> None:
    """Streams one target for `seconds`, so that the gripper gets there and the arm's watchdog is fed."""
    period = 1 / robot.config.control_hz
    for _ in range(max(1, round(seconds / period))):
        robot.send_action(dict(zip(MOTOR_NAMES, [*map(float, q), float(grip)], strict=True)))
        time.sleep(period)


def run_policy_on_robot(
    robot, loaded: LoadedPolicy, device: str, task: str, max_steps: int, blank_masks: dict[str, str]
) -> tuple[int, bool]:
    """Up to `max_steps` policy steps at the robot's control rate, through LeRobot's own inference helpers
    (as lerobot-record runs a policy). Returns (steps run, whether Ctrl-C ended it).

    blank_masks: segmentation key -> camera key, for a preprocessor whose cue step needs a mask per frame:
    it gets an empty one (nothing highlighted), what the env sends with the cue hidden."""
    import torch
    from lerobot.common.control_utils import predict_action
    from lerobot.policies.utils import make_robot_action
    from lerobot.utils.feature_utils import build_dataset_frame, hw_to_dataset_features

    features = {
        **hw_to_dataset_features(robot.observation_features, "observation"),
        **hw_to_dataset_features(robot.action_features, "action"),
    }
    period = 1 / robot.config.control_hz
    stop = threading.Event()
    loaded.policy.reset()
    steps = 0
    with interrupt_sets(stop):
        print(f"Running the policy for at most {max_steps} steps: {task!r}", flush=True)
        while steps < max_steps and not stop.is_set():
            started = time.perf_counter()
            frame = build_dataset_frame(features, robot.get_observation(), prefix="observation")
            for mask, camera in blank_masks.items():
                if camera in frame:
                    frame[mask] = np.zeros(frame[camera].shape[:2], dtype=np.uint8)
            action = predict_action(
                frame,
                loaded.policy,
                torch.device(device),
                loaded.preprocessor,
                loaded.postprocessor,
                use_amp=False,
                task=task,
                robot_type=robot.name,
            )
            robot.send_action(make_robot_action(action, features))
            steps += 1
            time.sleep(max(0.0, period - (time.perf_counter() - started)))
    return steps, stop.is_set()


def operator_trial(
    robot,
    loaded: LoadedPolicy,
    device: str,
    start: StartState,
    form: str,
    max_steps: int,
    blank_masks: dict[str, str],
    title: str,
) -> dict:
    """One trial: arm to the start pose, the operator lays out the scene, the policy runs, the operator
    scores. Returns the outcome columns it knows; the env's stage and location columns stay unset."""
    print(f"\n{title}: moving the arm to the start pose of `{start.subgoal}` (gripper open).", flush=True)
    state = robot.get_observation()
    _hold(robot, np.array([state[name] for name in MOTOR_NAMES[:6]]), 0.0, GRIP_S)
    robot.move_to(start.q)
    print(f"Set up: {start.setup()}", flush=True)
    read_line("Press Enter to start the trial (Ctrl-C ends it early)... ")
    if start.grip:
        _hold(robot, start.q, start.grip, GRIP_S)
    steps, interrupted = run_policy_on_robot(robot, loaded, device, start.task(form), max_steps, blank_masks)
    print(f"{'Stopped by Ctrl-C' if interrupted else 'Step limit reached'} after {steps} steps.", flush=True)
    success = ask(f"Did `{start.subgoal}` succeed? [y/n] ", {"y": True, "n": False})
    return {
        "success": success,
        "steps": steps,
        "truncated": not interrupted and steps >= max_steps,
        "subgoal": start.subgoal,
        "destination": start.destination,
        "scored_by": "operator",
    }
