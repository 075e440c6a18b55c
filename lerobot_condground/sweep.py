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
import os
import re
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from tqdm import tqdm

from lerobot_condground.checkpoints import LoadedPolicy, check_env_fits, describe_checkpoint
from lerobot_condground.conditions import PAPER_GRID, ConditionSpec, check_task
from lerobot_condground.provenance import command_line, versions
from lerobot_condground.results import COLUMNS, read_table, write_table
from lerobot_condground.rollout import EnvSpec

logger = logging.getLogger(__name__)

MANIFEST = "sweep.json"
RESULTS = "results.parquet"
PARTS = "parts"
LAUNCHERS = ("local", "ray")
EPISODES_PER_SEED_LIMIT = 100_000
EXPERT_SIZE = (96, 128)  # the expert reads no pixels; render little


@dataclass
class SweepPolicyConfig:
    # Comma-separated checkpoints, one per training seed: pretrained_model directories or hub ids
    # (offline: from the cache). `expert` is the scripted expert.
    paths: str = ""
    # Name in tables (default: the type, and the variant for act_modified).
    label: str | None = None
    device: str = "cpu"


@dataclass
class SweepEnvConfig:
    task: str = "PickPlaceRandomBin-v0"
    counterbalanced: bool = False
    # Default: each checkpoint's own camera size.
    observation_height: int | None = None
    observation_width: int | None = None
    episode_length: int = 300
    fps: int = 20


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
    seed_offset: int = 1_000_000


@dataclass
class SweepConfig:
    policy: SweepPolicyConfig = field(default_factory=SweepPolicyConfig)
    env: SweepEnvConfig = field(default_factory=SweepEnvConfig)
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


@dataclass(frozen=True)
class Unit:
    checkpoint: int  # index into the sweep's checkpoints
    condition: str
    eval_seed: int
    start: int
    stop: int

    def part_path(self, root: Path, checkpoint_hash: str) -> Path:
        safe = re.sub(r"[^A-Za-z0-9_]+", "-", self.condition)
        return root / PARTS / checkpoint_hash / safe / f"seed{self.eval_seed:03d}_ep{self.start:05d}-{self.stop:05d}.parquet"


def parse_conditions(text: str) -> list[str]:
    text = text.strip()
    if text == "paper":
        return list(PAPER_GRID)
    items = [c.strip() for c in (text.split(";") if ";" in text or "=" in text else text.split(",")) if c.strip()]
    names = []
    for item in items:
        name = ConditionSpec.parse(item).name  # unknown names fail here, with the allowed ones
        if name in names:
            raise ValueError(f"Condition {item!r} is listed twice in --sweep.conditions={text!r}")
        names.append(name)
    if not names:
        raise ValueError("--sweep.conditions is empty; allowed: paper, or condition names separated by commas")
    return names


def validate(cfg: SweepConfig) -> list[str]:
    check_task(cfg.env.task)
    if cfg.launcher not in LAUNCHERS:
        raise ValueError(f"Unknown --launcher={cfg.launcher!r}; allowed: {', '.join(LAUNCHERS)}")
    for name, value, low in (("--eval.seeds", cfg.eval.seeds, 1), ("--eval.n_episodes", cfg.eval.n_episodes, 1),
                             ("--eval.batch_size", cfg.eval.batch_size, 1), ("--env.episode_length", cfg.env.episode_length, 1)):
        if value < low:
            raise ValueError(f"{name}={value} must be at least {low}")
    if cfg.eval.n_episodes > EPISODES_PER_SEED_LIMIT:
        raise ValueError(f"--eval.n_episodes={cfg.eval.n_episodes} exceeds {EPISODES_PER_SEED_LIMIT} (layout seeds would collide)")
    if cfg.workers is not None and cfg.workers < 1:
        raise ValueError(f"--workers={cfg.workers} must be at least 1")
    if not cfg.policy.paths.strip():
        raise ValueError("--policy.paths is empty; give checkpoints separated by commas (or `expert`)")
    return parse_conditions(cfg.sweep.conditions)


