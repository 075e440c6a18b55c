"""`condground merge`: recordings merged by LeRobot's own merge, with every episode's provenance kept, and its
refusals of bad input."""

import json
import shutil

import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from helpers import read_json, run_cli
from lerobot_condground.cli import main
from lerobot_condground.core.provenance import RECORD_FILE


def test_a_merge_keeps_how_each_episode_was_made(recorded_dataset, tmp_path):
    drift = tmp_path / "drift"
    run_cli(
        "condground", "record", "--env.task=PickPlaceRandomBin-v0", "--env.condition=full_mixed",
        "--dataset.repo_id=local/test_drift", f"--dataset.root={drift}", "--dataset.num_episodes=1",
        "--seed=50", "--drift.std=0.05", "--progress=false",
    )  # fmt: skip
    out = tmp_path / "merged"
    stale = tmp_path / ".merged.partial"  # what a killed merge leaves: cleared by the rerun
    stale.mkdir()
    (stale / "junk").write_text("x")
    proc = run_cli("condground", "merge", f"--roots=[{recorded_dataset},{drift}]", f"--output.root={out}")
    assert "merged 2 + 1 = 3 episodes" in proc.stdout, proc.stdout
    assert not stale.exists()

    merged = LeRobotDataset("local/condground_merged", root=out)
    assert merged.meta.total_episodes == 3
    provenance = read_json(out / RECORD_FILE)
    sources = [read_json(root / RECORD_FILE) for root in (recorded_dataset, drift)]
    assert [s["record"]["drift"]["std"] for s in provenance["sources"]] == [0.0, 0.05]
    assert [s["root"] for s in provenance["sources"]] == [str(recorded_dataset), str(drift)]
    assert [e["source"] for e in provenance["episodes"]] == [0, 0, 1]
    assert [e["seed"] for e in provenance["episodes"]] == [e["seed"] for s in sources for e in s["episodes"]]
    assert provenance["episodes"][2]["drift_largest_rad"] == sources[1]["episodes"][0]["drift_largest_rad"]
    # The merged third episode is the drift recording's episode, frame for frame.
    own = LeRobotDataset("local/test_drift", root=drift)
    start = int(merged.meta.episodes["dataset_from_index"][2])
    assert merged.meta.episodes["length"][2] == own.meta.total_frames
    for i in (0, own.meta.total_frames - 1):
        np.testing.assert_array_equal(merged.hf_dataset[start + i]["action"], own.hf_dataset[i]["action"])

    # A recording does not resume into a merge (it would rewrite the merged provenance as its own) ...
    bad = run_cli(
        "condground", "record", "--env.task=PickPlaceRandomBin-v0", "--env.condition=full_mixed",
        f"--dataset.root={out}", "--dataset.num_episodes=4", "--progress=false", check=False,
    )  # fmt: skip
    assert bad.returncode == 2 and "holds a merge of 2 datasets" in bad.stderr, bad.stderr[-2000:]
    assert LeRobotDataset("local/condground_merged", root=out).meta.total_episodes == 3
    # ... and a merge is not merged again.
    again = run_cli(
        "condground", "merge", f"--roots=[{out},{drift}]", f"--output.root={tmp_path / 'x'}", check=False
    )
    assert again.returncode == 2 and "is itself a merge" in again.stderr, again.stderr[-2000:]
    assert not (tmp_path / "x").exists()


def test_refuses_bad_input(recorded_dataset, tmp_path, capsys):
    out = tmp_path / "out"

    def merge(*roots, output=out) -> str:
        assert main(["merge", f"--roots=[{','.join(map(str, roots))}]", f"--output.root={output}"]) == 2
        return capsys.readouterr().err

    assert "two or more roots" in merge(recorded_dataset)
    assert main(["merge", f"--roots=[{recorded_dataset},{recorded_dataset}]", "--output.video=false"]) == 2
    assert "--output.video=false" in capsys.readouterr().err
    assert "--roots[1]=" in merge(recorded_dataset, tmp_path / "missing")
    assert "already exists" in merge(recorded_dataset, recorded_dataset, output=recorded_dataset)
    assert "is --roots[0] again: its episodes would be merged twice" in merge(
        recorded_dataset, recorded_dataset
    )
    inside = recorded_dataset / "merged"
    assert f"--output.root={inside} overlaps --roots[0]" in merge(
        recorded_dataset, tmp_path / "missing", output=inside
    )
    assert not inside.exists()
    # A recording whose provenance does not list every episode: the merged list would misplace them.
    short = tmp_path / "short"
    shutil.copytree(recorded_dataset, short)
    record = read_json(short / RECORD_FILE)
    record["episodes"] = record["episodes"][:1]
    (short / RECORD_FILE).write_text(json.dumps(record))
    assert "lists 1 episodes, its meta/info.json 2" in merge(recorded_dataset, short)
    # fps and features must agree: named by source and feature (not LeRobot's two whole feature tables).
    for fps in (10, 20):
        other = tmp_path / f"other_{fps}"
        ds = LeRobotDataset.create(
            "local/other", fps=fps, root=other, use_videos=False,
            features={"action": {"dtype": "float32", "shape": (1,), "names": ["a"]}},
        )  # fmt: skip
        ds.add_frame({"action": np.zeros(1, np.float32), "task": "t"})
        ds.save_episode()
        ds.finalize()
    assert f"--roots[1]={tmp_path / 'other_10'} runs at 10 fps, --roots[0] at 20" in merge(
        recorded_dataset, tmp_path / "other_10"
    )
    err = merge(recorded_dataset, tmp_path / "other_20")
    assert "have other features (observation.images.top only in --roots[0]" in err
    assert "action of another shape or type)" in err
    assert len(err.strip().splitlines()[-1]) < 1000
    assert not out.exists() and not (tmp_path / ".out.partial").exists()
