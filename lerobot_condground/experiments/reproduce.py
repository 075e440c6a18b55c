"""`condground reproduce`: run the plan's stages, side by side where they may, resumable at every stage.

Each stage is a subprocess (the stock `lerobot-train`, `condground record|sweep|diagnose|probe|report`)
writing into `<output_dir>/<stage>` with its output in `<output_dir>/logs/<stage>.log`. A stage is done
when `<output_dir>/stages/<stage>.json` is there; it is written only after the command succeeded, so a
killed run repeats at most the stages in flight, and those resume themselves: a recording from its last
episode, a training from its last checkpoint, a sweep from its finished units; diagnose, probe and report
rewrite their own files. `reproduce.json` pins the settings that shape results: another setting on the same
directory is refused before any work starts. Runners started on one directory share its stages: a stage runs
under a lock (`<output_dir>/locks/<stage>.lock`) that its process holds until it exits, so a second runner
leaves it to the first and waits for its marker, and takes it over if the first died before finishing it.
"""

from __future__ import annotations

import fcntl
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from tqdm import tqdm

from lerobot_condground.core.configs import usable_cores
from lerobot_condground.core.files import read_json_object
from lerobot_condground.core.provenance import console_script, versions
from lerobot_condground.core.training import speed_flags
from lerobot_condground.core.ur3e import SERVO_BEFORE_THE_SETTING
from lerobot_condground.experiments.plan import (
    TAKEOVER_SEED,
    ReproduceConfig,
    Stage,
    checkpoint_dir,
    driver_checkpoint,
    makespan,
    plan,
    pooled_checkpoints,
)

MANIFEST = "reproduce.json"
LOG_STEP = re.compile(r"\bstep:(\d+(?:\.\d+)?)([KMB]?)\b")


class StageFailedError(RuntimeError):
    """A stage's command exited with an error: its own log says why, not a traceback of this scheduler."""


