"""The paper's experiment as a plan: presets, the settings they resolve to, the stages and their estimated time.

A stage is one command (`condground record`, the stock `lerobot-train`, `condground sweep`, `diagnose`,
`probe`, `report`) writing into its own directory; it runs when the stages it reads are done. Estimates
come from rates measured on the 2-core development machine (docs/measurements.md), so they say what a run
costs there and scale with this machine's cores.
"""

from __future__ import annotations

import heapq
from dataclasses import asdict, dataclass, field
from pathlib import Path

from lerobot_condground.core.conditions import TASKS, check_task
from lerobot_condground.core.configs import check_at_least, comma_items, usable_cores
from lerobot_condground.core.paper import METHODS, TABLE2_COLUMN
from lerobot_condground.core.training import (
    CPU_BATCH_SIZE,
    CPU_DRIFT_STD,
    CPU_EPISODES,
    CPU_FRAME_SIZE,
    CPU_STEPS,
    native_bf16,
    policy_flags,
)
from lerobot_condground.core.ur3e import check_servo

VARIANT_ORDER = ("standard", "full", "augmentation", "augmentation_attention")

# Preset values; every one is also a flag (a flag given wins). `policy` is the preset's lerobot-train policy
# flags, before --train.extra_flags.
PRESETS: dict[str, dict] = {
    # What fits the 2-core CPU machine in several sessions: the CPU training configuration
    # (lerobot_condground/core/training.py: its recovery data and step budget), the protocol of
    # docs/learning-curve/v3 (two training seeds, the last three checkpoints of each pooled on the same 50
    # held-out layouts: 300 rollouts a condition), the conditions that carry the paper's claims.
    "cpu": {
        "tasks": "PickPlaceRandomBin-v0,PickPlaceFixedBin-v0",
        "record.episodes": CPU_EPISODES,
        "record.drift_std": CPU_DRIFT_STD,
        "record.observation_height": CPU_FRAME_SIZE[0],
        "record.observation_width": CPU_FRAME_SIZE[1],
        "takeover.episodes": 0,
        "takeover.driver_steps": CPU_STEPS // 2,
        "train.variants": ",".join(VARIANT_ORDER),
        "train.seeds": 2,
        "train.steps": CPU_STEPS,
        "train.batch_size": CPU_BATCH_SIZE,
        "train.save_freq": CPU_STEPS // 6,
        "train.num_workers": 0,
        "train.device": "cpu",
        "eval.conditions": "clean,full_mixed,object_color_3,receptacle_shape_2,object_neither_3",
        "eval.counterbalanced": "full_mixed",
        "eval.seeds": 1,
        "eval.n_episodes": 50,
        "eval.batch_size": 10,
        "eval.pool": 3,
        "diagnose.pairs": 20,
        "probe.episodes": 50,
        "jobs": 2,
        "policy": policy_flags(),
    },
    # The paper's protocol (Results): 3 training seeds x 4 evaluation seeds x 50 rollouts over the full
    # 20-condition grid, at LeRobot's ACT defaults (ImageNet ResNet-18, dim 512, chunk 100, CVAE) and the
    # env's 240x320 camera, 100k steps of batch 8 (LeRobot's ACT recipe). A GPU machine's job.
    "paper": {
        "tasks": "PickPlaceRandomBin-v0,PickPlaceFixedBin-v0",
        "record.episodes": 100,
        "record.drift_std": 0.0,  # the paper's clean demonstrations
        "record.observation_height": 240,
        "record.observation_width": 320,
        "takeover.episodes": 0,
        "takeover.driver_steps": 50_000,
        "train.variants": ",".join(VARIANT_ORDER),
        "train.seeds": 3,
        "train.steps": 100_000,
        "train.batch_size": 8,
        "train.save_freq": 10_000,
        "train.num_workers": 4,
        "train.device": None,  # LeRobot picks the best device
        "eval.conditions": "paper",
        "eval.counterbalanced": "full_mixed",
        "eval.seeds": 4,
        "eval.n_episodes": 50,
        "eval.batch_size": 10,
        "eval.pool": 1,  # the paper evaluates each run's final policy
        "diagnose.pairs": 20,
        "probe.episodes": 50,
        "jobs": 1,
        "policy": [],
    },
}

