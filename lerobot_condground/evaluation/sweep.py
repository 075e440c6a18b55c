"""`condground sweep`: checkpoints × conditions × evaluation seeds × rollouts -> `results.parquet`.

    condground sweep --policy.paths=P1,P2,P3 --env.task=PickPlaceRandomBin-v0 --sweep.conditions=paper \
        --eval.seeds=4 --eval.n_episodes=50 --output_dir=outputs/sweeps/full [--launcher=local|ray] [--workers=N]

Paired by construction: episode e of evaluation seed s resets every env with the same layout seed,
whatever the condition or checkpoint, and the layout sampler draws the targets from their own seeded
stream, so a condition's scene is the clean scene plus its competitors.

The work is cut into units (one checkpoint, condition and evaluation seed, `--eval.batch_size`
episodes stepped as one batch). A finished unit is written at once to `parts/` under a name that says
which unit it is, so a killed sweep reruns only the units in flight; `results.parquet` is assembled
from the parts when all are there. `sweep.json` pins the grid and the checkpoints' hashes: a rerun
with other settings, or after a checkpoint changed, is refused instead of mixing results.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from tqdm import tqdm

from lerobot_condground.core.conditions import PAPER_GRID, ConditionSpec, check_task
from lerobot_condground.core.configs import (
    HELD_OUT_SEED_OFFSET,
    EvalEnvConfig,
    PolicyRefConfig,
    check_seed,
    comma_items,
    usable_cores,
)
from lerobot_condground.core.files import read_json_object
from lerobot_condground.core.provenance import command_line, versions
from lerobot_condground.evaluation.checkpoints import (
    LoadedPolicy,
    check_env_fits,
    describe_checkpoint,
    resolve_device,
)
from lerobot_condground.evaluation.launchers import LAUNCHERS, execute
from lerobot_condground.evaluation.results import COLUMNS, read_table, write_table
from lerobot_condground.evaluation.rollout import EnvSpec
from lerobot_condground.evaluation.units import EPISODES_PER_SEED_LIMIT, PARTS, Unit, check_part, make_jobs

logger = logging.getLogger(__name__)

MANIFEST = "sweep.json"
RESULTS = "results.parquet"


@dataclass
class SweepGridConfig:
    # `paper` (clean, every class at 1..3 competitors, full_mixed) or names separated by commas;
    # conditions given as fields are separated by semicolons (object_color=2,receptacle_shape=1;clean).
    conditions: str = "paper"


@dataclass
class SweepEvalConfig:
    seeds: int = 4  # evaluation seeds per checkpoint
    n_episodes: int = 50  # rollouts per evaluation seed
    batch_size: int = 10  # episodes stepped together as one policy batch (one unit of work)
    # Layout seeds are seed_offset + seed * 100000 + episode: away from the recording seeds (0, 1, ...).
    seed_offset: int = HELD_OUT_SEED_OFFSET


@dataclass
class SweepConfig:
    # --policy.paths: one checkpoint per training seed (or --policy.path for one); `expert` is the scripted expert.
    policy: PolicyRefConfig = field(default_factory=PolicyRefConfig)
    env: EvalEnvConfig = field(default_factory=EvalEnvConfig)
    sweep: SweepGridConfig = field(default_factory=SweepGridConfig)
    eval: SweepEvalConfig = field(default_factory=SweepEvalConfig)
    output_dir: str = "outputs/sweep"
    launcher: str = "local"
    # Parallel workers (default: all cores). Each runs its units on threads_per_worker threads.
    workers: int | None = None
    threads_per_worker: int | None = None
    # Ray cluster address for --launcher=ray (default: start a local Ray).
    ray_address: str | None = None
    progress: bool = True


def parse_conditions(text: str) -> list[str]:
    text = text.strip()
    if text == "paper":
        return list(PAPER_GRID)
    items = comma_items(text, "--sweep.conditions", ";" if ";" in text or "=" in text else ",")
    names = []
    for item in items:
        name = ConditionSpec.parse(item).name  # unknown names fail here, with the allowed ones
        if name in names:
            raise ValueError(f"Condition {item!r} is listed twice in --sweep.conditions={text!r}")
        names.append(name)
    if not names:
        raise ValueError(
            "--sweep.conditions is empty; allowed: paper, or condition names separated by commas"
        )
    return names


def validate(cfg: SweepConfig) -> list[str]:
    from lerobot_condground.envs.layout import check_competitor_pool

    check_task(cfg.env.task)
    check_competitor_pool(cfg.env.competitor_pool, "--env.competitor_pool")
    if cfg.launcher not in LAUNCHERS:
        raise ValueError(f"Unknown --launcher={cfg.launcher!r}; allowed: {', '.join(LAUNCHERS)}")
    for name, value, low in (
        ("--eval.seeds", cfg.eval.seeds, 1),
        ("--eval.n_episodes", cfg.eval.n_episodes, 1),
        ("--eval.batch_size", cfg.eval.batch_size, 1),
        ("--env.episode_length", cfg.env.episode_length, 1),
    ):
        if value < low:
            raise ValueError(f"{name}={value} must be at least {low}")
    if cfg.eval.n_episodes > EPISODES_PER_SEED_LIMIT:
        raise ValueError(
            f"--eval.n_episodes={cfg.eval.n_episodes} exceeds {EPISODES_PER_SEED_LIMIT} (layout seeds would collide)"
        )
    if cfg.workers is not None and cfg.workers < 1:
        raise ValueError(f"--workers={cfg.workers} must be at least 1")
    check_seed("--eval.seed_offset", cfg.eval.seed_offset, cfg.eval.seeds * EPISODES_PER_SEED_LIMIT)
    if not cfg.policy.checkpoints():
        raise ValueError("--policy.paths is empty; give checkpoints separated by commas (or `expert`)")
    if cfg.env.condition is not None:
        raise ValueError(
            f"--env.condition={cfg.env.condition!r} is not a sweep flag; allowed: the grid's conditions "
            "as --sweep.conditions=NAME,NAME,..."
        )
    return parse_conditions(cfg.sweep.conditions)


def make_manifest(cfg: SweepConfig, conditions: list[str], checkpoints: list[LoadedPolicy]) -> dict:
    grid = {
        "task": cfg.env.task,
        "conditions": conditions,
        "condition_specs": {c: asdict(ConditionSpec.parse(c)) for c in conditions},
        "counterbalanced": cfg.env.counterbalanced,
        "eval_seeds": cfg.eval.seeds,
        "n_episodes": cfg.eval.n_episodes,
        "batch_size": cfg.eval.batch_size,
        "seed_offset": cfg.eval.seed_offset,
        "episode_length": cfg.env.episode_length,
        "fps": cfg.env.fps,
        "servo": cfg.env.servo,
        "observation_height": cfg.env.observation_height,
        "observation_width": cfg.env.observation_width,
    }
    if cfg.env.camera_codec != "none":  # absent from sweeps made before the setting: they stay resumable
        grid["camera_codec"] = cfg.env.camera_codec
    if cfg.env.competitor_pool != "eval":  # the same
        grid["competitor_pool"] = cfg.env.competitor_pool
    return {
        "kind": "sweep",
        "grid": grid,
        "checkpoints": [c.describe() for c in checkpoints],
        "versions": versions(),
        "command": command_line("sweep", cfg),
    }


def check_same_sweep(root: Path, manifest: dict) -> bool:
    """A rerun must be the same sweep: same grid, same checkpoints with the same weights. True when the
    manifest is to be written: none yet, or one of a run that finished no episode (it pinned nothing, and a
    run refused or failed before its first result must not block the corrected rerun)."""
    path = root / MANIFEST
    results = (root / RESULTS).exists() or (
        (root / PARTS).exists() and any((root / PARTS).rglob("*.parquet"))
    )
    if not path.exists():
        if results:
            raise ValueError(
                f"{root} holds results but no {MANIFEST}: it is not a condground sweep directory"
            )
        return True
    if not results:
        return True
    previous = read_json_object(path, "Sweep manifest")
    before, now = previous["grid"], manifest["grid"]
    # Keys only a non-default setting writes (camera_codec, competitor_pool) can be on either side.
    diffs = [
        f"{k}: {before.get(k)!r} -> {now.get(k)!r}"
        for k in dict.fromkeys([*before, *now])
        if before.get(k) != now.get(k)
    ]
    old = [(c["path"], c["hash"], c.get("label")) for c in previous["checkpoints"]]
    new = [(c["path"], c["hash"], c.get("label")) for c in manifest["checkpoints"]]
    if old != new:
        diffs.append(f"checkpoints (path, hash, label): {old} -> {new}")
    if diffs:
        raise ValueError(
            f"{root} holds a sweep of another grid; differences: {'; '.join(diffs)}. "
            "Rerun with the same flags to resume it, or choose a new --output_dir."
        )
    return False


def plan_units(cfg: SweepConfig, conditions: list[str], n_checkpoints: int) -> list[Unit]:
    units = []
    for seed in range(cfg.eval.seeds):
        for start in range(0, cfg.eval.n_episodes, cfg.eval.batch_size):
            for condition in conditions:
                for index in range(n_checkpoints):
                    units.append(
                        Unit(
                            index,
                            condition,
                            seed,
                            start,
                            min(start + cfg.eval.batch_size, cfg.eval.n_episodes),
                        )
                    )
    return units


# ---------------------------------------------------------------- the sweep
def run_sweep(cfg: SweepConfig) -> Path:
    conditions = validate(cfg)
    checkpoints = [
        describe_checkpoint(p, cfg.policy.label, i, cfg.policy.trust_remote_code)
        for i, p in enumerate(cfg.policy.checkpoints())
    ]
    for loaded in checkpoints:
        check_env_fits(loaded, EnvSpec.for_checkpoint(cfg.env, loaded, "clean").lerobot_config())
    root = Path(cfg.output_dir)
    manifest = make_manifest(cfg, conditions, checkpoints)
    # Written with the first finished part (or at the end): a sweep whose checkpoints fail to build leaves
    # no manifest to hold the corrected rerun to its settings.
    unwritten = [manifest] if check_same_sweep(root, manifest) else []

    def write_manifest() -> None:
        if unwritten:
            root.mkdir(parents=True, exist_ok=True)
            (root / MANIFEST).write_text(json.dumps(unwritten.pop(), indent=2))

    units = plan_units(cfg, conditions, len(checkpoints))
    expected = {u.part_path(root, checkpoints[u.checkpoint].hash): u for u in units}
    for stale in (root / PARTS).rglob("*.tmp") if (root / PARTS).exists() else []:
        logger.info("Removing %s, a part a killed run left half-written", stale)
        stale.unlink()
    strays = list((root / PARTS).rglob("*.parquet")) if (root / PARTS).exists() else []
    strays = [p for p in strays if p not in expected]
    if strays:
        raise ValueError(
            f"{root} holds partial results of another grid ({len(strays)} files, e.g. {strays[0]}); choose a new --output_dir"
        )
    frames = {
        path: check_part(path, unit, checkpoints[unit.checkpoint].hash)
        for path, unit in expected.items()
        if path.exists()
    }
    todo = [u for path, u in expected.items() if path not in frames]

    cores = usable_cores()
    workers = min(cfg.workers or cores, max(len(todo), 1))
    threads = cfg.threads_per_worker or (
        max(1, cores // workers) if workers > 1 or cfg.launcher == "ray" else None
    )
    total = sum(u.stop - u.start for u in units)
    done_episodes = total - sum(u.stop - u.start for u in todo)
    print(
        f"sweep: {len(checkpoints)} checkpoint(s) x {len(conditions)} condition(s) x {cfg.eval.seeds} seed(s) x "
        f"{cfg.eval.n_episodes} episodes = {total} episodes; {done_episodes} already done; "
        f"{cfg.launcher} launcher, {workers} worker(s)",
        flush=True,
    )
    bar = tqdm(
        total=total, initial=done_episodes, unit="ep", desc="sweep", disable=not cfg.progress, smoothing=0.1
    )
    successes = [0, 0]
    started = time.perf_counter()

    def on_done(job: dict, rows: list[dict]) -> None:
        write_manifest()
        path = job["unit"].part_path(root, checkpoints[job["unit"].checkpoint].hash)
        write_table(rows, path)
        frames[path] = read_table(path)
        successes[0] += sum(r["success"] for r in rows)
        successes[1] += len(rows)
        bar.update(len(rows))
        bar.set_postfix(success=f"{successes[0]}/{successes[1]}")

    try:
        jobs = make_jobs(cfg.env, cfg.eval.seed_offset, resolve_device(cfg.policy.device), todo, checkpoints)
        execute(jobs, cfg.launcher, workers, threads, cfg.ray_address, on_done)
    finally:
        bar.close()
    write_manifest()
    elapsed = time.perf_counter() - started
    import pandas as pd

    results = pd.concat([frames[p] for p in expected], ignore_index=True)[list(COLUMNS)]
    write_table(results, root / RESULTS, metadata=read_json_object(root / MANIFEST, "Sweep manifest"))
    ran = successes[1]
    print(
        f"sweep: wrote {len(results)} episodes to {root / RESULTS}"
        + (f"; ran {ran} in {elapsed:.1f} s ({60 * ran / elapsed:.1f} rollouts/min)" if ran else ""),
        flush=True,
    )
    return root / RESULTS
