"""`condground failures`: why a checkpoint's rollouts fail, read off the simulation step by step.

The checkpoint runs on the sweep's layouts (same seeds as `condground sweep --eval.seed_offset`) while a
tracer reads what the env knows at every step: the tool-centre point, the target object's position, the
gripper command and the stage flags. Events:

- a *closing*: the gripper command crosses to closed (>= 0.5); its *offset* is the horizontal distance
  from the tool-centre point to the target's centre then (cm), its *height* the vertical one;
- *pushed*: how far the target moved on the table before the first closing (cm);
- *stalled*: the episode ran to its step limit and the tool moved less than 1 cm over its last 2 s;
- after the lift (the target held above 4 cm once), the *release*: the first time the gripper command
  crosses back to open; its offset is the horizontal distance from the target to the target receptacle's
  centre then (cm). Without a release the target is either still held at the end or slipped out closed;
- with a phase predictor (act_modified), the phase it predicted at every action chunk beside the world's
  phase then (place once the target is held or placed, pick before); *place_phase_unheld* counts the
  chunks it predicted place while the target was neither held nor placed: the prompt switched to the
  receptacle and the policy acted as if carrying a cube it did not have.

Each failed rollout gets one cause, the first that applies: `unstable` (physics), `cube_off_table`,
`wrong_object` (a look-alike grasped), `wrong_receptacle`, `lifted_not_placed` (dropped, or released
outside the bowl), `picked_not_lifted`, `pushed_away` (the target moved > 2 cm before any closing),
`closed_off_target` (closed beside it and never picked it; its offset says by how much), `never_closed`.
Writes `episodes.parquet` (one row per rollout with every measurement) and `failures.json` (counts per
cause, offsets at closing, and `carry`: the lifted-not-placed rollouts split into released, slipped out
and held to the end).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lerobot_condground.core.conditions import ROUTING_TASK
from lerobot_condground.core.configs import HELD_OUT_SEED_OFFSET, EvalEnvConfig, PolicyRefConfig, check_seed
from lerobot_condground.core.provenance import command_line, versions

logger = logging.getLogger(__name__)

CAUSES = (
    "success",
    "unstable",
    "cube_off_table",
    "wrong_object",
    "wrong_receptacle",
    "lifted_not_placed",
    "picked_not_lifted",
    "pushed_away",
    "closed_off_target",
    "never_closed",
)
CLOSED = 0.5  # gripper command: 0 open .. 1 closed
PUSHED_CM = 2.0
STALL_SECONDS = 2.0
STALL_CM = 1.0
TARGET = 1  # the target object's entity label
TARGET_RECEPTACLE = 2


@dataclass
class FailureOptions:
    episodes: int = 50
    seed_offset: int = HELD_OUT_SEED_OFFSET  # the sweep's default: its layouts, rollout by rollout
    batch_size: int = 10


@dataclass
class FailuresConfig:
    policy: PolicyRefConfig = field(default_factory=PolicyRefConfig)
    env: EvalEnvConfig = field(default_factory=EvalEnvConfig)
    failures: FailureOptions = field(default_factory=FailureOptions)
    output_dir: str = "outputs/failures"
    progress: bool = True


class Tracer:
    """Per-step read-outs of a batch of pick-and-place envs (a `run_episodes` step hook)."""

    def __init__(self, envs: list, fps: int):
        from lerobot_condground.envs.robot import FINGER_TRAVEL

        self.envs = envs
        self.closed_ctrl = CLOSED * FINGER_TRAVEL  # the gripper actuator's set point for a command
        self.stall_steps = int(STALL_SECONDS * fps)
        n = len(envs)
        self.start = None  # the target's position after reset, read at the first step
        self.closed = np.zeros(n, dtype=bool)
        self.closings: list[list[tuple[float, float, int]]] = [[] for _ in range(n)]  # offset, height, step
        self.pushed = np.zeros(n)
        self.tool: list[list[np.ndarray]] = [[] for _ in range(n)]
        self.active = np.zeros(n, dtype=bool)
        self.phases: list[list[tuple[int, int, int]]] = [[] for _ in range(n)]  # (step, predicted, world)
        # After the lift: the offset from the target receptacle (cm) and the step of the first opening.
        self.release: list[tuple[float, int] | None] = [None] * n
        self.held = np.zeros(n, dtype=bool)
        self.step = 0

    def __call__(self, step: int, batch, observations: list[dict], active: np.ndarray) -> None:
        self.active, self.step = active, step
        if self.start is None:
            self.start = [env.entity_pose(TARGET)[0] for env in self.envs]
        for i in np.flatnonzero(active):
            env = self.envs[i]
            tool, target = env.tcp_pose()[0], env.entity_pose(TARGET)[0]
            self.tool[i].append(tool)
            closed = env.data.ctrl[6] >= self.closed_ctrl  # the last step's gripper command
            if closed and not self.closed[i]:
                self.closings[i].append(
                    (float(np.hypot(*(tool - target)[:2]) * 100), float((tool - target)[2] * 100), step)
                )
            if not closed and self.closed[i] and env.tracker.lift and self.release[i] is None:
                receptacle = env.entity_pose(TARGET_RECEPTACLE)[0]
                self.release[i] = (float(np.hypot(*(target - receptacle)[:2]) * 100), step)
            self.closed[i] = closed
            self.held[i] = env.tracker.held == TARGET
            if not self.closings[i]:
                self.pushed[i] = max(self.pushed[i], float(np.hypot(*(target - self.start[i])[:2]) * 100))

    def on_phase(self, module, inputs, logits) -> None:
        """Forward hook on the phase head: its output for the batch the policy is acting on now (between
        this step's read-out and its action, so the world's phase is the one the prediction was made in)."""
        predicted = logits.argmax(-1).cpu().numpy()
        for i in np.flatnonzero(self.active):
            tracker = self.envs[i].tracker
            world = int(tracker.held == TARGET or tracker.place)
            self.phases[i].append((self.step, int(predicted[i]), world))

    def measurements(self, i: int, truncated: bool) -> dict:
        closings = self.closings[i]
        tail = np.array(self.tool[i][-self.stall_steps :])
        path = float(np.linalg.norm(np.diff(tail, axis=0), axis=1).sum() * 100) if len(tail) > 1 else 0.0
        offsets = [c[0] for c in closings]
        return {
            "closings": len(closings),
            "first_close_offset_cm": offsets[0] if offsets else float("nan"),
            "first_close_height_cm": closings[0][1] if closings else float("nan"),
            "first_close_step": closings[0][2] if closings else -1,
            "min_close_offset_cm": min(offsets) if offsets else float("nan"),
            "pushed_cm": float(self.pushed[i]),
            "stalled": bool(truncated and len(tail) >= self.stall_steps and path < STALL_CM),
            "release_offset_cm": self.release[i][0] if self.release[i] else float("nan"),
            "release_step": self.release[i][1] if self.release[i] else -1,
            "held_at_end": bool(self.held[i]),
            **self._phase_measurements(i),
        }

    def _phase_measurements(self, i: int) -> dict:
        if not any(self.phases):  # no phase predictor
            return {}
        steps, predicted, world = (np.array(column) for column in zip(*self.phases[i]))
        place = np.flatnonzero(predicted == 1)
        return {
            "phase_steps": steps,
            "phase_predicted": predicted.astype(np.int8),
            "phase_world": world.astype(np.int8),
            "first_place_phase_step": int(steps[place[0]]) if len(place) else -1,
            "phase_agreement": float((predicted == world).mean()),
            "place_phase_unheld": int(((predicted == 1) & (world == 0)).sum()),
        }


def cause(row: dict) -> str:
    """The first cause that applies to one rollout's outcome and measurements."""
    if row["success"]:
        return "success"
    if row["physics_unstable"]:
        return "unstable"
    if row["target_z"] < -0.05 or np.hypot(row["target_x"], row["target_y"]) > 1.0:
        return "cube_off_table"
    if row["selected_competitor_object"]:
        return "wrong_object"
    if row["placed_in_competitor_receptacle"]:
        return "wrong_receptacle"
    if row["lift"]:
        return "lifted_not_placed"
    if row["pick"]:
        return "picked_not_lifted"
    if row["pushed_cm"] > PUSHED_CM:
        return "pushed_away"
    if row["closings"]:
        return "closed_off_target"
    return "never_closed"