# Rates measured on the 2-core development machine (AMD EPYC, AVX2), per core, by frame size of the preset's
# model. Training samples/s, cpu: `standard` at ACT's own size from the learning runs (1.0 step/s of batch 16 a
# run, two side by side: docs/learning-curve/v2, nineteenth session), the other variants scaled by their rate
# against `standard` in one `condground bench` run (augmentation 0.96, augmentation_attention 0.96, full 0.78;
# docs/measurements.md); paper: `condground bench`'s policy cost at ACT's default size (2 cores, halved).
TRAIN_SAMPLES_PER_CORE_S = {
    "cpu": {"standard": 16.0, "augmentation": 15.4, "augmentation_attention": 15.3, "full": 12.4},
    "paper": {"standard": 1.8, "augmentation": 1.7, "augmentation_attention": 1.7, "full": 1.6},
    # cpu on a CPU that multiplies bf16 natively, where the preset trains under bf16 autocast
    # (core.training.speed_flags): the 6000-step runs of docs/learning-curve/v3 on the Zen 5 EPYC, two side by
    # side, whole-run means (standard 2.37 steps/s, augmentation 1.82, full 1.81; augmentation_attention not
    # timed there, taken as augmentation).
    "cpu_bf16": {"standard": 37.9, "augmentation": 29.1, "augmentation_attention": 29.1, "full": 29.0},
}
# The quickstart trained this model on both cores' two torch threads at 28.7 samples/s (twenty-first session, steps
# 300-3000, docs/quickstart.md), against 16.0 for each of two one-thread runs side by side: a run on t threads goes
# t**0.84 times as fast (the smaller model before 2026-12-04: 60 against 41, t**0.55).
THREAD_SCALING = 0.84
# Rollouts per minute per core (sweep workers scale linearly: x2.06 on 2): at ACT's own size, 96x128, six sweeps
# of 50 Task 2 rollouts (a 60 % policy: shorter than a failing one's 300 steps, so an upper bound) in 14.8
# minutes two at a time (nineteenth session; Task 1 at 75 %: 12.3 minutes);
# the sweep benchmark at 240x320 (25.7 per minute for 100-step episodes; up to 300 here).
ROLLOUTS_PER_CORE_MIN = {"cpu": 10.0, "paper": 8.6}
# One core's seconds per recorded episode (labels and video), spread over at most 2 (one recording process;
# the software renderer's threads are what use the second). paper: 100 clean episodes at 240x320 in 395 s on
# 2 cores; cpu: at 96x128 on the 2-core EPYC, 100 drift and 5 clean episodes in 199 s (the quickstart, twenty-first
# session), and two drift recordings at once, 100 each, in 205 s (twenty-second).
RECORD_CORE_S_PER_EPISODE = {"cpu": 3.8, "paper": 7.9}
# 300 recorded episodes (24 153 frames at 96x128) merged in 5 minutes beside two trainings.
MERGE_S_PER_EPISODE = 1.0
DIAGNOSE_S_PER_PAIR = 5.8  # Task 2 standard, 20 pairs at 96x128 in 115 s on one core beside a training
REPORT_S = 60.0


@dataclass
class RecordSettings:
    # Expert demonstrations per task, recorded with this joint drift (rad, record's --drift.std; 0: clean).
    episodes: int | None = None
    drift_std: float | None = None
    observation_height: int | None = None
    observation_width: int | None = None


