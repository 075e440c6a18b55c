import json
import subprocess
import sys
from importlib.metadata import distribution
from pathlib import Path

import pytest

from helpers import run_cli
from lerobot_condground.core.training import CPU_DRIFT_STD, amp_flags
from lerobot_condground.evaluation.results import read_table


def test_distribution_name_keeps_underscores_for_lerobot_discovery():
    assert distribution("lerobot_policy_condground").metadata["Name"] == "lerobot_policy_condground"


def test_lerobot_discovers_the_plugin_and_the_import_stays_cheap():
    code = (
        "import sys\n"
        "from lerobot.utils.import_utils import register_third_party_plugins\n"
        "register_third_party_plugins()\n"
        "from lerobot.envs.configs import EnvConfig\n"
        "import gymnasium as gym\n"
        "assert 'condground' in EnvConfig.get_known_choices(), EnvConfig.get_known_choices()\n"
        "from lerobot.configs.policies import PreTrainedConfig\n"
        "assert 'act_modified' in PreTrainedConfig.get_known_choices()\n"
        "from lerobot.processor.pipeline import ProcessorStepRegistry\n"
        "assert any('copy_paste' in name for name in ProcessorStepRegistry.list())\n"
        "from lerobot.policies.factory import get_policy_class\n"
        "assert get_policy_class('act_modified').name == 'act_modified'\n"
        "assert 'gym_condground/PickPlaceRandomBin-v0' in gym.registry\n"
        "assert 'lerobot_condground' in sys.modules\n"
        # OpenCV is imported by LeRobot's own policy package (ACTConfig), which every stock script
        # loads anyway; MuJoCo is ours to keep out of discovery.
        "assert 'mujoco' not in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_subpackages_map_to_the_top_level_pillars():
    import lerobot_condground.envs as envs
    import lerobot_condground.policies as policies
    import lerobot_condground.processors as processors

    for module, folder in ((envs, "envs"), (policies, "policies"), (processors, "processors")):
        assert module.__file__.replace("\\", "/").endswith(f"/{folder}/__init__.py")


def test_a_built_wheel_holds_every_module_of_the_source_tree(tmp_path):
    """The editable install finds any module; a wheel (`pip install .`, a machine without the checkout)
    holds only the packages pyproject lists, which once missed the policies' own folders."""
    import shutil
    import zipfile

    root = Path(__file__).resolve().parents[1]
    folders = {"envs": "lerobot_condground/envs", "policies": "lerobot_condground/policies"}
    folders |= {"processors": "lerobot_condground/processors"}
    # From a copy: setuptools reuses a checkout's build/ folder, which can hold what pyproject no longer lists.
    source_tree = tmp_path / "src"
    for top in ("lerobot_condground", "lerobot_policy_condground", *folders):
        shutil.copytree(root / top, source_tree / top, ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(root / name, source_tree / name)
    build = [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation"]
    subprocess.run([*build, "-w", tmp_path, "."], check=True, cwd=source_tree)
    (wheel,) = tmp_path.glob("*.whl")
    packed = set(zipfile.ZipFile(wheel).namelist())
    missing = []
    for top in ("lerobot_condground", "lerobot_policy_condground", *folders):
        for source in (root / top).rglob("*"):
            if source.suffix not in {".py", ".j2"} or "__pycache__" in source.parts:
                continue
            relative = source.relative_to(root).as_posix()
            if top in folders:
                relative = relative.replace(top, folders[top], 1)
            if relative not in packed:
                missing.append(relative)
    assert not missing, missing


def test_cli_help_lists_commands_and_flags(capsys):
    from lerobot_condground.cli import main

    out = run_cli("condground", "--help").stdout  # the console script itself; the rest in this process
    for command in (
        "record",
        "bench",
        "quickstart",
        "augment",
        "sweep",
        "probe",
        "diagnose",
        "attention",
        "report",
    ):
        assert f"  {command} " in out, command
    flags = {
        "record": (
            "--env.task",
            "--env.condition",
            "--dataset.repo_id",
            "--dataset.root",
            "--dataset.num_episodes",
        ),
        # The diagnosis flags other tools rely on.
        "sweep": (
            "--policy.paths",
            "--env.task",
            "--sweep.conditions",
            "--eval.seeds",
            "--eval.n_episodes",
            "--output_dir",
            "--launcher",
            "--workers",
        ),
        "diagnose": ("--policy.path", "--env.task", "--output_dir"),
        "probe": ("--policy.path", "--output_dir"),
        "attention": ("--policy.path", "--env.task", "--env.condition", "--output_dir"),
    }
    for command, names in flags.items():
        with pytest.raises(SystemExit) as done:
            main([command, "--help"])
        text = capsys.readouterr().out
        assert done.value.code == 0
        for flag in names:
            assert flag in text, (command, flag)
    assert main(["recrod"]) == 2 and "unknown command 'recrod'" in capsys.readouterr().err


def test_example_runs(tmp_path):
    import cv2

    root = Path(__file__).resolve().parents[1]
    out = tmp_path / "frame.png"
    proc = subprocess.run(
        [sys.executable, str(root / "examples" / "run_expert.py"), "--out", str(out)],
        capture_output=True,
        text=True,
        check=True,
    )
    assert "stage reached: 3" in proc.stdout and "success: True" in proc.stdout
    assert cv2.imread(str(out)).shape == (240, 640, 3)


def test_quickstart_trains_and_evaluates_act_modified(tmp_path):
    out = run_cli(
        "condground",
        "quickstart",
        f"--output_dir={tmp_path}",
        "--episodes_per_task=1",
        "--train.episodes=1",
        "--train.variant=full",
        "--expert_episodes=1",
        "--train.steps=2",
        "--train.batch_size=2",
        "--eval.episodes=1",
        "--eval.episode_length=10",
        "--diagnosis.episodes=1",
        "--diagnosis.probe_episodes=1",
        "--diagnosis.pairs=1",
        "--diagnosis.frame_stride=8",
        "--progress=false",
        timeout=900,
    ).stdout
    lines = out.splitlines()
    for policy in ("act_modified/full", "expert"):
        for condition in ("clean", "full_mixed"):
            assert any(line.split()[:2] == [policy, condition] for line in lines), out[-3000:]
    assert (
        tmp_path / "train" / "checkpoints" / "last" / "pretrained_model" / "policy_preprocessor.json"
    ).exists()
    # Task 1 is recorded at the configuration's drift (recovery data), Task 2 clean; trained at its precision.
    datasets = tmp_path / "datasets"
    provenance = {
        task: json.loads((datasets / task / "meta" / "condground_record.json").read_text())["drift"]["std"]
        for task in ("PickPlaceFixedBin-v0", "PickPlaceRandomBin-v0")
    }
    assert provenance == {"PickPlaceFixedBin-v0": CPU_DRIFT_STD, "PickPlaceRandomBin-v0": 0.0}
    trained = json.loads(
        (tmp_path / "train" / "checkpoints" / "last" / "pretrained_model" / "config.json").read_text()
    )
    assert trained["use_amp"] == bool(amp_flags())

    # It ends with the diagnosis suite and its report; the stock CLI rebuilds the report from the outputs.
    diagnosis = tmp_path / "diagnosis"
    rows = read_table(diagnosis / "sweep" / "results.parquet")
    assert len(rows) == 2 * 4 and set(rows.policy_label) == {"act_modified/full", "expert"}
    for name in (
        "diagnose/diagnostics.json",
        "probe/probe.json",
        "attention/attention.mp4",
        "report/report.html",
        "report/report.md",
    ):
        assert (diagnosis / name).exists(), name
    assert f"Report: {diagnosis / 'report' / 'report.html'}" in out
    dirs = [f"--input_dir={diagnosis / name}" for name in ("sweep", "diagnose", "probe", "attention")]
    rebuilt = run_cli("condground", "report", *dirs, f"--output={tmp_path / 'again.html'}")
    assert "report:" in rebuilt.stdout and "Table I" in (tmp_path / "again.html").read_text()
    bad = run_cli(
        "condground",
        "report",
        f"--input_dir={tmp_path / 'train'}",
        f"--output={tmp_path / 'x.html'}",
        check=False,
    )
    assert (
        bad.returncode == 2 and bad.stderr.startswith("condground report:") and "Traceback" not in bad.stderr
    )
    checkpoint = tmp_path / "train" / "checkpoints" / "last" / "pretrained_model"
    bad = run_cli(
        "condground",
        "attention",
        f"--policy.path={checkpoint}",
        "--env.condition=full_mix",
        f"--output_dir={tmp_path / 'att'}",
        check=False,
    )
    assert bad.returncode == 2 and "full_mix" in bad.stderr and "Traceback" not in bad.stderr


@pytest.mark.parametrize(
    "args, named",
    [
        # A config's own check (wrapped by draccus), a flag draccus cannot decode, a check inside the command.
        (["record", "--dataset.num_episodes=0"], "num_episodes=0"),
        (["record", "--max_consecutive_failures=0"], "--max_consecutive_failures=0 is not allowed"),
        (["record", "--seed=-1"], "--seed=-1 is not allowed"),
        (["record", "--env.fps=abc"], "`env.fps`: Couldn't parse 'abc' into an int"),
        (["record", "--dataset.repo_id=../../x"], "repo_id='../../x' is not a hub id"),
        (["record", "--dataset.num_episodes=1000000000"], "allowed: 1 to 100000"),
        (["record", "--seed=999990", "--dataset.num_episodes=20"], "at most 10 episodes from this seed"),
        (["sweep", "--eval.seeds=many"], "many"),
        (["sweep", "--policy.path=x", "--eval.seed_offset=-5"], "--eval.seed_offset=-5 is not allowed"),
        (["diagnose", "--policy.path=x", "--env.condition=full_mix"], "full_mix"),
        (["bench", "--train.steps=-1"], "--train.steps=-1 is not allowed; allowed: a number >= 1"),
        (["bench", "--seconds=nan"], "--seconds=nan is not allowed"),
        (
            ["bench", "--bogus=1"],
            "unrecognized arguments: --bogus=1; `condground bench --help` lists the flags",
        ),
        (["quickstart", "--train.episodes=0"], "--train.episodes=0 is not allowed"),
        (
            ["compare", "--eval.conditions=clean,full_mix"],
            "--eval.conditions='clean,full_mix' is not allowed",
        ),
        (["compare", "--treated.flags=--steps=1", "--treated.runs=a,b"], "--treated has flags and runs"),
        (["compare", "--baseline.name=std", "--treated.name=std"], "--treated.name are both 'std'"),
        (["compare", "--stage=plot"], "--stage='plot' is not allowed"),
        (["quickstart", "--train.drift_std=0.5"], "--train.drift_std=0.5 is not allowed; allowed: 0 (clean)"),
        (["quickstart", "--output_dir="], "--output_dir is empty"),
        (["quickstart", "--diagnosis.workers=0"], "--diagnosis.workers=0 is not allowed"),
    ],
)
def test_every_command_reports_bad_input_in_one_line(args, named, tmp_path, monkeypatch, capsys):
    """One error policy: the bad value named on one line, exit code 2, no traceback, nothing written."""
    from lerobot_condground.cli import main

    monkeypatch.chdir(tmp_path)
    assert main(args) == 2
    lines = [
        line for line in capsys.readouterr().err.strip().splitlines() if "third-party plugin" not in line
    ]
    assert len(lines) == 1 and lines[0].startswith(f"condground {args[0]}:") and named in lines[0], lines
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(
    "args",
    [
        *(
            [command, "--output_dir=taken"]
            for command in (
                "sweep",
                "subgoals",
                "probe",
                "diagnose",
                "attention",
                "fit",
                "failures",
                "quickstart",
                "reproduce",
                "compare",
            )
        ),
        ["record", "--dataset.root=taken"],
        ["augment", "--dataset.root=data", "--output.root=taken"],
    ],
)
def test_an_output_folder_that_is_a_file_is_one_line(args, tmp_path, monkeypatch, capsys):
    from lerobot_condground.cli import main

    monkeypatch.chdir(tmp_path)
    (tmp_path / "taken").write_text("the user's file")
    assert main(args) == 2
    lines = [
        line for line in capsys.readouterr().err.strip().splitlines() if "third-party plugin" not in line
    ]
    assert len(lines) == 1 and "='taken' is an existing file; allowed: a folder" in lines[0], lines
    assert [p.name for p in tmp_path.iterdir()] == ["taken"] and (
        tmp_path / "taken"
    ).read_text() == "the user's file"


def test_a_group_flag_keeps_the_command_default_of_the_group():
    """draccus rebuilds a group from its class defaults once one of its flags is given: the commands' own
    defaults for shared groups must survive that."""
    import draccus

    from lerobot_condground.diagnosis.attention import AttentionConfig
    from lerobot_condground.diagnosis.diagnose import DiagnoseConfig

    assert (
        draccus.parse(AttentionConfig, args=["--env.task=PickPlaceFixedBin-v0"]).env.condition == "full_mixed"
    )
    assert draccus.parse(DiagnoseConfig, args=["--env.episode_length=5"]).env.condition == "clean"


def test_a_range_flag_stays_text_where_yaml_would_read_base_60():
    """draccus reads values as YAML 1.1, where `1:2` is the number 62: --fit.episodes=1:2 must stay a range."""
    import importlib

    from lerobot_condground.cli import _parse

    fit = importlib.import_module("lerobot_condground.scripts.fit")
    for text in ("1:2", "5:9", "0:20", "3,5"):
        assert _parse(fit, [f"--fit.episodes={text}"], "condground fit").fit.episodes == text
    import draccus

    with pytest.raises(draccus.utils.ParsingError, match="n_episodes"):
        _parse(
            importlib.import_module("lerobot_condground.scripts.sweep"),
            ["--eval.n_episodes=1:2"],
            "condground sweep",
        )