def command(cfg: ReproduceConfig, stage: Stage, share: int) -> list[str]:
    """The command line of one stage; `share` is the cores it may use."""
    out = Path(cfg.output_dir)
    here = out / stage.name
    task, variant, seed = stage.task, stage.variant, stage.seed
    if stage.kind in ("record", "takeover"):
        recording = [
            console_script("condground"), "record", f"--env.task={task}", "--env.condition=clean",
            f"--env.servo={cfg.env.servo}", f"--env.observation_height={cfg.record.observation_height}",
            f"--env.observation_width={cfg.record.observation_width}",
            f"--dataset.repo_id=local/{task}", f"--dataset.root={here}", "--progress=false",
        ]  # fmt: skip
        if stage.kind == "record":
            return [
                *recording,
                f"--dataset.num_episodes={cfg.record.episodes}",
                f"--drift.std={cfg.record.drift_std}",
            ]
        device = [f"--takeover.device={cfg.train.device}"] if cfg.train.device else []
        return [
            *recording, f"--dataset.num_episodes={cfg.takeover.episodes}", f"--seed={TAKEOVER_SEED}",
            f"--takeover.policy_path={driver_checkpoint(cfg, task)}", *device,
        ]  # fmt: skip
    if stage.kind == "merge":
        return [
            console_script("condground"),
            "merge",
            f"--roots=[{','.join(str(out / name) for name in stage.after)}]",
            f"--output.root={here}",
            f"--output.repo_id=local/{task}",
        ]
    if stage.kind in ("train", "driver"):
        last = here / "checkpoints" / "last" / "pretrained_model" / "train_config.json"
        if last.is_file():  # LeRobot's own resume: model, optimizer, scheduler, step and data order
            return [console_script("lerobot-train"), f"--config_path={last}", "--resume=true"]
        device = [f"--policy.device={cfg.train.device}"] if cfg.train.device else []
        # channels-last, and bf16 where this CPU runs it faster (core.training.speed_flags): not pinned
        precision = speed_flags() if cfg.train.device == "cpu" else []
        steps = _steps(cfg, stage)
        (data,) = stage.after  # the dataset stage it trains on: the demonstrations (driver) or the merge
        return [
            console_script("lerobot-train"), "--policy.type=act_modified", f"--policy.variant={variant}", *device, *precision,
            "--policy.push_to_hub=false", *cfg.policy_flags(), f"--dataset.repo_id=local/{task}",
            f"--dataset.root={out / data}", f"--batch_size={cfg.train.batch_size}",
            f"--steps={steps}", f"--save_freq={cfg.train.save_freq}",
            f"--log_freq={max(1, min(100, steps // 20))}", f"--num_workers={cfg.train.num_workers}",
            "--wandb.enable=false", f"--seed={seed}", f"--output_dir={here}",
        ]  # fmt: skip
    if stage.kind in ("sweep", "sweep_counterbalanced"):
        checkpoints = pooled_checkpoints(cfg, task, variant)
        counterbalanced = stage.kind == "sweep_counterbalanced"
        return [
            console_script("condground"), "sweep", f"--policy.paths={','.join(map(str, checkpoints))}",
            f"--env.task={task}", f"--env.counterbalanced={str(counterbalanced).lower()}",
            f"--env.servo={cfg.env.servo}", f"--env.episode_length={cfg.eval.episode_length}",
            f"--sweep.conditions={cfg.eval.counterbalanced if counterbalanced else cfg.eval.conditions}",
            f"--eval.seeds={cfg.eval.seeds}", f"--eval.n_episodes={cfg.eval.n_episodes}",
            f"--eval.batch_size={cfg.eval.batch_size}", f"--workers={share}", f"--output_dir={here}",
            "--progress=false",
        ]  # fmt: skip
    if stage.kind in ("diagnose", "probe"):
        common = [
            f"--policy.path={checkpoint_dir(cfg, task, variant, seed)}",
            f"--env.task={task}",
            f"--env.servo={cfg.env.servo}",
        ]
        if stage.kind == "diagnose":
            specific = [
                f"--diagnose.pairs={cfg.diagnose.pairs}",
                f"--sweep_dir={out / 'sweep' / task / variant}",
            ]
        else:
            specific = [
                f"--env.episode_length={cfg.eval.episode_length}", f"--probe.episodes={cfg.probe.episodes}",
                f"--workers={share}",
            ]  # fmt: skip
        return [
            console_script("condground"),
            stage.kind,
            *common,
            *specific,
            f"--output_dir={here}",
            "--progress=false",
        ]
    inputs = [f"--input_dir={out / name}" for name in stage.after]
    return [
        console_script("condground"), "report", *inputs, f"--output={here / 'report.html'}",
        f"--title=condground reproduce, preset {cfg.preset}: {', '.join(cfg.task_list())}",
    ]  # fmt: skip


def check_same_settings(cfg: ReproduceConfig) -> None:
    """Refuses a directory that holds a reproduction with other settings; pins the settings of a new one."""
    out = Path(cfg.output_dir)
    path = out / MANIFEST
    settings = cfg.pinned()
    if path.exists():
        previous = read_json_object(path, "Reproduction manifest").get("settings", {})
        previous.setdefault("env", {"servo": SERVO_BEFORE_THE_SETTING})  # written before the setting existed
        previous.setdefault("record", {}).setdefault("drift_std", 0.0)  # likewise: clean demonstrations
        previous.setdefault("eval", {}).setdefault("pool", 1)  # likewise: the final checkpoints alone
        diffs = _differences(previous, settings)
        if diffs:
            raise ValueError(
                f"{out} holds a reproduction with other settings ({'; '.join(diffs)}); rerun with the same "
                "flags to continue it, or choose a new --output_dir"
            )
    elif out.exists() and any(out.iterdir()):
        raise FileExistsError(
            f"--output_dir={out} is not empty and holds no {MANIFEST}; allowed: a new or empty directory, "
            "or one an earlier `condground reproduce` wrote"
        )


