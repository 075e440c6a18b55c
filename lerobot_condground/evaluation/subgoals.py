"""`condground subgoals`: InstrumentRouting-v0 evaluated per subgoal, each from its own initial state, under one
condition of the paper's VLA case study -> one row per trial in `results.parquet` and a subgoal x condition
table of success with 95 % Wilson intervals.

    condground subgoals --policy.path=P --env.task=InstrumentRouting-v0 --condition=cue --trials=5 \
        --output_dir=outputs/subgoals [--seed=S] [--subgoals=pick,route] [--policy.device=cpu]

Conditions: `cue` runs a prompt-trained checkpoint with the RGB cue its preprocessor draws (the env sends the
destination masks); `no_cue` the same checkpoint with the cue hidden (the env sends empty masks); `explicit` a
checkpoint on clean frames with the explicit left/right instruction (empty masks if its preprocessor has the
cue step, which refuses frames without any). The generic instruction says "the highlighted container".

Trial t of a subgoal resets the env with the same layout seed whatever the condition or checkpoint, so every
condition sees the same scenes. One output directory gathers the conditions: run the command once per
condition with the same --output_dir and the table shows them side by side. `subgoals.json` pins each
condition's settings and checkpoint: a rerun with the same ones resumes (finished trials are kept, rows are
written after every batch), other ones are refused.

With `--robot.type=ur3e ...` the trials run on the arm and an operator scores them (`operator_trials.py`),
into the same table with `scored_by=operator`; an output directory holds simulated or real trials, not both.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import pandas as pd
from lerobot.robots.config import RobotConfig
from tqdm import tqdm

from lerobot_condground.core import paper
from lerobot_condground.core.conditions import ROUTING_TASK
from lerobot_condground.core.configs import EvalEnvConfig, PolicyRefConfig, check_seed, comma_items
from lerobot_condground.core.files import read_json_object
from lerobot_condground.core.provenance import command_line, versions
from lerobot_condground.core.routing import SUBGOALS
from lerobot_condground.evaluation.checkpoints import (
    LoadedPolicy,
    describe_checkpoint,
    load_policy,
    resolve_device,
)
from lerobot_condground.evaluation.results import (
    TABLE_COLUMNS,
    check_rows_against_runs,
    read_table,
    write_table,
)
from lerobot_condground.evaluation.rollout import EnvSpec, run_episodes
from lerobot_condground.evaluation.statistics import SUBGOAL_POOLS, SUBGOAL_TITLES, subgoal_rates
from lerobot_condground.evaluation.units import EPISODES_PER_SEED_LIMIT, layout_seed

CONDITIONS = tuple(paper.SUBGOAL_STUDY)  # cue, no_cue, explicit
CUE_STEP = "condground_rgb_cue"
ROBOTS = ("ur3e",)
MANIFEST = "subgoals.json"
RESULTS = "results.parquet"
TABLE_JSON = "subgoals_table.json"
TABLE_MD = "subgoals_table.md"


@dataclass
class SubgoalEnvConfig(EvalEnvConfig):
    # The one task with subgoals; a class default, which draccus keeps when other --env.* flags are given.
    task: str = ROUTING_TASK


@dataclass
class SubgoalsConfig:
    policy: PolicyRefConfig = field(default_factory=PolicyRefConfig)
    env: SubgoalEnvConfig = field(default_factory=SubgoalEnvConfig)
    # cue, no_cue or explicit (see the module's docstring).
    condition: str | None = None
    trials: int = 5  # per subgoal
    # Subgoals to evaluate, separated by commas.
    subgoals: str = ",".join(SUBGOALS)
    # Layout seeds are seed + subgoal index * 100000 + trial: away from the recording seeds (0, 1, ...).
    seed: int = 1_000_000
    # Steps per trial, in simulation and on the robot (default: --env.episode_length); Ctrl-C ends a trial
    # on the robot sooner.
    max_steps: int | None = None
    batch_size: int = 5  # simulated trials stepped together as one policy batch
    output_dir: str = "outputs/subgoals"
    # The real arm instead of the simulation (--robot.type=ur3e --robot.host=... --robot.cameras=...).
    robot: RobotConfig | None = None
    progress: bool = True

    @property
    def steps(self) -> int:
        return self.max_steps if self.max_steps is not None else self.env.episode_length


@dataclass(frozen=True)
class Trial:
    subgoal: str
    trial: int
    seed: int


def parse_subgoals(text: str) -> list[str]:
    items = comma_items(text, "--subgoals")
    bad = [s for s in items if s not in SUBGOALS]
    if not items or bad or len(set(items)) != len(items):
        raise ValueError(
            f"--subgoals={text!r} is not allowed; allowed: {', '.join(SUBGOALS)}, separated by commas, each once"
        )
    return [s for s in SUBGOALS if s in items]  # the procedure's order, whatever the flag's


def validate(cfg: SubgoalsConfig) -> list[str]:
    """Everything that needs no checkpoint; one ValueError naming the flag."""
    if cfg.condition not in CONDITIONS:
        raise ValueError(f"--condition={cfg.condition!r} is not allowed; allowed: {', '.join(CONDITIONS)}")
    subgoals = parse_subgoals(cfg.subgoals)
    if cfg.env.task != ROUTING_TASK:
        raise ValueError(
            f"--env.task={cfg.env.task!r} is not allowed; allowed: {ROUTING_TASK} (the pick-and-place tasks "
            "are evaluated per condition with condground sweep)"
        )
    if cfg.env.condition is not None or cfg.env.counterbalanced or cfg.env.competitor_pool != "eval":
        raise ValueError(
            f"--env.condition, --env.counterbalanced and --env.competitor_pool do not apply to {ROUTING_TASK} (no "
            "look-alike competitors); leave them unset"
        )
    for flag, value in (
        ("--trials", cfg.trials),
        ("--max_steps", cfg.steps),
        ("--batch_size", cfg.batch_size),
    ):
        if value < 1:
            raise ValueError(f"{flag}={value} is not allowed; allowed: an integer >= 1")
    if cfg.trials > EPISODES_PER_SEED_LIMIT:
        raise ValueError(
            f"--trials={cfg.trials} exceeds {EPISODES_PER_SEED_LIMIT} (layout seeds would collide)"
        )
    check_seed("--seed", cfg.seed, len(SUBGOALS) * EPISODES_PER_SEED_LIMIT)
    if cfg.robot is not None:
        if cfg.robot.type not in ROBOTS:
            raise ValueError(
                f"--robot.type={cfg.robot.type!r} is not allowed; allowed: {', '.join(ROBOTS)} (the start poses "
                "are UR3e joint configurations)"
            )
        if getattr(cfg.robot, "backend", None) == "sim":
            raise ValueError(
                "--robot.backend=sim drives the pick-and-place twin, which has no instrument; subgoals run in "
                "simulation without --robot.*, and on the arm with --robot.backend=rtde"
            )
        if cfg.condition == "cue":
            raise ValueError(
                "--condition=cue cannot run on the real arm: the cue is drawn from the destination's mask in "
                "every camera frame, and the ur3e robot produces no masks (no segmentation on hardware). Run "
                "cue in simulation (without --robot.*), or no_cue / explicit on the arm"
            )
    return subgoals


def cue_step(loaded: LoadedPolicy) -> dict | None:
    """The config of the checkpoint's enabled `condground_rgb_cue` step, or None."""
    if loaded.is_expert:
        return None
    for _, _, step in loaded.read.steps:
        config = step.get("config") or {}
        if step.get("registry_name") == CUE_STEP and config.get("enabled", True):
            return config
    return None


