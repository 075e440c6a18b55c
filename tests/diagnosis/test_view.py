"""Episodes in rerun: LeRobot's `lerobot-dataset-viz` on our datasets, and `condground view` with the label
layers (segmentation as a SegmentationImage under an annotation context, phase, prompts) and attention runs,
read back with rerun's own `rerun rrd print`."""

import os
import re
import subprocess

import pytest

from helpers import BIN, run_cli
from lerobot_condground.cli import main

REPO = "local/test_full_mixed"


def entities(rrd, tmp_path) -> dict[str, set[str]]:
    """entity path -> archetypes, from `rerun rrd print` (the viewer's analytics off, nothing sent)."""
    env = {**os.environ, "XDG_CONFIG_HOME": str(tmp_path / "config")}
    subprocess.run([str(BIN / "rerun"), "analytics", "disable"], env=env, capture_output=True, timeout=60)
    out = subprocess.run(
        [str(BIN / "rerun"), "rrd", "print", str(rrd)], env=env, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr[-2000:]
    found: dict[str, set[str]] = {}
    for path, columns in re.findall(r" - (/\S*) - data columns: \[([^\]]*)\]", out.stdout):
        found.setdefault(path, set()).update(c.split(":")[0] for c in columns.split())
    assert found, out.stdout[:2000]
    return found


def test_lerobot_dataset_viz_writes_an_rrd_of_our_dataset(recorded_dataset, tmp_path):
    run_cli(
        "lerobot-dataset-viz", "--repo-id", REPO, "--root", str(recorded_dataset), "--episode-index", "0",
        "--save", "1", "--output-dir", str(tmp_path / "viz"), "--num-workers", "0",
    )  # fmt: skip
    (rrd,) = (tmp_path / "viz").glob("*.rrd")
    found = entities(rrd, tmp_path)
    assert found["/observation.images.top"] == {"Image"} and "Scalars" in found["/action"]


def test_condground_view_logs_the_label_layers(recorded_dataset, tmp_path):
    rrd = tmp_path / "episode.rrd"
    run_cli(
        "condground", "view", f"--dataset.repo_id={REPO}", f"--dataset.root={recorded_dataset}",
        "--episode=1", f"--output={rrd}", "--progress=false",
    )  # fmt: skip
    found = entities(rrd, tmp_path)
    assert found["/cameras/top"] == {"Image"}
    assert found["/cameras/top/segmentation"] == {"SegmentationImage"}  # over its camera
    assert found["/cameras"] == {"AnnotationContext"}  # names and colours of the label ids, for every map
    assert found["/labels/phase"] == {"Scalars"}
    assert found["/prompts/object"] == found["/prompts/receptacle"] == {"Image"}
    assert {"/state/gripper.pos", "/action/shoulder_pan.pos"} <= set(found)
    # Its own recording is replaced by the next view into the same file.
    size = rrd.stat().st_size
    run_cli(
        "condground", "view", f"--dataset.repo_id={REPO}", f"--dataset.root={recorded_dataset}",
        "--episode=0", f"--output={rrd}", "--progress=false",
    )  # fmt: skip
    assert rrd.stat().st_size != size and "/cameras/top" in entities(rrd, tmp_path)


def test_condground_view_of_an_attention_run(tiny_checkpoints, tmp_path):
    from lerobot_condground.core.configs import EvalEnvConfig, PolicyRefConfig
    from lerobot_condground.diagnosis.attention import AttentionConfig, AttentionOptions, run_attention

    out = run_attention(
        AttentionConfig(
            policy=PolicyRefConfig(path=str(tiny_checkpoints[0])),
            env=EvalEnvConfig(condition="full_mixed", episode_length=6),
            attention=AttentionOptions(seed=2),
            output_dir=str(tmp_path / "attention"),
            progress=False,
        )
    )
    rrd = tmp_path / "attention.rrd"
    assert main(["view", f"--attention_dir={out}", f"--output={rrd}", "--progress=false"]) == 0
    found = entities(rrd, tmp_path)
    assert found["/attention/overlay"] == {"Image"} and found["/attention/map"] == {"Tensor"}
    assert {"/attention/stage", "/attention/phase_predicted", "/attention/mass/competitors"} <= set(found)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--episode=2"], "--episode=2 is not allowed; allowed: 0 to 1 (2 episodes in "),
        (
            ["--output=episode.mp4"],
            "--output='episode.mp4' is not allowed; allowed: a file name ending in .rrd",
        ),
    ],
)
def test_bad_input_is_one_line(recorded_dataset, tmp_path, capsys, args, message):
    data = [f"--dataset.repo_id={REPO}", f"--dataset.root={recorded_dataset}"]
    assert main(["view", *data, f"--output={tmp_path / 'x.rrd'}", *args]) == 2
    assert message in capsys.readouterr().err.strip().splitlines()[-1]
    assert not (tmp_path / "x.rrd").exists()


def test_a_dataset_without_labels_is_named(plain_dataset, tmp_path, capsys):
    data = ["--dataset.repo_id=local/test_plain", f"--dataset.root={plain_dataset}"]
    assert main(["view", *data, f"--output={tmp_path / 'x.rrd'}"]) == 2
    assert "has no label features" in capsys.readouterr().err and not (tmp_path / "x.rrd").exists()


def test_view_refuses_an_output_it_cannot_write_in_one_line(tmp_path, capsys):
    from lerobot_condground.cli import main

    (tmp_path / "folder.rrd").mkdir()
    (tmp_path / "afile").write_text("the user's")
    (tmp_path / "notes.rrd").write_text("the user's too")
    for output, fragment in (
        (tmp_path / "folder.rrd", "allowed: a file name ending in .rrd"),
        (tmp_path / "afile" / "x.rrd", "afile is a file, not a folder"),
        (tmp_path / "notes.rrd", "exists and is not a rerun recording; allowed: a new file name"),
    ):
        assert main(["view", f"--attention_dir={tmp_path}", f"--output={output}"]) == 2
        assert fragment in capsys.readouterr().err
    assert (tmp_path / "afile").read_text() == "the user's"
    assert (tmp_path / "notes.rrd").read_text() == "the user's too"