def check_train_flags(cfg: ReproduceConfig, stages: list[Stage]) -> None:
    """A training stage's whole command line parses against lerobot-train's own config, checked before the
    manifest pins --train.extra_flags: a flag lerobot-train refuses would otherwise fail the first training
    stage and pin settings the corrected rerun is then refused for."""
    import draccus
    from lerobot.configs.train import TrainPipelineConfig

    from lerobot_condground.evaluation.checkpoints import register_plugins

    train = next((s for s in stages if s.kind == "train"), None)
    if train is None:
        return
    args = command(cfg, train, 1)
    if "--resume=true" in args:
        return  # it parsed when the stage started
    register_plugins()
    try:
        draccus.parse(TrainPipelineConfig, args=args[1:], exit_on_error=False)
    except (draccus.utils.DraccusException, ValueError) as err:
        inner = err  # draccus wraps a config's own message in "Couldn't instantiate class ..."
        while inner.__cause__ or inner.__context__:
            inner = inner.__cause__ or inner.__context__
        message = " ".join(str(inner).split())
        raise ValueError(
            f"the training stages' lerobot-train flags do not parse ({message}); check --train.extra_flags="
            f"{cfg.train.extra_flags!r} and the preset's policy flags"
        ) from None


def _product(cfg: ReproduceConfig, stage: Stage) -> Path:
    """The file a stage exists to write: a stage that exits 0 without it is not done."""
    here = Path(cfg.output_dir) / stage.name
    if stage.kind == "train":
        return checkpoint_dir(cfg, stage.task, stage.variant, stage.seed) / "model.safetensors"
    if stage.kind == "driver":
        return driver_checkpoint(cfg, stage.task) / "model.safetensors"
    return (
        here
        / {
            "record": "meta/info.json",
            "takeover": "meta/info.json",
            "merge": "meta/info.json",
            "sweep": "results.parquet",
            "sweep_counterbalanced": "results.parquet",
            "diagnose": "diagnostics.json",
            "probe": "probe.json",
            "report": "report.html",
        }[stage.kind]
    )


def _differences(old: dict, new: dict, prefix: str = "") -> list[str]:
    diffs = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            diffs += _differences(a, b, f"{prefix}{key}.")
        elif a != b:
            diffs.append(f"{prefix}{key}: {a!r} -> {b!r}")
    return diffs


def _marker(cfg: ReproduceConfig, stage: Stage) -> Path:
    return Path(cfg.output_dir) / "stages" / f"{stage.key}.json"


def _is_done(cfg: ReproduceConfig, stage: Stage) -> bool:
    """Its marker is there and it read what it reads now: the report is rebuilt when stages were added."""
    path = _marker(cfg, stage)
    return path.exists() and read_json_object(path, "Stage marker").get("after") == list(stage.after)