def env_settings(condition: str, loaded: LoadedPolicy) -> dict:
    """What the env sends under a condition: its `cue` and `instruction` kwargs."""
    step = cue_step(loaded)
    if condition in ("cue", "no_cue") and step is None and not loaded.is_expert:
        raise ValueError(
            f"--condition={condition} shows or hides the RGB cue of a prompt-trained checkpoint, but the "
            f"preprocessor of {loaded.path!r} has no enabled {CUE_STEP} step; evaluate it with "
            "--condition=explicit"
        )
    if condition == "cue":
        return {"cue": True, "instruction": "generic"}
    if condition == "no_cue":
        return {"cue": False, "instruction": "generic"}
    return {"cue": False if step is not None else None, "instruction": "explicit"}


def check_cameras(loaded: LoadedPolicy, given: dict[str, tuple], where: str, fix: str) -> None:
    """The checkpoint's cameras, by name and size, must be ones the env or robot gives."""
    if loaded.is_expert:
        return
    if loaded.cameras and all(given.get(name) == tuple(size) for name, size in loaded.cameras.items()):
        return

    def listed(cameras: dict) -> str:
        return ", ".join(f"{name} {size[0]}x{size[1]}" for name, size in cameras.items()) or "none"

    raise ValueError(
        f"Checkpoint {loaded.path!r} reads cameras {listed(loaded.cameras)}, but {where} gives "
        f"{listed(given)}; {fix}"
    )