def summarize(rows) -> dict:
    """Counts per cause and the offsets at closing, over a table of rollouts (pandas)."""
    failed = rows[~rows["success"]]
    counts = rows["cause"].value_counts()
    closed = rows[rows["closings"] > 0]
    result = {
        "rollouts": len(rows),
        "successes": int(rows["success"].sum()),
        "causes": {c: int(counts.get(c, 0)) for c in CAUSES},
        "regrasped": int((failed["closings"] > 1).sum()),
        "stalled": int(failed["stalled"].sum()),
        "first_close_offset_cm": {
            "success_median": float(closed[closed["success"]]["first_close_offset_cm"].median()),
            "failure_median": float(closed[~closed["success"]]["first_close_offset_cm"].median()),
        },
    }
    carried = failed[failed["cause"] == "lifted_not_placed"]
    released = carried["release_step"] >= 0
    result["carry"] = {
        "released": int(released.sum()),
        "slipped": int((~released & ~carried["held_at_end"]).sum()),
        "held_to_end": int((~released & carried["held_at_end"]).sum()),
        "release_offset_cm": {
            "success_median": float(rows[rows["success"]]["release_offset_cm"].median()),
            "failure_median": float(carried["release_offset_cm"].median()),
        },
    }
    if "place_phase_unheld" in rows:
        result["phase"] = {
            "agreement": float(rows["phase_agreement"].mean()),
            "failures_with_place_phase_unheld": int((failed["place_phase_unheld"] > 0).sum()),
            "successes_with_place_phase_unheld": int((rows[rows["success"]]["place_phase_unheld"] > 0).sum()),
        }
    return result