@dataclass
class TakeoverSettings:
    # One DAgger round before the variants train (`condground record --takeover.*`): `standard` trains
    # --takeover.driver_steps on the demonstrations, drives this many episodes from new layouts until the
    # scripted expert takes over and finishes, and the variants train on the demonstrations and these merged
    # (`condground merge`). 0: the variants train on the demonstrations alone.
    episodes: int | None = None
    driver_steps: int | None = None


# Takeover episodes draw their layouts from this seed on: past the demonstrations' (0, 1, ...: at most
# MAX_EPISODES and their failures), below the held-out layouts `condground sweep` draws.
TAKEOVER_SEED = 500_000


@dataclass
class TrainSettings:
    # act_modified variants, separated by commas (standard, augmentation, augmentation_attention, full).
    variants: str | None = None
    seeds: int | None = None  # training seeds 0..seeds-1 per task and variant
    steps: int | None = None
    batch_size: int | None = None
    save_freq: int | None = None  # steps between checkpoints: a killed run loses at most this many
    num_workers: int | None = None
    device: str | None = None
    # More lerobot-train flags, separated by spaces, after the preset's (e.g. "--policy.dim_model=256").
    extra_flags: str = ""


@dataclass
class EvalSettings:
    # `paper` (all 20) or condition names separated by commas.
    conditions: str | None = None
    # Conditions evaluated again with counterbalanced assets (colors and shapes permuted); "" for none.
    counterbalanced: str | None = None
    seeds: int | None = None  # evaluation seeds per checkpoint
    n_episodes: int | None = None  # rollouts per evaluation seed
    batch_size: int | None = None
    episode_length: int = 300  # env steps before a rollout counts as failed
    # The last checkpoints of each training run swept on the same layouts and pooled (the protocol: 3); one
    # run's late checkpoints swing by up to 20 points here, so a single one says little.
    pool: int | None = None


@dataclass
class DiagnoseSettings:
    pairs: int | None = None  # matched clean/distractor episode pairs (Table II), Task 2


@dataclass
class ProbeSettings:
    episodes: int | None = None  # layouts of the prompt-swap probe, variants with prompts


@dataclass
class EnvSettings:
    # How joint targets reach the simulated servos, in the recordings and every evaluation: interpolated
    # (as the UR3e) or direct (reproductions made before this setting existed).
    servo: str = "interpolated"


