"""`condground reproduce`: the plan, its refusals, and a toy-size run killed mid-stage and resumed."""

import contextlib
import json
import os
import pathlib
import queue
import signal
import subprocess
import threading
import time

import pandas as pd
import pytest

from helpers import BIN, read_json, run_cli
from lerobot_condground.cli import main
from lerobot_condground.core.training import CPU_BATCH_SIZE, CPU_STEPS

# Every kind of stage once (Task 2 and `full`: diagnose and probe run; a DAgger round), each as small as it runs.
TOY = [
    "--tasks=PickPlaceRandomBin-v0",
    "--train.variants=full",
    "--record.episodes=2",
    "--takeover.episodes=1",
    "--takeover.driver_steps=10",
    "--train.seeds=1",
    "--train.steps=40",
    "--train.save_freq=10",
    "--train.batch_size=2",
    "--eval.conditions=full_mixed",
    "--eval.counterbalanced=full_mixed",
    "--eval.seeds=1",
    "--eval.n_episodes=2",
    "--eval.batch_size=2",
    "--eval.episode_length=10",
    "--diagnose.pairs=1",
    "--probe.episodes=1",
    "--progress=false",
]


def test_dry_run_prints_the_plan_and_its_time_without_writing(tmp_path, capsys):
    out = tmp_path / "plan"
    assert main(["reproduce", "--preset=cpu", f"--output_dir={out}", "--dry_run=true"]) == 0
    text = capsys.readouterr().out
    assert "preset cpu: 45 stages (0 done)" in text
    # Task 2 first, the paper's three methods before augmentation_attention
    trains = [line.split()[0] for line in text.splitlines() if line.startswith("train/")]
    assert trains[:6:2] == [
        f"train/PickPlaceRandomBin-v0/{v}/seed0" for v in ("standard", "full", "augmentation")
    ]
    assert trains[-1] == "train/PickPlaceFixedBin-v0/augmentation_attention/seed1"
    # the protocol: 2 training seeds x the last 3 checkpoints x 50 held-out layouts, 5 conditions
    assert "sweep/PickPlaceRandomBin-v0/full" in text and "1500 rollouts" in text
    assert "diagnose/PickPlaceRandomBin-v0/augmentation/seed0" in text
    assert "probe/PickPlaceFixedBin-v0/full/seed0" in text and "diagnose/PickPlaceFixedBin" not in text
    assert "estimated time left:" in text and "extra_flags" not in text
    # the CPU configuration's recovery data and budget (core.training)
    assert "datasets/PickPlaceRandomBin-v0" in text and "200 demonstrations, 0.06 rad drift" in text
    assert f"{CPU_STEPS} steps ({CPU_STEPS * CPU_BATCH_SIZE} samples)" in text
    assert not out.exists()

    assert (
        main(["reproduce", "--preset=paper", f"--output_dir={out}", "--dry_run=true", "--train.steps=5"]) == 0
    )
    text = capsys.readouterr().out
    assert "12000 rollouts" in text  # 3 training seeds x 20 conditions x 4 x 50
    assert "train/PickPlaceRandomBin-v0/standard/seed2" in text and "5 steps" in text

    dagger = ["--takeover.episodes=100", "--record.episodes=100"]
    assert main(["reproduce", "--preset=cpu", f"--output_dir={out}", "--dry_run=true", *dagger]) == 0
    text = capsys.readouterr().out
    assert "preset cpu: 51 stages (0 done)" in text
    names = [line.split()[0] for line in text.splitlines()[2:-1]]
    task = "PickPlaceRandomBin-v0"
    assert names[:5] == [
        f"demos/{task}",
        f"driver/{task}",
        f"takeover/{task}",
        f"datasets/{task}",
        f"train/{task}/standard/seed0",
    ]
    assert (
        f"{CPU_STEPS // 2} steps of standard" in text
        and "100 expert takeovers" in text
        and "100 + 100 episodes merged" in text
    )
    assert not out.exists()

    flags = "--train.extra_flags=--policy.dim_model=256"
    assert main(["reproduce", "--preset=cpu", f"--output_dir={out}", "--dry_run=true", flags]) == 0
    assert "do not account for --train.extra_flags='--policy.dim_model=256'" in capsys.readouterr().out