def sim_spec(cfg: SubgoalsConfig, loaded: LoadedPolicy, settings: dict) -> EnvSpec:
    spec = EnvSpec.for_checkpoint(cfg.env, loaded, "clean", prompts=False)
    return replace(spec, episode_length=cfg.steps, **settings)


def check_fits(cfg: SubgoalsConfig, loaded: LoadedPolicy, spec: EnvSpec) -> None:
    if cfg.robot is None:
        size = (spec.observation_height, spec.observation_width)
        check_cameras(
            loaded,
            {"top": size, "wrist": size},
            f"{ROUTING_TASK} (rendering both at one size)",
            "set that size with --env.observation_height/--env.observation_width (unset: the checkpoint's "
            "first camera's), or evaluate a checkpoint trained on these cameras (--policy.path)",
        )
    else:
        cameras = {name: (cam.height, cam.width) for name, cam in cfg.robot.cameras.items()}
        check_cameras(
            loaded,
            cameras,
            f"the {cfg.robot.type} robot",
            "give the robot those cameras at those sizes with --robot.cameras='{top: {type: opencv, "
            "index_or_path: 0, width: W, height: H, fps: 30}, ...}'",
        )


# ---------------------------------------------------------------- the output directory
def make_run(cfg: SubgoalsConfig, loaded: LoadedPolicy, subgoals: list[str], spec: EnvSpec) -> dict:
    """What pins one condition's trials: a rerun with other values would not continue the same trials."""
    env = {k: getattr(spec, k) for k in ("cue", "instruction", "fps")}
    if cfg.robot is None:
        env |= {
            "observation_height": spec.observation_height,
            "observation_width": spec.observation_width,
            "servo": spec.servo,
        }
    return {
        "checkpoint": loaded.describe(),
        "subgoals": subgoals,
        "trials": cfg.trials,
        "seed": cfg.seed,
        "max_steps": cfg.steps,
        "env": env,
    }


def check_same_run(root: Path, mode: str, condition: str, run: dict, rows: pd.DataFrame) -> dict:
    """The directory's manifest with this run in it; refuses another mode, or other settings for a
    condition already run there. What no trial was scored under pins nothing: a run refused or failed
    before its first trial never blocks the corrected rerun."""
    path = root / MANIFEST
    fresh = {"kind": "subgoals", "task": ROUTING_TASK, "mode": mode, "runs": {}}
    if not path.exists():
        if (root / RESULTS).exists():
            raise ValueError(
                f"{root} holds {RESULTS} but no {MANIFEST}: it is not a condground subgoals directory"
            )
        return fresh
    manifest = read_json_object(path, "Subgoals manifest")
    if manifest.get("kind") != "subgoals" or not isinstance(manifest.get("runs"), dict):
        raise ValueError(f"{path} is not a condground subgoals manifest; choose another --output_dir")
    check_rows_against_runs(root / RESULTS, rows, manifest["runs"])
    if not len(rows):
        return fresh
    if not (rows["condition"] == condition).any():
        manifest["runs"].pop(condition, None)
    if manifest.get("mode") != mode:
        raise ValueError(
            f"{root} holds trials run on {manifest.get('mode')!r}, this run is on {mode!r}; simulated and real "
            "trials go to separate --output_dir"
        )
    previous = manifest["runs"].get(condition)
    if previous is not None:
        old = {k: v for k, v in previous.items() if k in run}
        diffs = [f"{k}: {old.get(k)!r} -> {v!r}" for k, v in run.items() if old.get(k) != v]
        if diffs:
            raise ValueError(
                f"{root} holds condition {condition} run with other settings; differences: {'; '.join(diffs)}. "
                "Rerun with the same flags to resume it, or choose a new --output_dir."
            )
    return manifest


def read_rows(root: Path) -> pd.DataFrame:
    path = root / RESULTS
    return read_table(path) if path.exists() else pd.DataFrame(columns=list(TABLE_COLUMNS))