@dataclass
class ReproduceConfig:
    preset: str = "cpu"
    output_dir: str = "outputs/reproduce"
    # Tasks, separated by commas, in the order they run.
    tasks: str | None = None
    env: EnvSettings = field(default_factory=EnvSettings)
    record: RecordSettings = field(default_factory=RecordSettings)
    takeover: TakeoverSettings = field(default_factory=TakeoverSettings)
    train: TrainSettings = field(default_factory=TrainSettings)
    eval: EvalSettings = field(default_factory=EvalSettings)
    diagnose: DiagnoseSettings = field(default_factory=DiagnoseSettings)
    probe: ProbeSettings = field(default_factory=ProbeSettings)
    # Stages run side by side, each on cores/jobs threads (training) or workers (evaluation).
    jobs: int | None = None
    # Print the plan (stages, counts, estimated time here) and stop.
    dry_run: bool = False
    progress: bool = True

    def __post_init__(self):
        if self.preset not in PRESETS:
            raise ValueError(f"--preset={self.preset!r} is not allowed; allowed: {', '.join(PRESETS)}")
        if not self.output_dir.strip():
            raise ValueError("--output_dir is empty; allowed: a directory for every stage's outputs")
        preset = PRESETS[self.preset]
        if self.jobs is None:  # the preset's count, but never more stages than cores this process may use
            self.jobs = min(preset["jobs"], usable_cores())
        for key, value in preset.items():
            group, _, name = key.rpartition(".")
            owner = getattr(self, group) if group else self
            if key != "policy" and getattr(owner, name) is None:
                setattr(owner, name, value)
        for task in self.task_list():
            check_task(task)
        check_servo(self.env.servo, "--env.servo")
        self.variant_list()
        check_at_least(self.record, "record.", episodes=1, observation_height=1, observation_width=1)
        # What each stage's own command would refuse, refused here: pinned in reproduce.json, a value the
        # first stage fails on would block the corrected rerun.
        self._check_stage_limits()
        check_at_least(self.takeover, "takeover.", episodes=0, driver_steps=1)
        check_at_least(self.train, "train.", seeds=1, steps=1, batch_size=1, save_freq=1, num_workers=0)
        check_at_least(self.eval, "eval.", seeds=1, n_episodes=1, batch_size=1, episode_length=1, pool=1)
        self.pooled_steps()
        check_at_least(self.diagnose, "diagnose.", pairs=1)
        check_at_least(self.probe, "probe.", episodes=1)
        check_at_least(self, "", jobs=1)
        for flag in self.train.extra_flags.split():
            if not flag.startswith("--") or "=" not in flag:
                raise ValueError(
                    f"--train.extra_flags holds {flag!r}; allowed: lerobot-train flags --key=value separated by spaces"
                )
            key, value = flag.split("=", 1)
            _check_yaml_value(flag, value)
            if key in DEFEATING_TRAIN_FLAGS and DEFEATING_TRAIN_FLAGS[key](value):
                raise ValueError(
                    f"--train.extra_flags holds {flag!r}, which defeats every training stage ({DEFEATS[key]}); "
                    "allowed: any other lerobot-train flag"
                )
            if key in STAGE_TRAIN_FLAGS:
                instead = STAGE_TRAIN_FLAGS[key]
                raise ValueError(
                    f"--train.extra_flags holds {flag!r}, which each training stage sets itself after the extra "
                    f"flags (it would be ignored); allowed: any other lerobot-train flag"
                    + (f"; use {instead} instead" if instead else "")
                )
        self.condition_lists()

    def _check_stage_limits(self) -> None:
        from lerobot_condground.datasets.record import MAX_DRIFT_STD, MAX_EPISODES
        from lerobot_condground.envs.arm_env import check_resolution
        from lerobot_condground.evaluation.units import EPISODES_PER_SEED_LIMIT

        try:
            check_resolution(self.record.observation_height, self.record.observation_width)
        except ValueError as err:
            raise ValueError(f"--record.observation_height/width: {err}") from None
        for flag, value, limit in (
            ("--record.episodes", self.record.episodes, MAX_EPISODES),
            ("--takeover.episodes", self.takeover.episodes, MAX_EPISODES),
            ("--eval.n_episodes", self.eval.n_episodes, EPISODES_PER_SEED_LIMIT),
        ):
            if value > limit:
                raise ValueError(
                    f"{flag}={value} is not allowed; allowed: 1 to {limit} (the stage's own limit)"
                )
        if not 0.0 <= self.record.drift_std <= MAX_DRIFT_STD:
            raise ValueError(
                f"--record.drift_std={self.record.drift_std} is not allowed; allowed: 0 (clean) to "
                f"{MAX_DRIFT_STD} rad (the stage's own limit)"
            )

    def task_list(self) -> list[str]:
        return _split(self.tasks, "--tasks", TASKS)

    def variant_list(self) -> list[str]:
        return _split(self.train.variants, "--train.variants", VARIANT_ORDER)

    def condition_lists(self) -> tuple[list[str], list[str]]:
        """The conditions swept plainly, and those swept counterbalanced (may be none)."""
        from lerobot_condground.evaluation.sweep import parse_conditions

        counterbalanced = self.eval.counterbalanced
        return parse_conditions(self.eval.conditions), parse_conditions(
            counterbalanced
        ) if counterbalanced.strip() else []

    def pooled_steps(self) -> list[int]:
        """The steps of the checkpoints each run's sweep pools: the last --eval.pool that lerobot-train
        saves (every --train.save_freq steps and at the last step)."""
        saved = sorted(
            {*range(self.train.save_freq, self.train.steps + 1, self.train.save_freq), self.train.steps}
        )
        if self.eval.pool > len(saved):
            raise ValueError(
                f"--eval.pool={self.eval.pool} is not allowed with --train.steps={self.train.steps} and "
                f"--train.save_freq={self.train.save_freq}, which save {len(saved)} checkpoint(s); allowed: 1 to "
                f"{len(saved)}, or a smaller --train.save_freq"
            )
        return saved[-self.eval.pool :]

    def policy_flags(self) -> list[str]:
        return [*PRESETS[self.preset]["policy"], *self.train.extra_flags.split()]

    def pinned(self) -> dict:
        """The settings that shape results: a rerun on the same directory must keep them. Which tasks and
        variants run may grow (each has its own stages); how many stages run side by side may change."""
        settings = asdict(self)
        for key in ("tasks", "jobs", "dry_run", "progress", "output_dir"):
            settings.pop(key)
        settings["train"].pop("variants")
        if not self.takeover.episodes:  # as reproductions from before the setting: demonstrations alone
            settings.pop("takeover")
        settings["policy_flags"] = self.policy_flags()
        return settings


