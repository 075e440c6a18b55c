"""`condground compare`: one training recipe against another, as the lever protocol measures it.

Both arms train side by side at the same step budget on the same recording, several training seeds each
(or come as finished runs, or as the pooled rollouts a published table keeps); the last `--eval.pool`
checkpoints of every run are scored on the same held-out layouts under each condition; rollouts are paired
by (seed index, checkpoint rank, layout). The result is the layout-clustered, run-aware interval of
`statistics.clustered_difference` (the layout pairs, the training run replicates), beside Newcombe's
interval and McNemar's p of the pooled pairs (what issue 27 published), and Holm's p over the whole table a
row is published into (`--table`).

Folders under --output_dir: `train/<task>_<variant>_<arm>_s<seed>` (a run and `.log` beside it),
`eval/<run>/<step>` (a sweep), `failures/<run>`, and `comparisons/<task>_<treated>_vs_<baseline>/` with
compare.json (what was compared, how, and every difference between the arms), rollouts.parquet (every
pooled rollout with its stages), summary.csv (one row per condition, `levers.csv`'s columns),
checkpoints.csv, funnel.csv and compare.png. `condground report --input_dir=<that folder>` renders it.
Every stage resumes: finished runs, sweeps and analyses are kept, an interrupted run continues from its
last checkpoint.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shlex
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from lerobot_condground.core.conditions import NAMED_CONDITIONS, check_task
from lerobot_condground.core.configs import (
    HELD_OUT_SEED_OFFSET,
    DatasetRefConfig,
    EvalEnvConfig,
    check_at_least,
)
from lerobot_condground.core.files import read_json_object
from lerobot_condground.core.provenance import RECORD_FILE, command_line, console_script, versions
from lerobot_condground.core.training import CPU_BATCH_SIZE, CPU_POLICY, CPU_STEPS, policy_flags, speed_flags
from lerobot_condground.evaluation.results import read_table
from lerobot_condground.evaluation.statistics import (
    METRICS,
    cell_metrics,
    clustered_difference,
    holm,
    paired_difference,
    rate,
)

STAGES = ("all", "train", "evaluate", "analyse", "failures")
SOURCES = ("flags", "runs", "rollouts")
# What makes two arms' training differ besides their recipe: the budget and the data.
BUDGET_KEYS = ("steps", "save_freq", "batch_size")
DATA_KEYS = ("dataset.repo_id", "dataset.root", "dataset.episodes")
SUMMARY_COLUMNS = [
    "lever", "task", "condition", "baseline_arm", "seeds", "n", "baseline", "treated", "diff", "diff_low",
    "diff_high", "p", "cluster_low", "cluster_high", "cluster_p", "seed_effects", "flags", "steps",
    "checkpoints", "differences",
]  # fmt: skip


@dataclass
class ArmConfig:
    # What tables call the arm; its runs train in <output_dir>/train/<task>_<variant>_<name>_s<seed>.
    name: str = ""
    # Its own lerobot-train flags (after the CPU configuration's and --train.flags): trained here ...
    flags: str = ""
    # ... or its finished runs: lerobot-train output folders, one per training seed, separated by commas ...
    runs: str | None = None
    # ... or its pooled rollouts in a published `<stem>_rollouts.csv` (the rows of lever `name` and the task).
    rollouts: str | None = None

    def source(self) -> str:
        return "runs" if self.runs else "rollouts" if self.rollouts else "flags"


@dataclass
class CompareTrainConfig:
    # Training seeds of each arm trained here (the i-th seed of one arm is paired with the i-th of the other).
    seeds: str = "0,1"
    steps: int = CPU_STEPS
    save_freq: int = 2000
    # act_modified variant of both arms (an arm's flags may change it).
    variant: str = "standard"
    # lerobot-train flags of both arms, after the CPU configuration's.
    flags: str = ""
    # torch threads of each training run (every run trains at once).
    threads: int = 1


@dataclass
class CompareEvalConfig:
    # Conditions scored and compared, separated by commas (e.g. clean,full_mixed).
    conditions: str = "clean"
    # Held-out layouts per checkpoint: seeds seed_offset ... seed_offset + episodes - 1.
    episodes: int = 50
    seed_offset: int = HELD_OUT_SEED_OFFSET
    # The last checkpoints of each run pooled.
    pool: int = 3
    # Sweeps (and failure analyses) at once, one worker each.
    jobs: int = 2


@dataclass
class CompareConfig:
    env: EvalEnvConfig = field(default_factory=EvalEnvConfig)
    # The recording both arms train on (an arm's flags may name another, which is then a difference).
    dataset: DatasetRefConfig = field(default_factory=DatasetRefConfig)
    # Named `baseline` and `treated` unless given names.
    baseline: ArmConfig = field(default_factory=ArmConfig)
    treated: ArmConfig = field(default_factory=ArmConfig)
    train: CompareTrainConfig = field(default_factory=CompareTrainConfig)
    eval: CompareEvalConfig = field(default_factory=CompareEvalConfig)
    output_dir: str = "outputs/compare"
    # A `levers.csv`-format table to publish the summary into (beside it: <stem>_checkpoints, _rollouts,
    # _funnel and, with --failures, _failures.csv, and <stem>_<task>.png); Holm's p is over the whole table.
    table: str | None = None
    stage: str = "all"
    # Compare arms that differ in budget or data (their differences are written beside the result).
    allow_differences: bool = False
    # `condground failures` of each run's last checkpoint on the held-out layouts (causes of failure); the
    # failures stage runs it whatever this says.
    failures: bool = False
    progress: bool = True

    def __post_init__(self):
        check_task(self.env.task)
        if self.stage not in STAGES:
            raise ValueError(f"--stage={self.stage!r} is not allowed; allowed: {', '.join(STAGES)}")
        if self.env.condition is not None:
            raise ValueError(
                f"--env.condition={self.env.condition!r} is not allowed here; allowed: --eval.conditions"
            )
        check_at_least(self.eval, "eval.", episodes=2, pool=1, jobs=1)
        check_at_least(self.train, "train.", steps=1, save_freq=1, threads=1)
        for flag, arm in (("--baseline", self.baseline), ("--treated", self.treated)):
            arm.name = arm.name or flag.removeprefix("--")
            if not arm.name.isidentifier():
                raise ValueError(
                    f"{flag}.name={arm.name!r} is not allowed; allowed: a name such as augmentation"
                )
            given = [s for s in ("runs", "rollouts") if getattr(arm, s)]
            if len(given) > 1 or (given and arm.flags):
                raise ValueError(
                    f"{flag} has {' and '.join(['flags', *given] if arm.flags else given)}; allowed: one of "
                    ".flags (trained here), .runs (finished runs) or .rollouts (a published table)"
                )
        if self.baseline.name == self.treated.name:
            raise ValueError(f"--baseline.name and --treated.name are both {self.baseline.name!r}")
        if self.treated.rollouts:
            raise ValueError("--treated.rollouts is not allowed; a published table can only be the baseline")
        self.seeds()
        self.conditions()

    def seeds(self) -> list[int]:
        try:
            seeds = [int(s) for s in self.train.seeds.split(",")]
        except ValueError:
            raise ValueError(
                f"--train.seeds={self.train.seeds!r} is not allowed; allowed: integers separated by commas"
            ) from None
        if len(set(seeds)) != len(seeds) or min(seeds) < 0:
            raise ValueError(f"--train.seeds={self.train.seeds!r}: seeds must be distinct and >= 0")
        return seeds

    def conditions(self) -> list[str]:
        names = [c for c in self.eval.conditions.split(",") if c]
        unknown = [c for c in names if c not in NAMED_CONDITIONS]
        if unknown or not names or len(set(names)) != len(names):
            raise ValueError(
                f"--eval.conditions={self.eval.conditions!r} is not allowed; allowed: distinct names among "
                f"{', '.join(NAMED_CONDITIONS)}, separated by commas"
            )
        return names

    def layouts(self) -> range:
        return range(self.eval.seed_offset, self.eval.seed_offset + self.eval.episodes)


@dataclass
class Arm:
    """One arm as the comparison sees it: its runs (one per seed index) or its published rollouts."""

    name: str
    source: str
    flags: list[str]
    runs: list[Path]
    # steps, save_freq, batch_size and dataset.* as the arm trains (None where not known)
    setting: dict
    pooled: list[int]  # checkpoint steps pooled, oldest first


def _flag_values(flags: list[str]) -> dict:
    """The budget and data a list of lerobot-train flags sets (the last of a repeated flag wins, as in
    draccus); flags that set none of them are ignored."""
    parser = argparse.ArgumentParser(allow_abbrev=False, add_help=False)
    for key in (*BUDGET_KEYS, *DATA_KEYS):
        parser.add_argument(f"--{key}")
    return {k: v for k, v in vars(parser.parse_known_args(flags)[0]).items() if v is not None}


def _normal(key: str, value) -> str | None:
    """A setting as text, so that a flag's `6000` equals a config's 6000 and a path its resolved form."""
    if value is None:
        return None
    if key == "dataset.root":
        return str(Path(value).resolve())
    return str(value)


def run_dir(cfg: CompareConfig, arm: str, seed: int) -> Path:
    return Path(cfg.output_dir) / "train" / f"{cfg.env.task}_{cfg.train.variant}_{arm}_s{seed}"


def checkpoint(run: Path, step: int) -> Path:
    return run / "checkpoints" / f"{step:06d}" / "pretrained_model"


def _pooled(name: str, steps: int, every: int, pool: int) -> list[int]:
    if steps % every:
        raise ValueError(f"{name}: --save_freq={every} does not divide --steps={steps}")
    first = steps - every * (pool - 1)
    if first <= 0:
        raise ValueError(f"{name}: --eval.pool={pool} checkpoints every {every} steps do not fit in {steps}")
    return list(range(first, steps + 1, every))


def resolve_arm(cfg: CompareConfig, arm: ArmConfig) -> Arm:
    seeds = cfg.seeds()
    if arm.source() == "flags":
        flags = shlex.split(arm.flags)
        setting = {
            "steps": cfg.train.steps, "save_freq": cfg.train.save_freq, "batch_size": CPU_BATCH_SIZE,
            "dataset.repo_id": cfg.dataset.repo_id or f"local/{cfg.env.task}", "dataset.root": cfg.dataset.root,
            "dataset.episodes": None,
            **_flag_values(shlex.split(cfg.train.flags)), **_flag_values(flags),
        }  # fmt: skip
        try:
            steps, every = int(setting["steps"]), int(setting["save_freq"])
        except ValueError:
            raise ValueError(f"--{arm.name}: --steps and --save_freq must be integers") from None
        runs = [run_dir(cfg, arm.name, seed) for seed in seeds]
        return Arm(arm.name, "flags", flags, runs, setting, _pooled(arm.name, steps, every, cfg.eval.pool))
    if arm.source() == "runs":
        runs = [Path(r) for r in arm.runs.split(",") if r]
        if len(runs) != len(seeds):
            raise ValueError(
                f"--{arm.name}: {len(runs)} runs in .runs and {len(seeds)} --train.seeds; allowed: one run a seed"
            )
        settings, recipes = [], []
        for run in runs:
            path = run / "checkpoints" / "last" / "pretrained_model" / "train_config.json"
            if not path.is_file():
                raise FileNotFoundError(
                    f"{path}: not a finished lerobot-train run (its last checkpoint's config)"
                )
            config = read_json_object(path, "Training config")
            dataset = config.get("dataset") or {}
            settings.append(
                {"steps": config.get("steps"), "save_freq": config.get("save_freq"),
                 "batch_size": config.get("batch_size"), "dataset.repo_id": dataset.get("repo_id"),
                 "dataset.root": dataset.get("root"), "dataset.episodes": dataset.get("episodes")}
            )  # fmt: skip
            policy = config.get("policy") or {}
            if not isinstance(policy, dict):
                raise ValueError(f"{path}: its policy is {type(policy).__name__}, not an object of settings")
            recipes.append(recipe_flags(policy))
        if any(s != settings[0] for s in settings):
            raise ValueError(f"--{arm.name}.runs: the runs differ in budget or data: {settings}")
        if any(r != recipes[0] for r in recipes):
            raise ValueError(f"--{arm.name}.runs: the runs differ in their policy settings: {recipes}")
        steps, every = settings[0]["steps"], settings[0]["save_freq"]
        if not (isinstance(steps, int) and isinstance(every, int) and steps > 0 and every > 0):
            raise ValueError(
                f"--{arm.name}.runs: steps {steps!r} and save_freq {every!r} are not step counts"
            )
        return Arm(
            arm.name, "runs", recipes[0], runs, settings[0], _pooled(arm.name, steps, every, cfg.eval.pool)
        )
    table = published_rollouts(Path(arm.rollouts), arm.name, cfg.env.task)
    steps = sorted(table["step"].unique())[-cfg.eval.pool :]
    if len(steps) < cfg.eval.pool or table["seed"].nunique() != len(seeds):
        raise ValueError(
            f"--{arm.name}.rollouts={arm.rollouts}: {table['seed'].nunique()} seeds and {len(steps)} checkpoints of "
            f"{arm.name} on {cfg.env.task}; allowed: {len(seeds)} seeds (--train.seeds) with --eval.pool={cfg.eval.pool}"
        )
    setting = dict.fromkeys((*BUDGET_KEYS, *DATA_KEYS))
    setting["steps"] = int(steps[-1])
    return Arm(arm.name, "rollouts", [], [], setting, [int(s) for s in steps])


# Policy fields a finished run's config holds that are not its recipe: read from the dataset (features, the
# camera, the label keys), chosen for the machine (device, bf16, memory format), or LeRobot's bookkeeping.
NOT_RECIPE = {
    "input_features", "output_features", "attention_camera", "label_keys", "device", "use_amp",
    "channels_last", "push_to_hub", "repo_id", "private", "tags", "license", "pretrained_path",
}  # fmt: skip


def recipe_flags(policy: dict) -> list[str]:
    """A finished act_modified run's policy settings as the lerobot-train flags that set them over the CPU
    configuration (`core.training.policy_flags`): its variant, and each field that differs from what that
    variant has there."""
    import draccus

    from lerobot_condground.policies.act_modified.configuration_act_modified import ACTModifiedConfig

    if policy.get("type") != "act_modified":
        return []
    variant = policy.get("variant")
    reference = draccus.encode(ACTModifiedConfig(variant=variant, **CPU_POLICY))
    flags = [f"--policy.variant={variant}"]
    for key, value in policy.items():
        if key not in NOT_RECIPE and key != "variant" and key in reference and reference[key] != value:
            text = (
                f"[{','.join(map(str, value))}]" if isinstance(value, list) else json.dumps(value).strip('"')
            )
            flags.append(f"--policy.{key}={text}")
    return flags


def published_rollouts(path: Path, name: str, task: str) -> pd.DataFrame:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such rollouts table")
    table = pd.read_csv(path)
    missing = {"lever", "task", "seed", "step", "layout_seed", "success"} - set(table.columns)
    if missing:
        raise ValueError(f"{path}: not a rollouts table (missing {sorted(missing)})")
    for column in ("seed", "step", "layout_seed", "success"):
        values = pd.to_numeric(table[column], errors="coerce")
        bad = table[column][
            values.isna() | (values != values.round()) | ((column == "success") & ~values.isin([0, 1]))
        ]
        if len(bad):
            allowed = "0 or 1" if column == "success" else "an integer"
            raise ValueError(
                f"{path}: {column}={bad.iloc[0]!r} in row {bad.index[0] + 2}; allowed: {allowed}"
            )
    if "condition" not in table:  # the tables of issue 27 scored clean scenes only
        table = table.assign(condition="clean")
    table = table[table["lever"].eq(name) & table["task"].eq(task)]
    if table.empty:
        raise ValueError(f"{path} has no rollouts of {name} on {task}")
    return table.assign(condition=table["condition"].fillna("clean"))


def _shown(key: str, value: str) -> str:
    """A setting as tables print it: a path inside the working directory relative to it (published tables must
    not name this machine's folders), any other as it is."""
    if key == "dataset.root" and Path(value).is_relative_to(Path.cwd().resolve()):
        return str(Path(value).relative_to(Path.cwd().resolve()))
    return value


def differences(a: Arm, b: Arm) -> list[str]:
    """Every known budget or data setting in which the arms differ, as `key: a -> b`."""
    out = []
    for key in (*BUDGET_KEYS, *DATA_KEYS):
        x, y = _normal(key, a.setting.get(key)), _normal(key, b.setting.get(key))
        if x is not None and y is not None and x != y:
            out.append(f"{key}: {_shown(key, x)} -> {_shown(key, y)}")
    return out


def training_seeds(root: Path) -> set[int]:
    """The layout seeds of a recording's episodes, from the provenance `condground record` (or merge,
    augment) writes beside it."""
    path = root / RECORD_FILE
    if not path.is_file():
        raise ValueError(
            f"--dataset.root={root}: no {RECORD_FILE}, so its layouts cannot be checked against the held-out "
            "ones; allowed: a recording made by condground record, merge or augment"
        )
    episodes = read_json_object(path, "Recording provenance").get("episodes")
    if not isinstance(episodes, list) or not all(
        isinstance(e, dict) and isinstance(e.get("seed"), int) for e in episodes
    ):
        raise ValueError(f"{path}: its episodes do not list their seeds; the file is damaged")
    return {e["seed"] for e in episodes}


def check_layouts(cfg: CompareConfig, arms: list[Arm]) -> None:
    """No held-out layout may be one a recording of the comparison trained on. Checked before training and
    evaluating, on the recordings the flags name (a path read from a finished run's config is not opened)."""
    held_out = set(cfg.layouts())
    roots = {
        DatasetRefConfig(repo_id=a.setting["dataset.repo_id"], root=a.setting["dataset.root"]).path()
        for a in arms
        if a.source == "flags"
    }
    for root in sorted(roots):
        shared = sorted(training_seeds(root) & held_out)
        if shared:
            raise ValueError(
                f"--dataset.root={root} trained on {len(shared)} of the held-out layouts (seeds "
                f"{', '.join(map(str, shared[:5]))}{', ...' if len(shared) > 5 else ''}); "
                f"allowed: --eval.seed_offset past the recording's seeds (default {HELD_OUT_SEED_OFFSET})"
            )


def train_command(cfg: CompareConfig, arm: Arm, run: Path, seed: int) -> list[str]:
    last = run / "checkpoints" / "last" / "pretrained_model" / "train_config.json"
    if last.exists():
        return [console_script("condground"), "train", f"--config_path={last}", "--resume=true"]
    data = [f"--dataset.root={cfg.dataset.root}"] if cfg.dataset.root else []
    return [
        console_script("condground"), "train", "--policy.type=act_modified", f"--policy.variant={cfg.train.variant}",
        "--policy.device=cpu", "--policy.push_to_hub=false", *policy_flags(), *speed_flags(),
        f"--batch_size={CPU_BATCH_SIZE}", f"--dataset.repo_id={cfg.dataset.repo_id or f'local/{cfg.env.task}'}", *data,
        f"--steps={cfg.train.steps}", f"--save_freq={cfg.train.save_freq}", *shlex.split(cfg.train.flags),
        *arm.flags, "--log_freq=100", "--num_workers=0", "--wandb.enable=false", f"--seed={seed}",
        f"--output_dir={run}",
    ]  # fmt: skip


def train(cfg: CompareConfig, arms: list[Arm]) -> None:
    """Every unfinished run of the arms trained here, all at once, each on --train.threads torch threads."""
    from tqdm import tqdm

    env = {**os.environ, "OMP_NUM_THREADS": str(cfg.train.threads), "MKL_NUM_THREADS": str(cfg.train.threads)}
    running = []
    for arm in arms:
        if arm.source != "flags":
            continue
        for seed, run in zip(cfg.seeds(), arm.runs, strict=True):
            if checkpoint(run, arm.pooled[-1]).exists():
                continue
            run.parent.mkdir(parents=True, exist_ok=True)
            command = train_command(cfg, arm, run, seed)
            log = open(run.with_suffix(".log"), "a")  # noqa: SIM115 (closed when the run ends)
            log.write(f"\n# {time.strftime('%F %T')} {shlex.join(command)}\n")
            log.flush()
            process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=env)
            running.append((run, process, log, arm.pooled[-1], int(arm.setting["save_freq"])))
    if not running:
        return

    def saved() -> int:
        return sum(len(list((run / "checkpoints").glob("[0-9]*"))) for run, *_ in running)

    total = sum(steps // every for *_, steps, every in running)
    with tqdm(total=total, initial=saved(), desc="train (checkpoints)", disable=not cfg.progress) as bar:
        while any(process.poll() is None for _, process, *_ in running):
            time.sleep(5)
            bar.update(saved() - bar.n)
    for run, process, log, steps, _ in running:
        log.close()
        if process.returncode or not checkpoint(run, steps).exists():
            raise RuntimeError(f"training {run.name} failed (rc {process.returncode}); see {run}.log")


def eval_dir(cfg: CompareConfig, run: Path, step: int) -> Path:
    return Path(cfg.output_dir) / "eval" / run.name / f"{step:06d}"


def swept(results: Path, conditions: list[str]) -> bool:
    """Whether a sweep's table holds every condition asked for (a sweep resumes, so a new condition is added)."""
    return results.exists() and set(conditions) <= set(read_table(results)["condition"])


def _env_flags(cfg: CompareConfig) -> list[str]:
    env = cfg.env
    sizes = [
        f"--env.observation_{k}={v}"
        for k, v in (("height", env.observation_height), ("width", env.observation_width))
        if v
    ]
    return [
        f"--env.task={env.task}", f"--env.servo={env.servo}", f"--env.episode_length={env.episode_length}",
        f"--env.fps={env.fps}", f"--env.counterbalanced={str(env.counterbalanced).lower()}",
        f"--env.camera_codec={env.camera_codec}", *sizes,
    ]  # fmt: skip


def run_all(commands: list[list[str]], jobs: int, desc: str, progress: bool) -> None:
    """Runs the commands, `jobs` at a time; stops at the first that fails, with its last lines."""
    from tqdm import tqdm

    queue, running = list(commands), []
    with tqdm(total=len(commands), desc=desc, disable=not progress or not commands) as bar:
        while queue or running:
            while queue and len(running) < jobs:
                command = queue.pop(0)
                running.append(
                    subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
                )
            time.sleep(1)
            for process in [p for p in running if p.poll() is not None]:
                running.remove(process)
                err = process.stderr.read()
                if process.returncode:
                    for other in running:
                        other.terminate()
                    raise RuntimeError(f"failed: {shlex.join(process.args)}\n{err[-2000:]}")
                bar.update(1)


def evaluate(cfg: CompareConfig, arms: list[Arm]) -> None:
    """One sweep per pooled checkpoint of every run, each resumable, --eval.jobs at once."""
    conditions, commands = cfg.conditions(), []
    for arm in arms:
        for run in arm.runs:
            for step in arm.pooled:
                out = eval_dir(cfg, run, step)
                if swept(out / "results.parquet", conditions):
                    continue
                if not checkpoint(run, step).is_dir():
                    raise FileNotFoundError(
                        f"{checkpoint(run, step)}: the run has no checkpoint at step {step}"
                    )
                commands.append([
                    console_script("condground"), "sweep", f"--policy.paths={checkpoint(run, step)}", *_env_flags(cfg),
                    f"--sweep.conditions={','.join(conditions)}", "--eval.seeds=1",
                    f"--eval.n_episodes={cfg.eval.episodes}", f"--eval.seed_offset={cfg.eval.seed_offset}",
                    "--workers=1", f"--output_dir={out}", "--progress=false",
                ])  # fmt: skip
    run_all(commands, cfg.eval.jobs, "evaluate (sweeps)", cfg.progress)


def outcomes(
    cfg: CompareConfig, arm: Arm, index: int, step: int, condition: str, published=None
) -> pd.DataFrame:
    """The rollouts of the arm's index-th run at `step` under `condition`, on the held-out layouts."""
    if arm.source == "rollouts":
        seed = sorted(published["seed"].unique())[index]
        frame = published[
            published["seed"].eq(seed) & published["step"].eq(step) & published["condition"].eq(condition)
        ]
        where = f"--{arm.name}.rollouts"
    else:
        results = eval_dir(cfg, arm.runs[index], step) / "results.parquet"
        table = read_table(results)
        frame, where = table[table["condition"].eq(condition)], str(results)
    frame = frame[frame["layout_seed"].isin(cfg.layouts())]
    if len(frame) != cfg.eval.episodes or frame["layout_seed"].nunique() != cfg.eval.episodes:
        raise ValueError(
            f"{where} has {len(frame)} rollouts of {arm.name} (run {index}, step {step}) under {condition} on the "
            f"held-out layouts; allowed: one on each of the {cfg.eval.episodes} layouts from seed {cfg.eval.seed_offset}"
        )
    return frame.sort_values("layout_seed").reset_index(drop=True)


def comparison_dir(cfg: CompareConfig) -> Path:
    return Path(cfg.output_dir) / "comparisons" / f"{cfg.env.task}_{cfg.treated.name}_vs_{cfg.baseline.name}"


def analyse(cfg: CompareConfig, arms: list[Arm], found: list[str]) -> pd.DataFrame:
    """Pairs the arms under each condition; writes the comparison folder (and --table); returns summary rows."""
    base, treated = arms
    published = (
        published_rollouts(Path(cfg.baseline.rollouts), base.name, cfg.env.task)
        if base.source == "rollouts"
        else None
    )
    rollouts, per_checkpoint, rows = [], [], []
    for condition in cfg.conditions():
        columns = {}
        for arm in arms:
            columns[arm.name] = []
            for index, seed in enumerate(cfg.seeds()):
                for step in arm.pooled:
                    frame = outcomes(cfg, arm, index, step, condition, published)
                    columns[arm.name].append(frame[["layout_seed", "success"]].assign(run=index))
                    rollouts.append(
                        frame.assign(arm=arm.name, condition=condition, run=index, seed=seed, step=step)
                    )
                    r = rate(int(frame["success"].sum()), len(frame))
                    per_checkpoint.append(
                        {"lever": arm.name, "task": cfg.env.task, "condition": condition, "seed": seed, "step": step,
                         "success": r["rate"], "n": r["n"], "ci_low": r["low"], "ci_high": r["high"]}
                    )  # fmt: skip
        a = pd.concat([c["success"] for c in columns[base.name]]).to_numpy()
        b = pd.concat([c["success"] for c in columns[treated.name]]).to_numpy()
        d = paired_difference(a, b)
        c = clustered_difference(
            *(pd.concat(columns[x.name]).rename(columns={"layout_seed": "layout"}) for x in arms)
        )
        rows.append(
            {"lever": treated.name, "task": cfg.env.task, "condition": condition, "baseline_arm": base.name,
             "seeds": len(cfg.seeds()), "n": d["n"], "baseline": d["rate_a"], "treated": d["rate_b"],
             "diff": d["diff"], "diff_low": d["low"], "diff_high": d["high"], "p": d["p_value"],
             "cluster_low": c["low"], "cluster_high": c["high"], "cluster_p": c["p_value"],
             "seed_effects": " ".join(f"{e:+.4f}" for e in c["seed_effects"]),
             "flags": shlex.join(treated.flags), "steps": treated.setting["steps"],
             "checkpoints": " ".join(map(str, treated.pooled)), "differences": "; ".join(found)}
        )  # fmt: skip
    summary = pd.DataFrame(rows, columns=SUMMARY_COLUMNS)
    every = pd.concat(rollouts, ignore_index=True)
    own = every[every["arm"].isin([a.name for a in arms if a.source != "rollouts"])]
    funnel = cell_metrics(own.assign(lever=own["arm"], task=cfg.env.task), by=("lever", "task", "condition"))
    funnel = funnel[
        ["lever", "task", "condition", "episodes", *(f"{m}{s}" for m in METRICS for s in ("", "_k", "_n"))]
    ]
    checkpoints = pd.DataFrame(per_checkpoint)
    out = comparison_dir(cfg)
    out.mkdir(parents=True, exist_ok=True)
    keep = [c for c in every.columns if c not in ("lever", "task")]
    every[keep].to_parquet(out / "rollouts.parquet", index=False)
    summary.to_csv(out / "summary.csv", index=False, float_format="%.4f")
    checkpoints.to_csv(out / "checkpoints.csv", index=False, float_format="%.4f")
    funnel.to_csv(out / "funnel.csv", index=False, float_format="%.4f")
    plot_checkpoints(checkpoints, out / "compare.png", f"{cfg.env.task}: {treated.name} against {base.name}")
    (out / "compare.json").write_text(json.dumps(manifest(cfg, arms, found, summary), indent=1, default=str))
    if cfg.table:
        publish(cfg, arms, summary, checkpoints, every, funnel)
    return summary


def manifest(cfg: CompareConfig, arms: list[Arm], found: list[str], summary: pd.DataFrame) -> dict:
    return {
        "kind": "compare", "task": cfg.env.task, "command": command_line("compare", cfg),
        "arms": {a.name: {"source": a.source, "flags": a.flags, "runs": [str(r) for r in a.runs], "setting": a.setting,
                          "checkpoints": a.pooled} for a in arms},
        "seeds": cfg.seeds(), "conditions": cfg.conditions(), "layouts": [cfg.layouts().start, cfg.layouts().stop],
        "differences": found, "summary": summary.to_dict("records"), "figure": "compare.png", "versions": versions(),
    }  # fmt: skip


def merge_csv(
    path: Path, rows: pd.DataFrame, names, column: str = "lever", baseline=None, fmt="%.4f"
) -> pd.DataFrame:
    """Writes `rows` to `path` in place of its earlier rows of these names on their task (and against this
    baseline arm, when given: one lever may be paired against two baselines; and under these conditions: a
    comparison scored under fewer conditions keeps the others' rows); returns the table."""
    table = rows
    if path.exists():
        old = pd.read_csv(path)
        replaced = old["task"].isin(set(rows["task"])) & old[column].isin(list(names))
        if baseline is not None and "baseline_arm" in old:
            replaced &= old["baseline_arm"].eq(baseline)
        if "condition" in rows and "condition" in old:
            replaced &= old["condition"].fillna("clean").isin(set(rows["condition"]))
        table = pd.concat([old[~replaced], rows], ignore_index=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    table.to_csv(path, index=False, float_format=fmt)
    return table


def _tables(cfg: CompareConfig) -> list[Path]:
    """--table and the companion tables `publish` and `failures` merge into."""
    if not cfg.table:
        return []
    path = Path(cfg.table)
    return [
        path,
        *(
            path.with_name(f"{path.stem}_{kind}.csv")
            for kind in ("checkpoints", "rollouts", "funnel", "failures")
        ),
    ]


def check_table(path: Path) -> None:
    """A table a comparison merges into must be one it could have written: a user's other file is refused
    before any work (merging would overwrite it)."""
    if path.suffix != ".csv":
        raise ValueError(
            f"--table={path} is not allowed; allowed: a .csv file (a lever table, new or existing)"
        )
    if not path.exists():
        return
    try:
        columns = set(pd.read_csv(path, nrows=1).columns) if path.is_file() else set()
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError):
        columns = set()
    if not {"lever", "task"} <= columns:
        raise ValueError(
            f"{path} exists and is not a lever table (no lever and task columns); allowed: a table an earlier "
            "comparison wrote, or a new path"
        )


def publish(cfg, arms, summary, checkpoints, every, funnel) -> None:
    """The summary into --table (Holm over every comparison the table holds: one family), and the arms
    trained or evaluated here into its companion tables (a published baseline's rows stay as they were)."""
    path = Path(cfg.table)
    table = merge_csv(path, summary, [cfg.treated.name], baseline=cfg.baseline.name)
    table.assign(holm_p=holm(table["cluster_p"])).to_csv(path, index=False, float_format="%.4f")
    own = [a.name for a in arms if a.source != "rollouts"]
    mine = merge_csv(
        path.with_name(f"{path.stem}_checkpoints.csv"), checkpoints[checkpoints["lever"].isin(own)], own
    )
    rollouts = every[every["arm"].isin(own)].assign(lever=lambda f: f["arm"], task=cfg.env.task)
    merge_csv(
        path.with_name(f"{path.stem}_rollouts.csv"),
        rollouts[["lever", "task", "condition", "seed", "step", "layout_seed", "success"]].astype({"success": int}), own,
    )  # fmt: skip
    merge_csv(path.with_name(f"{path.stem}_funnel.csv"), funnel, own)
    clean = mine["condition"].fillna("clean").eq("clean") & mine["task"].eq(cfg.env.task)
    plot_checkpoints(mine[clean], path.with_name(f"{path.stem}_{cfg.env.task}.png"), cfg.env.task)


def plot_checkpoints(rows: pd.DataFrame, path: Path, title: str) -> None:
    """Held-out success of every checkpoint with its interval, one panel per condition, a colour per arm."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = (
        rows.assign(condition=rows["condition"].fillna("clean"))
        if "condition" in rows
        else rows.assign(condition="clean")
    )
    conditions = list(dict.fromkeys(rows["condition"]))
    arms = list(dict.fromkeys(rows["lever"]))
    fig, axes = plt.subplots(1, len(conditions), figsize=(4.5 * len(conditions) + 2, 3.6), squeeze=False)
    span = rows["step"].max() - rows["step"].min()
    gap = (span / max(rows["step"].nunique() - 1, 1)) * 0.6 / max(len(arms), 1)
    for ax, condition in zip(axes[0], conditions, strict=True):
        for i, arm in enumerate(arms):
            for j, (seed, run) in enumerate(
                rows[rows["condition"].eq(condition) & rows["lever"].eq(arm)].groupby("seed")
            ):
                run = run.sort_values("step")
                ax.errorbar(run["step"] + gap * (i - (len(arms) - 1) / 2), run["success"] * 100,
                            yerr=[(run["success"] - run["ci_low"]) * 100, (run["ci_high"] - run["success"]) * 100],
                            color=plt.cm.tab10(i % 10), marker="os^v"[j % 4], capsize=2, label=f"{arm}, seed {seed}")  # fmt: skip
        ax.set(xlabel="training steps", ylabel=f"held-out success under {condition} (%)", ylim=(-5, 105))
    axes[0][-1].legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def failures(cfg: CompareConfig, arms: list[Arm]) -> pd.DataFrame:
    """`condground failures` of every run's last checkpoint on the held-out layouts: each failure's cause."""
    todo = [
        (arm, seed, run, Path(cfg.output_dir) / "failures" / run.name)
        for arm in arms for seed, run in zip(cfg.seeds(), arm.runs, strict=True)
    ]  # fmt: skip
    run_all(
        [
            [console_script("condground"), "failures", f"--policy.path={checkpoint(run, arm.pooled[-1])}", f"--env.task={cfg.env.task}",
             f"--env.servo={cfg.env.servo}", f"--failures.episodes={cfg.eval.episodes}",
             f"--failures.seed_offset={cfg.eval.seed_offset}", f"--output_dir={out}", "--progress=false"]
            for arm, seed, run, out in todo
            if not (out / "failures.json").exists()
        ],
        cfg.eval.jobs, "failures", cfg.progress,
    )  # fmt: skip
    rows = []
    for arm, seed, _, out in todo:
        result = read_json_object(out / "failures.json", "Failure analysis")
        offsets, carry = result["first_close_offset_cm"], result["carry"]
        rows.append(
            {"lever": arm.name, "task": cfg.env.task, "seed": seed, "step": arm.pooled[-1], "rollouts": result["rollouts"],
             **result["causes"], "regrasped": result["regrasped"], "stalled": result["stalled"],
             "close_offset_cm_success": offsets["success_median"], "close_offset_cm_failure": offsets["failure_median"],
             "released": carry["released"], "slipped": carry["slipped"], "held_to_end": carry["held_to_end"],
             "release_offset_cm_success": carry["release_offset_cm"]["success_median"],
             "release_offset_cm_failure": carry["release_offset_cm"]["failure_median"]}
        )  # fmt: skip
    table = pd.DataFrame(rows)
    if table.empty:
        return table
    out = comparison_dir(cfg)
    out.mkdir(parents=True, exist_ok=True)
    table.to_csv(out / "failures.csv", index=False, float_format="%.2f")
    if cfg.table:
        path = Path(cfg.table)
        merge_csv(path.with_name(f"{path.stem}_failures.csv"), table, [a.name for a in arms], fmt="%.2f")
    return table


def run(cfg: CompareConfig) -> pd.DataFrame | None:
    arms = [resolve_arm(cfg, cfg.baseline), resolve_arm(cfg, cfg.treated)]
    runs = [run.resolve() for arm in arms for run in arm.runs]
    if len(set(runs)) != len(runs):
        twice = next(r for r in runs if runs.count(r) > 1)
        raise ValueError(f"the run {twice} is given twice; allowed: each training run in one arm, once")
    for path in _tables(cfg):
        check_table(path)
    found = differences(*arms)
    if found and not cfg.allow_differences:
        raise ValueError(
            f"{arms[0].name} and {arms[1].name} differ in budget or data ({'; '.join(found)}); allowed: the same "
            "budget and data, or --allow_differences=true (the differences are then written beside the result)"
        )
    if cfg.stage in ("all", "train", "evaluate"):
        check_layouts(cfg, arms)
    for arm in arms:
        logging.info(
            "%s: %s, checkpoints %s pooled, %s", arm.name, arm.source, arm.pooled,
            shlex.join(arm.flags) or "no flags of its own",
        )  # fmt: skip
    if cfg.stage in ("all", "train"):
        train(cfg, arms)
    if cfg.stage in ("all", "evaluate"):
        evaluate(cfg, [a for a in arms if a.source != "rollouts"])
    summary = None
    if cfg.stage in ("all", "analyse"):
        summary = analyse(cfg, arms, found)
    if (cfg.failures and cfg.stage == "all") or cfg.stage == "failures":
        failures(cfg, [a for a in arms if a.source != "rollouts"])
    return summary