def format_failures(result: dict) -> str:
    n = result["rollouts"]
    lines = [f"{'cause':<20} {'rollouts':>8}"]
    lines += [f"{c:<20} {k:>8} ({k / n:.0%})" for c, k in result["causes"].items() if k]
    offsets = result["first_close_offset_cm"]
    lines.append(
        f"first closing, median offset from the target: {offsets['success_median']:.1f} cm in successes, "
        f"{offsets['failure_median']:.1f} cm in failures; failures that re-grasped: {result['regrasped']}, "
        f"stalled: {result['stalled']}"
    )
    carry = result["carry"]
    lines.append(
        f"lifted, not placed: {carry['released']} released (median {carry['release_offset_cm']['failure_median']:.1f} cm "
        f"from the receptacle's centre, successes {carry['release_offset_cm']['success_median']:.1f} cm), "
        f"{carry['slipped']} slipped out closed, {carry['held_to_end']} held to the end"
    )
    if phase := result.get("phase"):
        lines.append(
            f"phase predictor agrees with the world on {phase['agreement']:.0%} of chunks; predicted place "
            f"without the target held in {phase['failures_with_place_phase_unheld']} failures and "
            f"{phase['successes_with_place_phase_unheld']} successes"
        )
    return "\n".join(lines)


def run_failures(cfg: FailuresConfig) -> Path:
    """Traced rollouts of one checkpoint -> DIR/episodes.parquet and DIR/failures.json."""
    import pandas as pd
    from tqdm import tqdm

    from lerobot_condground.core.conditions import check_condition
    from lerobot_condground.evaluation.checkpoints import describe_checkpoint, load_policy, resolve_device
    from lerobot_condground.evaluation.rollout import EnvPool, EnvSpec, run_episodes
    from lerobot_condground.evaluation.units import EPISODES_PER_SEED_LIMIT, layout_seed

    opts = cfg.failures
    if not 1 <= opts.episodes <= EPISODES_PER_SEED_LIMIT:
        raise ValueError(
            f"--failures.episodes={opts.episodes} is not allowed; allowed: 1 to {EPISODES_PER_SEED_LIMIT}"
        )
    if opts.batch_size < 1:
        raise ValueError(f"--failures.batch_size={opts.batch_size} must be at least 1")
    check_seed("--failures.seed_offset", opts.seed_offset, opts.episodes)
    if cfg.env.task == ROUTING_TASK:
        raise ValueError(
            f"--env.task={cfg.env.task!r}: the failure causes are pick-and-place stages; use `condground subgoals`"
        )
    condition = check_condition(cfg.env.condition or "clean", "--env.condition")
    path = cfg.policy.single()
    described = describe_checkpoint(path, cfg.policy.label, trust_remote_code=cfg.policy.trust_remote_code)
    if described.is_expert:
        raise ValueError("--policy.path=expert: the scripted expert does not fail; give a checkpoint")
    spec = EnvSpec.for_checkpoint(cfg.env, described, condition)
    loaded = load_policy(described, spec.lerobot_config(), resolve_device(cfg.policy.device))
    # act_modified's phase predictor (of its moving average when it keeps one: the weights that act).
    phase_head = getattr(getattr(loaded.policy, "acting_model", None), "phase_head", None)
    out = Path(cfg.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    pool, rows = EnvPool(), []
    starts = range(0, opts.episodes, opts.batch_size)
    for start in tqdm(starts, desc="failures", unit="batch", disable=not cfg.progress):
        episodes = list(range(start, min(start + opts.batch_size, opts.episodes)))
        seeds = [layout_seed(opts.seed_offset, 0, e) for e in episodes]
        envs = pool.get(spec, len(seeds))
        tracer = Tracer(envs, spec.fps)
        # The phase head runs once per action chunk, inside the policy call right after the tracer's step.
        hook = phase_head.register_forward_hook(tracer.on_phase) if phase_head is not None else None
        try:
            outcomes = run_episodes(loaded, envs, seeds, spec.episode_length, on_step=tracer)
        finally:
            if hook is not None:
                hook.remove()
        for i, (episode, seed, outcome) in enumerate(zip(episodes, seeds, outcomes, strict=True)):
            row = {
                "episode": episode,
                "layout_seed": seed,
                **outcome,
                **tracer.measurements(i, outcome["truncated"]),
            }
            rows.append({**row, "cause": cause(row)})
    table = pd.DataFrame(rows)
    table.to_parquet(out / "episodes.parquet", index=False)
    result = {
        "checkpoint": described.path,
        "checkpoint_hash": described.hash,
        "label": described.label,
        "task": spec.task,
        "condition": condition,
        "servo": spec.servo,
        "seed_offset": opts.seed_offset,
        **summarize(table),
        "command": command_line("failures", cfg),
        "versions": versions(),
    }
    (out / "failures.json").write_text(json.dumps(result, indent=2))
    print(format_failures(result))  # noqa: T201 (the command's result)
    return out