def _check_yaml_value(flag: str, value: str) -> None:
    """draccus reads each value as YAML: one it cannot scan (a backquote, `$(...)`, a stray quote) is named
    with its character here, not as a YAML traceback from the pre-check's parse."""
    import yaml

    try:
        yaml.safe_load(value)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        at = (
            f" at {value[mark.column]!r} (character {mark.column + 1})"
            if mark and mark.column < len(value)
            else ""
        )
        raise ValueError(
            f"--train.extra_flags holds {flag!r}, whose value YAML cannot read{at}; allowed: a plain value, or "
            "one in quotes YAML reads"
        ) from None


# lerobot-train flags that would leave a training stage nothing to hand on, and why.
DEFEATING_TRAIN_FLAGS = {
    "--save_checkpoint": lambda value: value.strip().lower() in ("false", "no", "off", "0"),
    "--policy.path": lambda value: True,
    "--policy.pretrained_path": lambda value: True,
}
DEFEATS = {
    "--save_checkpoint": "no checkpoint is saved, and every later stage reads the training's checkpoints",
    "--policy.path": "the stage would train the policy it names instead of the plan's variant",
    "--policy.pretrained_path": "the stage would start from weights the plan does not record",
}
# lerobot-train flags a training stage sets after --train.extra_flags, with the reproduce flag that sets each.
STAGE_TRAIN_FLAGS = {
    "--policy.type": None,
    "--policy.variant": "--train.variants",
    "--policy.device": "--train.device",
    "--policy.push_to_hub": None,
    "--dataset.repo_id": None,
    "--dataset.root": None,
    "--batch_size": "--train.batch_size",
    "--steps": "--train.steps",
    "--save_freq": "--train.save_freq",
    "--log_freq": None,
    "--num_workers": "--train.num_workers",
    "--wandb.enable": None,
    "--seed": "--train.seeds",
    "--output_dir": "--output_dir",
    "--config_path": None,
    "--resume": None,
}


def _split(text: str, flag: str, allowed: tuple[str, ...]) -> list[str]:
    items = comma_items(text, flag)
    for item in items:
        if item not in allowed:
            raise ValueError(f"{flag} holds {item!r}; allowed: {', '.join(allowed)}, separated by commas")
    if not items or len(set(items)) != len(items):
        raise ValueError(
            f"{flag}={text!r} is not allowed; allowed: each of {', '.join(allowed)} at most once"
        )
    return items


# Stages that make the data and checkpoints the results are measured on: the report reads none of them.
DATA_KINDS = ("record", "driver", "takeover", "merge", "train")