def env_spec(cfg: SweepConfig, loaded: LoadedPolicy, condition: str) -> EnvSpec:
    if cfg.env.observation_height is not None and cfg.env.observation_width is not None:
        size = (cfg.env.observation_height, cfg.env.observation_width)
    elif loaded.is_expert:
        size = EXPERT_SIZE
    else:
        size = next(iter(loaded.cameras.values()), EXPERT_SIZE)
    return EnvSpec(
        task=cfg.env.task, condition=condition, counterbalanced=cfg.env.counterbalanced,
        observation_height=size[0], observation_width=size[1], wrist_camera="wrist" in loaded.cameras,
        prompts=loaded.needs_prompts, fps=cfg.env.fps, episode_length=cfg.env.episode_length,
    )


def layout_seed(cfg: SweepEvalConfig, eval_seed: int, episode: int) -> int:
    return cfg.seed_offset + eval_seed * EPISODES_PER_SEED_LIMIT + episode


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
        "observation_height": cfg.env.observation_height,
        "observation_width": cfg.env.observation_width,
    }
    return {"kind": "sweep", "grid": grid, "checkpoints": [c.describe() for c in checkpoints],
            "versions": versions(), "command": command_line("sweep", cfg)}



def check_same_sweep(root: Path, manifest: dict) -> None:
    """A rerun must be the same sweep: same grid, same checkpoints with the same weights."""
    path = root / MANIFEST
    if not path.exists():
        if (root / RESULTS).exists() or (root / PARTS).exists():
            raise ValueError(f"{root} holds results but no {MANIFEST}: it is not a condground sweep directory")
        return
    previous = json.loads(path.read_text())
    diffs = [f"{k}: {previous['grid'].get(k)!r} -> {v!r}" for k, v in manifest["grid"].items() if previous["grid"].get(k) != v]
    old = [(c["path"], c["hash"]) for c in previous["checkpoints"]]
    new = [(c["path"], c["hash"]) for c in manifest["checkpoints"]]
    if old != new:
        diffs.append(f"checkpoints (path, hash): {old} -> {new}")
    if diffs:
        raise ValueError(
            f"{root} holds a sweep of another grid; differences: {'; '.join(diffs)}. "
            "Rerun with the same flags to resume it, or choose a new --output_dir."
        )


def plan_units(cfg: SweepConfig, conditions: list[str], n_checkpoints: int) -> list[Unit]:
    units = []
    for seed in range(cfg.eval.seeds):
        for start in range(0, cfg.eval.n_episodes, cfg.eval.batch_size):
            for condition in conditions:
                for index in range(n_checkpoints):
                    units.append(Unit(index, condition, seed, start, min(start + cfg.eval.batch_size, cfg.eval.n_episodes)))
    return units


def check_part(path: Path, unit: Unit, checkpoint_hash: str):
    """A finished part must hold exactly its unit's episodes; anything else is a clear error."""
    frame = read_table(path)
    expected = list(range(unit.start, unit.stop))
    problems = []
    if sorted(frame["episode"].tolist()) != expected:
        problems.append(f"episodes {sorted(frame['episode'].tolist())} instead of {unit.start}..{unit.stop - 1}")
    for column, value in (("checkpoint_hash", checkpoint_hash), ("condition", unit.condition), ("eval_seed", unit.eval_seed)):
        if set(frame[column].tolist()) != {value}:
            problems.append(f"{column} {sorted(set(frame[column].tolist()))} instead of {value!r}")
    if problems:
        raise ValueError(f"Partial results file {path} does not match its unit ({'; '.join(problems)}); delete it to rerun those episodes")
    return frame


# ---------------------------------------------------------------- workers
_POLICIES: dict = {}
_POOL = None


def init_worker(threads: int | None) -> None:
    """Per-process setup of a parallel worker: a fixed number of threads for torch and Mesa."""
    if threads:
        for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "LP_NUM_THREADS"):
            os.environ[var] = str(threads)
        import torch

        torch.set_num_threads(threads)
    os.environ.setdefault("MUJOCO_GL", "egl")
    import lerobot_condground.registration  # noqa: F401  (env and policy types, in spawned processes)


