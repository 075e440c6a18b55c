"""`condground augment`: an augmented copy of a recorded dataset, and its refusals of bad input."""

import numpy as np
import torch

from helpers import read_json, run_cli
from lerobot_condground.cli import main
from lerobot_condground.core.labels import OBS_SEGMENTATION, SYNTHETIC_DISTRACTOR, decode_labels

CAM = "observation.images.top"


def test_augment_differs_only_where_synthetic(recorded_dataset, tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    out_root = tmp_path / "augmented"
    # PNG frames, so the comparison is exact (video would re-encode every pixel).
    proc = run_cli(
        "condground",
        "augment",
        "--dataset.repo_id=local/test_full_mixed",
        f"--dataset.root={recorded_dataset}",
        "--output.repo_id=local/test_augmented",
        f"--output.root={out_root}",
        "--output.video=false",
        "--copy_paste.prob=1.0",
        "--copy_paste.seed=3",
        "--progress=false",
    )
    assert "frames with pastes:" in proc.stdout, proc.stdout
    source = LeRobotDataset("local/test_full_mixed", root=recorded_dataset)
    augmented = LeRobotDataset("local/test_augmented", root=out_root)
    assert augmented.meta.total_episodes == source.meta.total_episodes
    assert augmented.meta.total_frames == source.meta.total_frames
    assert augmented.meta.fps == source.meta.fps and augmented.meta.robot_type == source.meta.robot_type
    assert set(augmented.meta.features) == set(source.meta.features)
    assert read_json(out_root / "meta/condground_record.json") == read_json(
        recorded_dataset / "meta/condground_record.json"
    )
    assert read_json(out_root / "meta/condground_augment.json")["copy_paste"]["seed"] == 3
    pasted = 0
    for i in range(0, len(source), 13):
        a, b = decode_labels(source[i]), decode_labels(augmented[i])
        synthetic = b[OBS_SEGMENTATION] == SYNTHETIC_DISTRACTOR
        pasted += int(synthetic.any())
        assert torch.equal((a[CAM] != b[CAM]).any(0) & ~synthetic, torch.zeros_like(synthetic))
        assert torch.equal(a[OBS_SEGMENTATION][~synthetic], b[OBS_SEGMENTATION][~synthetic])
        for key in ("action", "observation.state", "observation.phase", "observation.prompt.object"):
            assert torch.equal(a[key], b[key]), key
        assert a["task"] == b["task"] and a["episode_index"] == b["episode_index"]
    assert pasted > 0


def _augment(*args) -> int:
    return main(["augment", "--progress=false", *args])


def test_refuses_bad_input(recorded_dataset, tmp_path, capsys):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    source = ["--dataset.repo_id=local/test_full_mixed", f"--dataset.root={recorded_dataset}"]
    out = [f"--output.root={tmp_path / 'out'}"]
    assert _augment(f"--dataset.root={tmp_path / 'missing'}", *out) == 2
    assert "--dataset.root=" in capsys.readouterr().err
    assert _augment(*source, f"--output.root={recorded_dataset}") == 2
    assert "already exists" in capsys.readouterr().err
    assert _augment(*source, *out, "--copy_paste.camera_key=observation.images.wrist") == 2
    assert "observation.images.top" in capsys.readouterr().err
    assert _augment(*source, *out, "--copy_paste.prob=2") == 2
    assert "--copy_paste.prob=2.0 is not allowed" in capsys.readouterr().err
    assert _augment(*source, *out, "--copy_paste.warmup_steps=100") == 2
    assert "--copy_paste.warmup_steps=100 ramps pastes in over training batches" in capsys.readouterr().err
    # A dataset without segmentation cannot be augmented.
    plain = tmp_path / "plain"
    ds = LeRobotDataset.create(
        "local/plain",
        fps=10,
        root=plain,
        use_videos=False,
        features={
            CAM: {"dtype": "image", "shape": (8, 8, 3), "names": ["height", "width", "channels"]},
            "action": {"dtype": "float32", "shape": (1,), "names": ["a"]},
        },
    )
    ds.add_frame({CAM: np.zeros((8, 8, 3), np.uint8), "action": np.zeros(1, np.float32), "task": "t"})
    ds.save_episode()
    ds.finalize()
    assert _augment("--dataset.repo_id=local/plain", f"--dataset.root={plain}", *out) == 2
    assert OBS_SEGMENTATION in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_a_killed_augment_leaves_nothing_that_blocks_the_rerun(recorded_dataset, tmp_path):
    import os
    import signal
    import subprocess
    import time

    from helpers import BIN

    out_root = tmp_path / "augmented"
    args = [
        str(BIN / "condground"),
        "augment",
        "--dataset.repo_id=local/test_full_mixed",
        f"--dataset.root={recorded_dataset}",
        "--output.repo_id=local/test_killed",
        f"--output.root={out_root}",
        "--progress=false",
    ]
    proc = subprocess.Popen(args, env={**os.environ, "MUJOCO_GL": "egl"}, stderr=subprocess.DEVNULL)
    partial = tmp_path / ".augmented.partial"
    deadline = time.time() + 120
    while not (partial / "meta" / "info.json").exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert partial.exists() and not out_root.exists(), "killed while writing, before the copy was whole"
    out = run_cli("condground", *args[1:])
    assert "frames with pastes:" in out.stdout
    assert (out_root / "meta" / "condground_augment.json").is_file() and not partial.exists()