@dataclass
class Stage:
    name: str  # e.g. train/PickPlaceRandomBin-v0/full/seed0; also its directory under --output_dir
    kind: str  # one of DATA_KINDS, sweep, sweep_counterbalanced, diagnose, probe, report
    after: tuple[str, ...]  # stages whose outputs it reads
    estimate_s: float  # on one job's share of this machine
    work: str  # what it does, in counts
    rollouts: int = 0  # sweeps: how many
    task: str = ""
    variant: str = ""  # driver, train, sweeps, diagnose, probe
    seed: int = 0  # train, diagnose, probe: the training seed

    @property
    def key(self) -> str:
        return self.name.replace("/", "__")


def checkpoint_dir(cfg: ReproduceConfig, task: str, variant: str, seed: int) -> Path:
    """The training run's final checkpoint, where lerobot-train writes it."""
    steps = cfg.train.steps
    return _checkpoint(Path(cfg.output_dir) / "train" / task / variant / f"seed{seed}", steps, steps)


def driver_checkpoint(cfg: ReproduceConfig, task: str) -> Path:
    """The final checkpoint of the policy that drives the takeover episodes."""
    steps = cfg.takeover.driver_steps
    return _checkpoint(Path(cfg.output_dir) / "driver" / task, steps, steps)


def pooled_checkpoints(cfg: ReproduceConfig, task: str, variant: str) -> list[Path]:
    """What a variant's sweeps evaluate: the pooled late checkpoints of every training run, run by run."""
    run = Path(cfg.output_dir) / "train" / task / variant
    return [
        _checkpoint(run / f"seed{seed}", cfg.train.steps, step)
        for seed in range(cfg.train.seeds)
        for step in cfg.pooled_steps()
    ]


def _checkpoint(run: Path, steps: int, step: int) -> Path:
    """Where lerobot-train saves step `step` of a `steps`-step run."""
    from lerobot.common.train_utils import get_step_checkpoint_dir
    from lerobot.utils.constants import PRETRAINED_MODEL_DIR

    return get_step_checkpoint_dir(run, steps, step) / PRETRAINED_MODEL_DIR