@pytest.mark.parametrize(
    "flag, message",
    [
        ("--preset=gpu", "--preset='gpu' is not allowed; allowed: cpu, paper"),
        ("--train.variants=standard,bogus", "--train.variants holds 'bogus'"),
        ("--tasks=PickPlaceRandomBin-v0,PickPlaceRandomBin-v0", "each of"),
        ("--eval.conditions=clean,nope", "Unknown condition 'nope'"),
        ("--train.steps=0", "--train.steps=0 is not allowed"),
        ("--train.extra_flags=dim_model=3", "--train.extra_flags holds 'dim_model=3'"),
        (
            "--train.extra_flags=--output_dir=/tmp/x",
            "sets itself after the extra flags (it would be ignored)",
        ),
        ("--train.extra_flags=--steps=5", "use --train.steps instead"),
        ("--train.extra_flags=--policy.dim_model=`3`", "whose value YAML cannot read at '`' (character 1)"),
        (
            "--train.extra_flags=--save_checkpoint=false",
            "defeats every training stage (no checkpoint is saved",
        ),
        (
            "--train.extra_flags=--policy.path=outputs/x",
            "defeats every training stage (the stage would train",
        ),
        ("--record.observation_height=32", "--record.observation_height/width: Image height 32 cannot be"),
        ("--eval.n_episodes=150000", "--eval.n_episodes=150000 is not allowed; allowed: 1 to 100000"),
        (
            "--train.extra_flags=--policy.init_from_act=typo_dir",
            "do not parse (init_from_act='typo_dir' is neither an existing checkpoint directory nor a hub id",
        ),
        (
            "--train.extra_flags=--policy.no_such_field=1",
            "lerobot-train flags do not parse (unrecognized arguments: --policy.no_such_field=1)",
        ),
        ("--jobs=0", "--jobs=0 is not allowed"),
        ("--env.servo=fast", "--env.servo='fast' is not allowed; allowed: interpolated, direct"),
        ("--record.drift_std=0.2", "--record.drift_std=0.2 is not allowed; allowed: 0 (clean) to 0.15 rad"),
        ("--takeover.episodes=-1", "--takeover.episodes=-1 is not allowed; allowed: a number >= 0"),
        ("--takeover.episodes=100001", "--takeover.episodes=100001 is not allowed; allowed: 1 to 100000"),
        ("--takeover.driver_steps=0", "--takeover.driver_steps=0 is not allowed; allowed: a number >= 1"),
        ("--eval.pool=0", "--eval.pool=0 is not allowed; allowed: a number >= 1"),
        (
            "--eval.pool=7",
            "--eval.pool=7 is not allowed with --train.steps=6000 and --train.save_freq=1000, which save 6 "
            "checkpoint(s); allowed: 1 to 6",
        ),
    ],
)
def test_bad_input_is_one_error_before_work(tmp_path, capsys, flag, message):
    out = tmp_path / "run"
    assert main(["reproduce", f"--output_dir={out}", flag]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_a_directory_it_did_not_write_is_refused(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("mine")
    assert main(["reproduce", f"--output_dir={tmp_path}", *TOY]) == 2
    assert "holds no reproduce.json" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def test_a_reproduction_from_before_the_servo_setting_continues_only_as_it_ran(tmp_path):
    """Its manifest has no env.servo: it recorded and evaluated with the targets set at once."""
    from lerobot_condground.experiments.plan import EnvSettings, ReproduceConfig
    from lerobot_condground.experiments.reproduce import check_same_settings

    out = tmp_path / "run"
    settings = ReproduceConfig(output_dir=str(out)).pinned()
    assert settings.pop("env") == {"servo": "interpolated"}
    out.mkdir()
    (out / "reproduce.json").write_text(json.dumps({"settings": settings}))
    with pytest.raises(ValueError, match="other settings \\(env.servo: 'direct' -> 'interpolated'\\)"):
        check_same_settings(ReproduceConfig(output_dir=str(out)))
    check_same_settings(ReproduceConfig(output_dir=str(out), env=EnvSettings(servo="direct")))


def test_the_plan_times_cpu_training_at_the_bf16_rate_only_where_training_runs_in_bf16():
    from lerobot_condground.experiments.plan import ReproduceConfig, TrainSettings, plan

    def train_minutes(cfg, bf16):
        return {s.name: s.estimate_s / 60 for s in plan(cfg, cores=2, bf16=bf16) if s.kind == "train"}

    cpu = ReproduceConfig(output_dir="unused")
    fp32, bf16 = train_minutes(cpu, False), train_minutes(cpu, True)
    standard = "train/PickPlaceFixedBin-v0/standard/seed0"
    assert fp32.keys() == bf16.keys() and all(bf16[k] < fp32[k] for k in fp32)
    # the measured runs: 6000 steps of batch 16 in about 100 minutes in fp32, 42 in bf16, two side by side
    assert 95 < fp32[standard] < 105 and 40 < bf16[standard] < 45
    on_gpu = ReproduceConfig(output_dir="unused", train=TrainSettings(device="cuda"))
    assert train_minutes(on_gpu, True) == train_minutes(on_gpu, False)


def test_sweeps_pool_the_last_checkpoints_of_every_run_and_older_reproductions_keep_the_final_one(tmp_path):
    """The protocol: each run's last --eval.pool saved checkpoints, on the same layouts; a manifest from
    before the setting swept each run's final checkpoint alone and continues only so."""
    from lerobot_condground.experiments.plan import EvalSettings, ReproduceConfig, TrainSettings, plan
    from lerobot_condground.experiments.reproduce import check_same_settings, command

    out = tmp_path / "run"
    train = TrainSettings(steps=2500, save_freq=1000)
    cfg = ReproduceConfig(output_dir=str(out), tasks="PickPlaceFixedBin-v0", train=train)
    sweep = next(s for s in plan(cfg) if s.kind == "sweep" and s.variant == "full")
    (paths,) = [
        a.removeprefix("--policy.paths=") for a in command(cfg, sweep, 1) if a.startswith("--policy.paths=")
    ]
    run = out / "train" / "PickPlaceFixedBin-v0" / "full"
    # saved at 1000, 2000 and the last step: those three, run by run
    assert paths.split(",") == [
        str(run / f"seed{seed}" / "checkpoints" / f"{step:06d}" / "pretrained_model")
        for seed in (0, 1)
        for step in (1000, 2000, 2500)
    ]
    assert sweep.rollouts == 2 * 3 * 5 * 50
    settings = ReproduceConfig(output_dir=str(out)).pinned()
    assert settings["eval"].pop("pool") == 3
    out.mkdir()
    (out / "reproduce.json").write_text(json.dumps({"settings": settings}))
    with pytest.raises(ValueError, match="other settings \\(eval.pool: 1 -> 3\\)"):
        check_same_settings(ReproduceConfig(output_dir=str(out)))
    check_same_settings(ReproduceConfig(output_dir=str(out), eval=EvalSettings(pool=1)))


def test_a_reproduction_from_before_recovery_data_continues_only_with_clean_demonstrations(tmp_path):
    """Its manifest has no record.drift_std: it recorded clean demonstrations, and its stages say so."""
    from lerobot_condground.core.training import CPU_DRIFT_STD, amp_flags
    from lerobot_condground.experiments.plan import RecordSettings, ReproduceConfig, plan
    from lerobot_condground.experiments.reproduce import check_same_settings, command

    out = tmp_path / "run"
    cfg = ReproduceConfig(output_dir=str(out))
    by_kind = {stage.kind: command(cfg, stage, 1) for stage in plan(cfg)}
    assert f"--drift.std={CPU_DRIFT_STD}" in by_kind["record"]
    assert set(amp_flags()) <= set(by_kind["train"])  # bf16 only where this CPU runs it faster
    settings = cfg.pinned()
    assert settings["record"].pop("drift_std") == CPU_DRIFT_STD
    out.mkdir()
    (out / "reproduce.json").write_text(json.dumps({"settings": settings}))
    with pytest.raises(ValueError, match="other settings \\(record.drift_std: 0.0 -> 0.06\\)"):
        check_same_settings(ReproduceConfig(output_dir=str(out)))
    clean = ReproduceConfig(output_dir=str(out), record=RecordSettings(drift_std=0.0))
    check_same_settings(clean)
    assert "--drift.std=0.0" in command(clean, plan(clean)[0], 1)

    # Nor does it have a takeover group: it trained on its demonstrations alone, and continues only so.
    dagger = ReproduceConfig(output_dir=str(out), record=RecordSettings(drift_std=0.0))
    dagger.takeover.episodes = 100
    with pytest.raises(
        ValueError,
        match=f"other settings \\(takeover: None -> \\{{'episodes': 100, 'driver_steps': {CPU_STEPS // 2}\\}}\\)",
    ):
        check_same_settings(dagger)


def test_a_stage_killed_mid_way_leaves_only_what_its_rerun_can_take(tmp_path):
    """What a killed stage left before its marker: a merge's renamed output (which `condground merge`
    refuses to overwrite) and a training without a checkpoint go; a training with one and the recordings
    (both resume in place) stay, as does everything outside the stage's own directory."""
    from lerobot_condground.experiments.plan import ReproduceConfig, plan
    from lerobot_condground.experiments.reproduce import _prepare

    cfg = ReproduceConfig(output_dir=str(tmp_path))
    cfg.takeover.episodes = 1
    stages = {}
    for stage in plan(cfg):
        stages.setdefault(stage.kind, stage)
    assert {"record", "driver", "takeover", "merge", "train"} <= set(stages)
    left = {}
    for kind, stage in stages.items():
        here = tmp_path / stage.name
        (here / "meta").mkdir(parents=True)
        (here / "meta" / "info.json").write_text("{}")
        left[kind] = here
    (left["train"] / "checkpoints" / "last").mkdir(parents=True)
    (tmp_path / "notes.txt").write_text("mine")
    for stage in stages.values():
        _prepare(cfg, stage)
    gone = {kind for kind, here in left.items() if not here.exists()}
    assert gone == {"merge", "driver"}  # the driver had no checkpoint yet
    assert (left["train"] / "checkpoints" / "last").is_dir() and (tmp_path / "notes.txt").is_file()


def _commands(out, key: str) -> list[str]:
    """The command lines a stage's log shows, one per time the stage was started."""
    return [line for line in (out / "logs" / f"{key}.log").read_text().splitlines() if line.startswith("$ ")]


# A toy run killed and resumed twice (about 3 to 5 min): `pytest -m slow`.
@pytest.mark.slow
def test_a_killed_run_resumes_without_repeating_or_losing_a_stage(tmp_path):
    out = tmp_path / "repro"
    env = {**os.environ, "MUJOCO_GL": "egl", "HF_HUB_OFFLINE": "1"}
    args = [str(BIN / "condground"), "reproduce", f"--output_dir={out}", "--jobs=2", *TOY]
    # Killed hard (the whole process group, as a lost session would) once the training saved a checkpoint.
    first = subprocess.Popen(
        args, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True
    )
    train = out / "train" / "PickPlaceRandomBin-v0" / "full" / "seed0"
    deadline = time.time() + 400
    while not (train / "checkpoints" / "last").exists():
        assert first.poll() is None, first.stdout.read().decode()
        assert time.time() < deadline, "the training saved no checkpoint"
        time.sleep(0.1)
    os.killpg(first.pid, signal.SIGKILL)
    first.wait()
    assert not (out / "stages" / "train__PickPlaceRandomBin-v0__full__seed0.json").exists()
    recorded = (out / "stages" / "datasets__PickPlaceRandomBin-v0.json").stat().st_mtime_ns

    second = run_cli("condground", "reproduce", f"--output_dir={out}", "--jobs=2", *TOY).stdout
    assert "10 stages (4 done)" in second
    assert "start: datasets/" not in second and "start: train/PickPlaceRandomBin-v0/full/seed0" in second
    assert (out / "stages" / "datasets__PickPlaceRandomBin-v0.json").stat().st_mtime_ns == recorded
    for stage in ("demos", "driver", "takeover", "datasets"):
        assert len(_commands(out, f"{stage}__PickPlaceRandomBin-v0")) == 1
    # The variants trained on the demonstrations and the takeover episodes the driver's states began, merged.
    merged = read_json(out / "datasets" / "PickPlaceRandomBin-v0" / "meta" / "condground_record.json")
    assert [episode["source"] for episode in merged["episodes"]] == [0, 0, 1]
    driver = out / "driver" / "PickPlaceRandomBin-v0" / "checkpoints" / "000010" / "pretrained_model"
    assert merged["sources"][1]["record"]["takeover"]["policy_path"] == str(driver)
    assert merged["episodes"][2]["seed"] >= 500_000  # new layouts, none of the demonstrations'
    assert (
        "--dataset.root=" + str(out / "datasets" / "PickPlaceRandomBin-v0")
        in _commands(out, "train__PickPlaceRandomBin-v0__full__seed0")[0]
    )
    commands = _commands(out, "train__PickPlaceRandomBin-v0__full__seed0")
    assert len(commands) == 2 and "--resume=true" in commands[1]  # went on from its checkpoint
    assert (train / "checkpoints" / "000040" / "pretrained_model" / "model.safetensors").is_file()
    results = pd.read_parquet(out / "sweep" / "PickPlaceRandomBin-v0" / "full" / "results.parquet")
    assert len(results) == 2 * 3 and set(results["condition"]) == {"full_mixed"}
    # the run's last three checkpoints (the preset's --eval.pool), each on the same layouts
    assert sorted(results["checkpoint"].str.extract(r"checkpoints/(\d+)/")[0].unique()) == [
        "000020",
        "000030",
        "000040",
    ]
    assert (results.groupby("checkpoint")["layout_seed"].apply(sorted).map(tuple).nunique()) == 1
    assert (
        read_json(out / "probe" / "PickPlaceRandomBin-v0" / "full" / "seed0" / "probe.json")["episodes"] == 1
    )
    assert (out / "diagnose" / "PickPlaceRandomBin-v0" / "full" / "seed0" / "diagnostics.json").is_file()
    report = (out / "report" / "report.md").read_text()
    assert "full_mixed (counterbalanced)" in report and "## Table II" in report

    third = run_cli("condground", "reproduce", f"--output_dir={out}", *TOY).stdout
    assert "10 stages (10 done)" in third and "start:" not in third  # --jobs may change; nothing reruns

    changed = run_cli("condground", "reproduce", f"--output_dir={out}", *TOY, "--train.steps=50", check=False)
    assert changed.returncode == 2
    assert "other settings (train.steps: 40 -> 50)" in changed.stderr


def _processes_naming(text: str) -> list[str]:
    found = []
    for cmdline in pathlib.Path("/proc").glob("[0-9]*/cmdline"):
        try:
            args = cmdline.read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:  # ended meanwhile
            continue
        if text in args:
            found.append(args)
    return found


def test_a_terminated_run_takes_its_stages_with_it(tmp_path):
    """`kill PID` of a reproduce run: the recording it started must not outlive it. (A training stage that
    exits 0 without its checkpoint fails as one message naming the stage; the one flag that made that happen,
    --save_checkpoint=false, is now refused before any stage starts.)"""
    out = tmp_path / "repro"
    flags = [
        f"--output_dir={out}", "--tasks=PickPlaceRandomBin-v0", "--train.variants=standard",
        "--record.episodes=1", "--train.steps=2", "--train.batch_size=2", "--eval.pool=1", "--progress=false",
    ]  # fmt: skip
    env = {**os.environ, "MUJOCO_GL": "egl", "HF_HUB_OFFLINE": "1"}
    first = subprocess.Popen(
        [str(BIN / "condground"), "reproduce", *flags], env=env, stdout=subprocess.DEVNULL
    )
    log = out / "logs" / "datasets__PickPlaceRandomBin-v0.log"
    deadline = time.time() + 120
    while not log.exists():
        assert first.poll() is None and time.time() < deadline
        time.sleep(0.1)
    first.terminate()
    assert first.wait(timeout=60) == 128 + signal.SIGTERM
    assert _processes_naming(str(out)) == []
    assert not list((out / "stages").glob("*"))


class _Lines:
    """A runner's output line by line, with a deadline: a runner that prints nothing must not hang the test."""

    def __init__(self, proc: subprocess.Popen):
        self.proc, self.lines = proc, queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.put(line)
        self.lines.put(None)

    def wait_for(self, text: str, timeout: float = 180) -> None:
        deadline = time.time() + timeout
        while True:
            try:
                line = self.lines.get(timeout=max(0.0, deadline - time.time()))
            except queue.Empty:
                raise AssertionError(f"the runner printed no {text!r} within {timeout} s") from None
            assert line is not None, f"the runner exited (code {self.proc.wait()}) without printing {text!r}"
            if text in line:
                return


def test_two_runners_on_one_directory_share_its_stages_and_a_dead_runners_stage_is_taken_over(tmp_path):
    out = tmp_path / "repro"
    flags = [
        f"--output_dir={out}", "--tasks=PickPlaceRandomBin-v0", "--train.variants=standard",
        "--record.episodes=4", "--progress=false",
    ]  # fmt: skip
    env = {**os.environ, "MUJOCO_GL": "egl", "HF_HUB_OFFLINE": "1"}

    def runner():
        return subprocess.Popen(
            [str(BIN / "condground"), "reproduce", *flags], env=env, stdout=subprocess.PIPE, text=True,
            start_new_session=True,
        )  # fmt: skip

    first = second = runner()
    try:
        _Lines(first).wait_for("start: datasets/PickPlaceRandomBin-v0")
        second = runner()
        lines = _Lines(second)
        lines.wait_for("wait: datasets/PickPlaceRandomBin-v0 runs in another", timeout=60)
        recording = _processes_naming(f"--dataset.root={out}/datasets/PickPlaceRandomBin-v0")
        assert len(recording) == 1  # the second runner left the stage to the first
        os.kill(first.pid, signal.SIGKILL)  # the runner dies; the recording it started goes on
        first.wait()
        # Only once the orphaned recording ended (its lock with it) does the second runner take the stage.
        lines.wait_for("start: datasets/PickPlaceRandomBin-v0")
        deadline = time.time() + 30  # the runner prints its start line just before it logs the command
        while len(_commands(out, "datasets__PickPlaceRandomBin-v0")) < 2 and time.time() < deadline:
            time.sleep(0.1)
        assert len(_commands(out, "datasets__PickPlaceRandomBin-v0")) == 2
        log = (out / "logs" / "datasets__PickPlaceRandomBin-v0.log").read_text()
        assert log.rindex("$ ") > log.index("expert success:")  # the first recording had finished before
    finally:
        for proc in (first, second):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def test_the_report_is_rebuilt_when_the_plan_grew(tmp_path):
    from lerobot_condground.experiments.plan import ReproduceConfig, plan
    from lerobot_condground.experiments.reproduce import _is_done, _marker

    def report_stage(variants: str):
        cfg = ReproduceConfig(output_dir=str(tmp_path), tasks="PickPlaceFixedBin-v0")
        cfg.train.variants = variants
        return cfg, plan(cfg)[-1]

    cfg, report = report_stage("standard")
    marker = _marker(cfg, report)
    marker.parent.mkdir(parents=True)
    marker.write_text(json.dumps({"command": [], "after": list(report.after)}))
    assert _is_done(cfg, report)
    cfg, report = report_stage("standard,full")  # --train.variants grew: more sweeps to report
    assert report.name == "report" and not _is_done(cfg, report)