# ---------------------------------------------------------------- the table
def _cell(cell: dict | None) -> str:
    if cell is None:
        return "—"
    return f"{cell['k']}/{cell['n']} {cell['rate']:.0%} [{cell['low']:.0%}, {cell['high']:.0%}]"


def table_markdown(cells: list[dict]) -> str:
    """Subgoals (routing ones marked) x conditions: k/n, rate and 95 % Wilson interval."""
    conditions = [c for c in CONDITIONS if any(x["condition"] == c for x in cells)]
    by = {(x["subgoal"], x["condition"]): x for x in cells}
    lines = [
        "| subgoal | " + " | ".join(conditions) + " |",
        "|---" * (len(conditions) + 1) + "|",
    ]
    for name in (*SUBGOALS, *SUBGOAL_POOLS):
        if any((name, c) in by for c in conditions):
            lines.append(
                f"| {SUBGOAL_TITLES[name]} | "
                + " | ".join(_cell(by.get((name, c))) for c in conditions)
                + " |"
            )
    return "\n".join(lines)


def write_tables(root: Path, rows: pd.DataFrame) -> str:
    cells = subgoal_rates(rows, by=("condition",))
    markdown = table_markdown(cells)
    (root / TABLE_JSON).write_text(json.dumps({"task": ROUTING_TASK, "cells": cells}, indent=2))
    (root / TABLE_MD).write_text(
        "Success per subgoal and condition: successes/trials, rate [95 % Wilson interval].\n\n"
        + markdown
        + "\n"
    )
    return markdown


# ---------------------------------------------------------------- running
def identity(cfg: SubgoalsConfig, loaded: LoadedPolicy, spec: EnvSpec, trial: Trial) -> dict:
    return {
        **loaded.identity(),
        "task": ROUTING_TASK,
        "condition": cfg.condition,
        "condition_spec": json.dumps({"cue": spec.cue, "instruction": spec.instruction}),
        "counterbalanced": False,
        "eval_seed": cfg.seed,
        "episode": trial.trial,
        "layout_seed": trial.seed,
        "prompt": None,
    }


def run_in_sim(cfg, loaded: LoadedPolicy, spec: EnvSpec, todo: list[Trial], on_rows) -> None:
    import torch

    by_subgoal: dict[str, list[Trial]] = {}
    for trial in todo:
        by_subgoal.setdefault(trial.subgoal, []).append(trial)
    for subgoal, trials in by_subgoal.items():
        subgoal_spec = replace(spec, subgoal=subgoal)
        envs = []
        try:
            for start in range(0, len(trials), cfg.batch_size):
                batch = trials[start : start + cfg.batch_size]
                while len(envs) < len(batch):
                    envs.append(subgoal_spec.make())
                seeds = [t.seed for t in batch]
                torch.manual_seed(seeds[0])
                outcomes = run_episodes(loaded, envs[: len(batch)], seeds, max_steps=cfg.steps)
                on_rows([{**identity(cfg, loaded, spec, t), **o} for t, o in zip(batch, outcomes)])
        finally:
            for env in envs:
                env.close()


def run_on_robot(cfg, loaded: LoadedPolicy, spec: EnvSpec, device: str, todo: list[Trial], on_rows) -> None:
    from lerobot.robots.utils import make_robot_from_config

    from lerobot_condground.evaluation.operator_trials import operator_trial, start_states

    blank_masks = {seg: camera for camera, seg in (cue_step(loaded) or {}).get("cameras", {}).items()}
    starts = {}
    for subgoal in dict.fromkeys(t.subgoal for t in todo):
        trials = [t for t in todo if t.subgoal == subgoal]
        starts |= dict(zip(trials, start_states(subgoal, [t.seed for t in trials])))
    robot = make_robot_from_config(cfg.robot)
    robot.connect()
    try:
        for n, trial in enumerate(todo, 1):
            title = f"Trial {n}/{len(todo)} ({trial.subgoal} #{trial.trial + 1}, condition {cfg.condition})"
            try:
                scored = operator_trial(
                    robot, loaded, device, starts[trial], spec.instruction, cfg.steps, blank_masks, title
                )
            except EOFError:
                raise ValueError(
                    f"The input ended before {title} was scored; the trials scored so far are in "
                    f"{Path(cfg.output_dir) / RESULTS}, and the same command resumes after them"
                ) from None
            except KeyboardInterrupt:  # Ctrl-C outside a running trial: the operator ends the session
                print(
                    f"\nStopped by Ctrl-C before {title} was scored; the trials scored so far are in "
                    f"{Path(cfg.output_dir) / RESULTS}, and the same command resumes after them.",
                    flush=True,
                )
                break
            on_rows([{**identity(cfg, loaded, spec, trial), **scored}])
    finally:
        robot.disconnect()