def plan(cfg: ReproduceConfig, cores: int | None = None, bf16: bool | None = None) -> list[Stage]:
    """Every stage in the order it should run: Task 2 (the paper's harder task) first, the paper's three
    methods of each task before the variants it does not report (augmentation_attention). `bf16`: whether the
    CPU preset's training runs under bf16 autocast (default: where this CPU multiplies bf16 natively)."""
    from lerobot_condground.policies.act_modified.configuration_act_modified import VARIANTS

    cores = cores or usable_cores()
    share = max(1, cores // cfg.jobs)
    scale = cfg.preset
    tasks, variants = cfg.task_list(), cfg.variant_list()
    pairs = sorted(
        ((t, v) for t in tasks for v in variants),
        key=lambda tv: (tv[1] not in METHODS, tasks.index(tv[0]), variants.index(tv[1])),
    )
    rollouts_s = 60.0 / (ROLLOUTS_PER_CORE_MIN[scale] * share)
    conditions, counterbalanced = cfg.condition_lists()
    per_condition = cfg.eval.seeds * cfg.eval.n_episodes
    stages: list[Stage] = []
    recorded: set[str] = set()
    demos = f"{cfg.record.drift_std} rad drift" if cfg.record.drift_std else "clean"

    bf16 = native_bf16() if bf16 is None else bf16
    cpu_bf16 = scale == "cpu" and cfg.train.device == "cpu" and bf16
    rates = TRAIN_SAMPLES_PER_CORE_S["cpu_bf16" if cpu_bf16 else scale]

    def train_s(variant: str, steps: int) -> float:
        return steps * cfg.train.batch_size / (rates[variant] * share**THREAD_SCALING)

    record_s = RECORD_CORE_S_PER_EPISODE[scale] / min(cores, 2)
    takeover = cfg.takeover.episodes
    for task, variant in pairs:
        if task not in recorded:
            recorded.add(task)
            demo_stage = f"demos/{task}" if takeover else f"datasets/{task}"
            stages.append(
                Stage(
                    demo_stage, "record", (), cfg.record.episodes * record_s,
                    f"{cfg.record.episodes} demonstrations, {demos}", task=task,
                )
            )  # fmt: skip
            if takeover:
                steps = cfg.takeover.driver_steps
                stages += [
                    Stage(
                        f"driver/{task}", "driver", (demo_stage,), train_s("standard", steps),
                        f"{steps} steps of standard", task=task, variant="standard",
                    ),
                    Stage(
                        f"takeover/{task}", "takeover", (f"driver/{task}",), takeover * record_s,
                        f"{takeover} expert takeovers", task=task,
                    ),
                    Stage(
                        f"datasets/{task}", "merge", (demo_stage, f"takeover/{task}"),
                        (cfg.record.episodes + takeover) * MERGE_S_PER_EPISODE,
                        f"{cfg.record.episodes} + {takeover} episodes merged", task=task,
                    ),
                ]  # fmt: skip
        samples = cfg.train.steps * cfg.train.batch_size
        trains = [f"train/{task}/{variant}/seed{s}" for s in range(cfg.train.seeds)]
        stages += [
            Stage(
                name, "train", (f"datasets/{task}",), train_s(variant, cfg.train.steps),
                f"{cfg.train.steps} steps ({samples} samples)", task=task, variant=variant, seed=seed,
            )
            for seed, name in enumerate(trains)
        ]  # fmt: skip
        sweep = f"sweep/{task}/{variant}"
        for kind, name, conds in (
            ("sweep", sweep, conditions),
            ("sweep_counterbalanced", f"sweep_counterbalanced/{task}/{variant}", counterbalanced),
        ):
            if conds:
                n = cfg.train.seeds * cfg.eval.pool * len(conds) * per_condition
                stages.append(
                    Stage(
                        name,
                        kind,
                        tuple(trains),
                        n * rollouts_s,
                        f"{n} rollouts",
                        n,
                        task=task,
                        variant=variant,
                    )
                )
        for seed, train in enumerate(trains):
            if task == "PickPlaceRandomBin-v0" and f"act_modified/{variant}" in TABLE2_COLUMN:
                stages.append(
                    Stage(
                        f"diagnose/{task}/{variant}/seed{seed}", "diagnose", (train, sweep),
                        cfg.diagnose.pairs * DIAGNOSE_S_PER_PAIR, f"{cfg.diagnose.pairs} matched pairs",
                        task=task, variant=variant, seed=seed,
                    )
                )  # fmt: skip
            if VARIANTS[variant]["use_prompts"]:
                stages.append(
                    Stage(
                        f"probe/{task}/{variant}/seed{seed}", "probe", (train,),
                        2 * cfg.probe.episodes * rollouts_s, f"{cfg.probe.episodes} layouts x 2 prompts",
                        task=task, variant=variant, seed=seed,
                    )
                )  # fmt: skip
    stages.append(
        Stage(
            "report",
            "report",
            tuple(s.name for s in stages if s.kind not in DATA_KINDS),
            REPORT_S,
            "HTML + Markdown",
        )
    )
    return stages


def makespan(stages: list[Stage], jobs: int, done: set[str] = frozenset()) -> float:
    """Estimated wall-clock seconds to run what is not done, `jobs` stages at a time, in plan order as soon as
    what they read is done (the way the runner schedules them)."""
    todo = [s for s in stages if s.name not in done]
    finished = set(done)
    running: list[tuple[float, str]] = []
    now = 0.0
    while todo or running:
        ready = [s for s in todo if all(a in finished for a in s.after)]
        while ready and len(running) < jobs:
            stage = ready.pop(0)
            todo.remove(stage)
            heapq.heappush(running, (now + stage.estimate_s, stage.name))
        if not running:  # what is left reads a stage that is not planned
            break
        now, name = heapq.heappop(running)
        finished.add(name)
    return now