def run_unit(job: dict) -> list[dict]:
    """Runs one unit in this process; policies and envs are cached across the units a worker gets."""
    from lerobot_condground.checkpoints import load_policy
    from lerobot_condground.rollout import EnvPool, run_episodes

    global _POOL
    _POOL = _POOL or EnvPool()
    spec: EnvSpec = job["env"]
    key = (job["path"], job["device"], spec.observation_height, spec.observation_width)
    if key not in _POLICIES:
        _POLICIES[key] = load_policy(job["path"], spec.lerobot_config(), job["device"], job["label"], job["index"])
    loaded = _POLICIES[key]
    envs = _POOL.get(spec, len(job["seeds"]))
    import torch

    torch.manual_seed(job["seeds"][0])
    outcomes = run_episodes(loaded, envs, job["seeds"], max_steps=spec.episode_length, swap=job.get("swap"))
    rows = []
    for episode, seed, result in zip(job["episodes"], job["seeds"], outcomes):
        rows.append({**job["identity"], "episode": episode, "layout_seed": seed, **result})
    return rows


def make_jobs(cfg: SweepConfig, units: list[Unit], checkpoints: list[LoadedPolicy]) -> list[dict]:
    jobs = []
    for unit in units:
        loaded = checkpoints[unit.checkpoint]
        episodes = list(range(unit.start, unit.stop))
        jobs.append({
            "unit": unit,
            "path": loaded.path, "label": loaded.label, "index": unit.checkpoint, "device": cfg.policy.device,
            "env": env_spec(cfg, loaded, unit.condition),
            "episodes": episodes,
            "seeds": [layout_seed(cfg.eval, unit.eval_seed, e) for e in episodes],
            "identity": {
                "policy_label": loaded.label, "policy_type": loaded.policy_type, "variant": loaded.variant,
                "checkpoint": loaded.path, "checkpoint_hash": loaded.hash, "training_seed": loaded.training_seed,
                "task": cfg.env.task, "condition": unit.condition, "counterbalanced": cfg.env.counterbalanced,
                "eval_seed": unit.eval_seed, "prompt": "target",
            },
        })
    return jobs


def execute(jobs: list[dict], launcher: str, workers: int, threads: int | None, ray_address: str | None, on_done) -> None:
    """Runs jobs on the chosen launcher; on_done(job, rows) is called in this process as each finishes."""
    if launcher == "ray":
        _execute_ray(jobs, workers, threads, ray_address, on_done)
    elif workers == 1 and threads is None:
        # In this process, with its threads as they are; a thread count needs a fresh process, since
        # Mesa reads LP_NUM_THREADS only when it first loads.
        init_worker(None)
        for job in jobs:
            on_done(job, run_unit(job))
    else:
        import multiprocessing as mp
        from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

        # spawn: a fresh interpreter per worker, no forked EGL contexts or torch thread pools.
        with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=init_worker, initargs=(threads,)) as pool:
            pending = {pool.submit(run_unit, job): job for job in jobs}
            try:
                while pending:
                    done, _ = wait(pending, return_when=FIRST_COMPLETED)
                    for future in done:
                        on_done(pending.pop(future), future.result())
            except BaseException:
                for future in pending:
                    future.cancel()
                raise


def _ray_unit(job: dict, threads: int | None) -> list[dict]:
    init_worker(threads)
    return run_unit(job)


def _execute_ray(jobs, workers, threads, ray_address, on_done) -> None:
    import ray

    env_vars = {k: os.environ[k] for k in ("MUJOCO_GL", "HF_HUB_OFFLINE", "HF_HOME", "HF_LEROBOT_HOME") if k in os.environ}
    started = not ray.is_initialized()
    if started:
        ray.init(address=ray_address, num_cpus=None if ray_address else workers, include_dashboard=False,
                 runtime_env={"env_vars": env_vars}, log_to_driver=False, logging_level=logging.WARNING)
    try:
        task = ray.remote(num_cpus=threads or 1)(_ray_unit)
        pending = {task.remote(job, threads): job for job in jobs}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                on_done(pending.pop(ref), ray.get(ref))
    finally:
        if started:
            ray.shutdown()