def _claim(cfg: ReproduceConfig, stage: Stage) -> int | None:
    """The stage's lock, or None while another runner's stage process holds it. flock's lock belongs to the
    open file: the stage's process inherits it, so it outlives a runner killed hard until the stage exits."""
    fd = os.open(Path(cfg.output_dir) / "locks" / f"{stage.key}.lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    return fd


def _done_elsewhere(stage: Stage, todo: list[Stage], elsewhere: set[str], done: set[str]) -> float:
    """Books a stage another runner finished; returns its estimate for the progress bar."""
    todo.remove(stage)
    elsewhere.discard(stage.name)
    done.add(stage.name)
    return stage.estimate_s


def _log(cfg: ReproduceConfig, stage: Stage) -> Path:
    return Path(cfg.output_dir) / "logs" / f"{stage.key}.log"


def _fraction(cfg: ReproduceConfig, stage: Stage) -> float:
    """How far a running stage is, from what it has written so far (training: its log; sweeps: their units)."""
    if stage.kind in ("train", "driver"):
        try:
            text = _log(cfg, stage).read_bytes()[-4096:].decode(errors="replace")
        except OSError:
            return 0.0
        steps = LOG_STEP.findall(text)
        if not steps:
            return 0.0
        value, unit = steps[-1]
        return min(1.0, float(value) * {"": 1, "K": 1e3, "M": 1e6, "B": 1e9}[unit] / _steps(cfg, stage))
    if stage.kind.startswith("sweep"):
        parts = Path(cfg.output_dir) / stage.name / "parts"
        done = sum(1 for _ in parts.rglob("*.parquet")) * cfg.eval.batch_size if parts.exists() else 0
        return min(1.0, done / max(stage.rollouts, 1))
    return 0.0


def _steps(cfg: ReproduceConfig, stage: Stage) -> int:
    return cfg.train.steps if stage.kind == "train" else cfg.takeover.driver_steps


def _prepare(cfg: ReproduceConfig, stage: Stage) -> None:
    """A training killed before its first checkpoint left a directory lerobot-train refuses to reuse, and a
    merge killed after its rename (before its marker) one `condground merge` refuses to overwrite: each is this
    stage's own, so it goes. Anything else resumes in place."""
    here = Path(cfg.output_dir) / stage.name
    if not here.exists():
        return
    if stage.kind == "merge" or (
        stage.kind in ("train", "driver") and not (here / "checkpoints" / "last").exists()
    ):
        shutil.rmtree(here)


def describe(cfg: ReproduceConfig, stages: list[Stage], done: set[str], cores: int) -> str:
    lines = [
        f"condground reproduce, preset {cfg.preset}: {len(stages)} stages ({len(done)} done) in {cfg.output_dir}",
        f"{'stage':<66} {'work':<30} estimate",
    ]
    for s in stages:
        state = "done" if s.name in done else _hours(s.estimate_s)
        lines.append(f"{s.name:<66} {s.work:<30} {state}")
    left = makespan(stages, cfg.jobs, done)
    lines.append(
        f"estimated time left: {_hours(left)} with {cfg.jobs} stage(s) side by side on {cores} core(s) "
        "(rates measured on the 2-core development machine)"
    )
    if cfg.train.extra_flags:  # the training rates are the preset model's
        lines.append(
            f"the training estimates do not account for --train.extra_flags={cfg.train.extra_flags!r}"
        )
    return "\n".join(lines)


def _hours(seconds: float) -> str:
    return f"{seconds / 3600:.1f} h" if seconds >= 3600 else f"{seconds / 60:.0f} min"


def run(cfg: ReproduceConfig) -> Path:
    cores = usable_cores()
    stages = plan(cfg, cores)
    check_same_settings(cfg)
    check_train_flags(cfg, stages)
    done = {s.name for s in stages if _is_done(cfg, s)}
    print(describe(cfg, stages, done, cores), flush=True)
    if cfg.dry_run:
        return Path(cfg.output_dir)
    out = Path(cfg.output_dir)
    for sub in ("stages", "logs", "locks"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    if not (out / MANIFEST).exists():
        (out / MANIFEST).write_text(json.dumps({"settings": cfg.pinned(), "versions": versions()}, indent=2))

    share = max(1, cores // cfg.jobs)
    env = {
        **os.environ,
        "WANDB_MODE": "disabled",
        "OMP_NUM_THREADS": str(share),
        "MKL_NUM_THREADS": str(share),
    }
    todo = [s for s in stages if s.name not in done]
    running: dict[str, tuple[Stage, subprocess.Popen, float, int]] = {}
    elsewhere: set[str] = set()  # stages another runner on this directory is running
    total = sum(s.estimate_s for s in stages)
    bar = tqdm(total=round(total), unit="s", desc="reproduce", disable=not cfg.progress, smoothing=0.05,
               bar_format="{desc}: {percentage:3.0f}% |{bar}| {elapsed} elapsed, ETA {remaining} {postfix}")  # fmt: skip
    finished = sum(s.estimate_s for s in stages if s.name in done)
    # `kill` (SIGTERM) would end this process without its `finally`, orphaning the running stages, which a
    # rerun would then race in the same directories. The exit waits for the loop's next turn: raised inside
    # Popen, it would orphan a stage started but not yet in `running`.
    terminated: list[int] = []
    signal.signal(signal.SIGTERM, lambda signum, frame: terminated.append(signum))
    try:
        while todo or running:
            if terminated:
                sys.exit(128 + terminated[0])
            for name, (stage, proc, started, lock) in list(running.items()):
                if proc.poll() is None:
                    continue
                del running[name]
                product = _product(cfg, stage)
                if proc.returncode != 0 or not product.is_file():
                    os.close(lock)
                    tail = _log(cfg, stage).read_text(errors="replace").splitlines()[-40:]
                    why = f"exit {proc.returncode}" if proc.returncode else f"exit 0, but no {product}"
                    raise StageFailedError(
                        f"stage {name} failed ({why}); the end of its log {_log(cfg, stage)}:\n"
                        + "\n".join(tail)
                        + "\nThe stages done are kept: the same command retries from this one."
                    )
                seconds = round(time.time() - started, 1)
                _marker(cfg, stage).write_text(
                    json.dumps(
                        # The console script by name: the marker is published, this machine's paths are not.
                        {
                            "command": [Path(proc.args[0]).name, *proc.args[1:]],
                            "after": list(stage.after),
                            "seconds": seconds,
                        },
                        indent=1,
                    )
                )
                os.close(lock)  # after the marker: a runner that takes the lock next sees the stage done
                done.add(name)
                finished += stage.estimate_s
                bar.write(f"done: {name} ({_hours(time.time() - started)})")
            for stage in [s for s in todo if s.name in elsewhere and _is_done(cfg, s)]:
                finished += _done_elsewhere(stage, todo, elsewhere, done)
                bar.write(f"done elsewhere: {stage.name}")
            for stage in [s for s in todo if all(a in done for a in s.after)]:
                if len(running) >= cfg.jobs:
                    break
                lock = _claim(cfg, stage)
                if lock is None:
                    if stage.name not in elsewhere:
                        elsewhere.add(stage.name)
                        bar.write(
                            f"wait: {stage.name} runs in another `condground reproduce` on this directory"
                        )
                    continue
                if _is_done(cfg, stage):  # finished by another runner since this one looked
                    os.close(lock)
                    finished += _done_elsewhere(stage, todo, elsewhere, done)
                    continue
                elsewhere.discard(stage.name)
                todo.remove(stage)
                _prepare(cfg, stage)
                args = command(cfg, stage, share)
                bar.write(f"start: {stage.name}  (log: {_log(cfg, stage)})")
                with _log(cfg, stage).open("a") as log:
                    log.write(f"$ {' '.join(args)}\n")
                    log.flush()
                    proc = subprocess.Popen(
                        args, env=env, stdout=log, stderr=subprocess.STDOUT, pass_fds=(lock,)
                    )
                running[stage.name] = (stage, proc, time.time(), lock)
            if not running and not elsewhere and todo:
                raise RuntimeError(f"stages {[s.name for s in todo]} read stages that are not planned")
            bar.n = round(finished + sum(s.estimate_s * _fraction(cfg, s) for s, *_ in running.values()))
            bar.set_postfix_str(", ".join([*running, *(f"{n} (elsewhere)" for n in elsewhere)]), refresh=True)
            time.sleep(1.0)
    finally:
        for _, proc, *_ in running.values():
            proc.terminate()
        for _, proc, _, lock in running.values():
            proc.wait()
            os.close(lock)
        bar.close()
    report = out / "report" / "report.html"
    print(f"reproduce: all {len(stages)} stages done; report {report}", flush=True)
    return report