def run_subgoals(cfg: SubgoalsConfig) -> Path:
    subgoals = validate(cfg)
    loaded = describe_checkpoint(cfg.policy.single(), cfg.policy.label, 0, cfg.policy.trust_remote_code)
    if cfg.robot is not None and loaded.is_expert:
        raise ValueError(
            f"--policy.path={loaded.path} is the scripted expert, which reads the simulation's state; the robot "
            "needs a checkpoint"
        )
    if loaded.needs_prompts:
        # Checked before the weights load: the routing env (and the arm) give no prompt crops, and the policy
        # would refuse only at its first step, after the output directory was set up.
        raise ValueError(
            f"--policy.path={loaded.path} reads prompt crops (act_modified with use_prompts), which "
            f"{ROUTING_TASK} does not give; allowed: a checkpoint without prompts (pi05_grounded, or act_modified "
            "trained with --policy.use_prompts=false)"
        )
    settings = env_settings(cfg.condition, loaded)
    spec = sim_spec(cfg, loaded, settings)
    check_fits(cfg, loaded, spec)
    device = resolve_device(cfg.policy.device)
    root = Path(cfg.output_dir)
    mode = "sim" if cfg.robot is None else cfg.robot.type
    run = make_run(cfg, loaded, subgoals, spec)
    rows = read_rows(root)
    manifest = check_same_run(root, mode, cfg.condition, run, rows)
    manifest["runs"][cfg.condition] = {**run, "command": command_line("subgoals", cfg)}
    manifest["versions"] = versions()

    mine = rows[rows["condition"] == cfg.condition]
    done = set(zip(mine["subgoal"], mine["episode"].astype(int)))
    plan = [
        Trial(s, t, layout_seed(cfg.seed, SUBGOALS.index(s), t)) for s in subgoals for t in range(cfg.trials)
    ]
    todo = [t for t in plan if (t.subgoal, t.trial) not in done]
    where = "simulation" if cfg.robot is None else f"{mode}, operator-scored"
    print(
        f"subgoals: {cfg.condition} with {loaded.label} ({where}): {len(subgoals)} subgoal(s) x {cfg.trials} "
        f"trial(s) = {len(plan)} trials; {len(plan) - len(todo)} already done",
        flush=True,
    )
    frames = [rows] if len(rows) else []
    bar = tqdm(
        total=len(plan), initial=len(plan) - len(todo), unit="trial", desc="subgoals",
        disable=not cfg.progress or cfg.robot is not None,
    )  # fmt: skip

    written = []

    def on_rows(new: list[dict]) -> None:
        # The manifest is written with the first scored trial: a run refused or failed before it leaves the
        # directory as it was, so the corrected rerun is not held to this run's settings.
        if not written:
            root.mkdir(parents=True, exist_ok=True)
            (root / MANIFEST).write_text(json.dumps(manifest, indent=2))
            written.append(True)
        frames.append(pd.DataFrame(new, columns=list(TABLE_COLUMNS)))
        write_table(pd.concat(frames, ignore_index=True), root / RESULTS, metadata=manifest)
        bar.update(len(new))

    try:
        if todo:
            loaded = load_policy(loaded, spec.lerobot_config(), device)
            if cfg.robot is None:
                run_in_sim(cfg, loaded, spec, todo, on_rows)
            else:
                run_on_robot(cfg, loaded, spec, device, todo, on_rows)
    finally:
        bar.close()
    if not frames:  # stopped before the first trial was scored
        print(f"subgoals: no trial scored; nothing written to {root / RESULTS}", flush=True)
        return root / RESULTS
    results = pd.concat(frames, ignore_index=True)
    print(write_tables(root, results), flush=True)
    print(f"subgoals: {len(results)} trials in {root / RESULTS}; table in {root / TABLE_MD}", flush=True)
    return root / RESULTS