# ---------------------------------------------------------------- the sweep
def run_sweep(cfg: SweepConfig) -> Path:
    conditions = validate(cfg)
    paths = [p.strip() for p in cfg.policy.paths.split(",") if p.strip()]
    checkpoints = [describe_checkpoint(p, cfg.policy.label, i) for i, p in enumerate(paths)]
    for loaded in checkpoints:
        check_env_fits(loaded, env_spec(cfg, loaded, "clean").lerobot_config())
    root = Path(cfg.output_dir)
    manifest = make_manifest(cfg, conditions, checkpoints)
    check_same_sweep(root, manifest)
    root.mkdir(parents=True, exist_ok=True)
    if not (root / MANIFEST).exists():
        (root / MANIFEST).write_text(json.dumps(manifest, indent=2))

    units = plan_units(cfg, conditions, len(checkpoints))
    expected = {u.part_path(root, checkpoints[u.checkpoint].hash): u for u in units}
    for stale in (root / PARTS).rglob("*.tmp") if (root / PARTS).exists() else []:
        logger.info("Removing %s, a part a killed run left half-written", stale)
        stale.unlink()
    strays = [p for p in (root / PARTS).rglob("*.parquet")] if (root / PARTS).exists() else []
    strays = [p for p in strays if p not in expected]
    if strays:
        raise ValueError(f"{root} holds partial results of another grid ({len(strays)} files, e.g. {strays[0]}); choose a new --output_dir")
    frames = {path: check_part(path, unit, checkpoints[unit.checkpoint].hash) for path, unit in expected.items() if path.exists()}
    todo = [u for path, u in expected.items() if path not in frames]

    cores = os.cpu_count() or 1
    workers = min(cfg.workers or cores, max(len(todo), 1))
    threads = cfg.threads_per_worker or (max(1, cores // workers) if workers > 1 or cfg.launcher == "ray" else None)
    total = sum(u.stop - u.start for u in units)
    done_episodes = total - sum(u.stop - u.start for u in todo)
    print(f"sweep: {len(checkpoints)} checkpoint(s) x {len(conditions)} condition(s) x {cfg.eval.seeds} seed(s) x "
          f"{cfg.eval.n_episodes} episodes = {total} episodes; {done_episodes} already done; "
          f"{cfg.launcher} launcher, {workers} worker(s)", flush=True)
    bar = tqdm(total=total, initial=done_episodes, unit="ep", desc="sweep", disable=not cfg.progress, smoothing=0.1)
    successes = [0, 0]
    started = time.perf_counter()

    def on_done(job: dict, rows: list[dict]) -> None:
        path = job["unit"].part_path(root, checkpoints[job["unit"].checkpoint].hash)
        write_table(rows, path)
        frames[path] = read_table(path)
        successes[0] += sum(r["success"] for r in rows)
        successes[1] += len(rows)
        bar.update(len(rows))
        bar.set_postfix(success=f"{successes[0]}/{successes[1]}")

    try:
        execute(make_jobs(cfg, todo, checkpoints), cfg.launcher, workers, threads, cfg.ray_address, on_done)
    finally:
        bar.close()
    elapsed = time.perf_counter() - started
    import pandas as pd

    results = pd.concat([frames[p] for p in expected], ignore_index=True)[list(COLUMNS)]
    write_table(results, root / RESULTS, metadata=json.loads((root / MANIFEST).read_text()))
    ran = successes[1]
    print(f"sweep: wrote {len(results)} episodes to {root / RESULTS}"
          + (f"; ran {ran} in {elapsed:.1f} s ({60 * ran / elapsed:.1f} rollouts/min)" if ran else ""), flush=True)
    return root / RESULTS
