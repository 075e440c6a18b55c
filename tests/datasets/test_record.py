import json
import os
import shutil
import signal
import subprocess

import numpy as np
import pytest
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from helpers import BIN, read_json, run_cli
from lerobot_condground.core.labels import (
    OBS_PHASE,
    OBS_PROMPT_OBJECT,
    OBS_PROMPT_RECEPTACLE,
    OBS_SEGMENTATION,
    decode_labels,
    phase_masks,
)
from lerobot_condground.core.provenance import RECORD_FILE
from lerobot_condground.envs.assets import COLORS
from lerobot_condground.envs.robot import HOME_QPOS, MOTOR_NAMES


def test_recorded_dataset_loads_with_lerobot_and_labels_are_consistent(recorded_dataset):
    ds = LeRobotDataset("local/test_full_mixed", root=recorded_dataset)
    assert ds.meta.total_episodes == 2 and ds.fps == 20
    assert ds.meta.features["observation.state"]["names"] == list(MOTOR_NAMES)
    assert ds.meta.video_keys == ["observation.images.top"]
    # Label images are PNG strings: cheap to fetch for every frame of an action chunk, skipped by stats.
    assert all(
        ds.meta.features[key]["dtype"] == "string" and key not in ds.meta.stats
        for key in (OBS_SEGMENTATION, OBS_PROMPT_OBJECT, OBS_PROMPT_RECEPTACLE)
    )
    provenance = read_json(recorded_dataset / RECORD_FILE)
    assert provenance["env"]["condition"] == "full_mixed" and len(provenance["episodes"]) == 2
    for ep in range(2):
        start = ds.meta.episodes["dataset_from_index"][ep]
        end = ds.meta.episodes["dataset_to_index"][ep]
        entities = provenance["episodes"][ep]["entities"]
        assert sorted(e["match"] for e in entities[2:]) == [
            "color",
            "color",
            "neither",
            "neither",
            "shape",
            "shape",
        ]
        phases = np.array([int(ds[i][OBS_PHASE]) for i in range(start, end)])
        assert phases[0] == 0 and phases[-1] == 1 and np.all(np.diff(phases) >= 0)
        switch = start + int(np.argmax(phases))
        for idx, color in ((start, "red"), (switch - 1, "red"), (switch + 5, "blue")):
            item = decode_labels(ds[idx])
            relevant, competitors = phase_masks(item[OBS_SEGMENTATION], item[OBS_PHASE])
            relevant = relevant.numpy()
            assert relevant.sum() > 20 and not (relevant & competitors.numpy()).any()
            rgb = item["observation.images.top"].numpy().transpose(1, 2, 0)[relevant].mean(axis=0)
            assert np.argmax(rgb) == np.argmax(COLORS[color]), (idx, rgb)
        item = decode_labels(ds[start])
        seg = item[OBS_SEGMENTATION].numpy()
        assert set(np.unique(seg)) == set(range(9))
        rgb = item["observation.images.top"].numpy().transpose(1, 2, 0)
        for entity in entities:
            mean = rgb[seg == entity["label"]].mean(axis=0)
            assert np.argmax(mean) == np.argmax(COLORS[entity["color"]]) or entity["color"] == "yellow", (
                entity
            )
        for key, color in ((OBS_PROMPT_OBJECT, "red"), (OBS_PROMPT_RECEPTACLE, "blue")):
            crop = item[key].numpy().astype(float)
            assert crop.shape == (64, 64, 3)
            assert np.argmax(crop[20:44, 20:44].reshape(-1, 3).mean(axis=0)) == np.argmax(COLORS[color])
        assert item["task"] == "Pick the red cube and place it in the blue bowl."


def test_rerun_resumes_and_different_settings_are_refused(tmp_path, capsys):
    root = tmp_path / "ds"
    common = [
        "--env.task=PickPlaceFixedBin-v0",
        "--dataset.repo_id=local/resume",
        f"--dataset.root={root}",
        "--progress=false",
        "--env.observation_height=96",
        "--env.observation_width=128",
        "--env.wrist_camera=true",
    ]
    run_cli("condground", "record", *common, "--dataset.num_episodes=1")
    out = run_cli("condground", "record", *common, "--dataset.num_episodes=2")
    assert "expert success: 1/1" in out.stdout
    ds = LeRobotDataset("local/resume", root=root)
    assert ds.meta.total_episodes == 2 and len(ds) == ds.meta.total_frames
    assert ds.meta.video_keys == ["observation.images.top", "observation.images.wrist"]
    assert ds[len(ds) - 1]["observation.images.wrist"].shape == (3, 96, 128)
    seeds = [e["seed"] for e in read_json(root / RECORD_FILE)["episodes"]]
    assert len(set(seeds)) == 2
    bad = run_cli(
        "condground", "record", *common, "--dataset.num_episodes=3", "--env.condition=full_mixed", check=False
    )
    assert bad.returncode != 0
    assert (
        "already holds a dataset recorded differently" in bad.stderr
        and "env.condition 'clean' != 'full_mixed'" in bad.stderr
    )
    # A dataset recorded before the servo setting existed holds the targets-set-at-once expert's motion.
    # ... and before the competitor pool existed, the evaluation pool's competitors.
    provenance = read_json(root / RECORD_FILE)
    assert provenance["env"].pop("servo") == "interpolated"
    assert provenance["env"].pop("competitor_pool") == "eval"
    (root / RECORD_FILE).write_text(json.dumps(provenance))
    bad = run_cli("condground", "record", *common, "--dataset.num_episodes=3", check=False)
    assert bad.returncode != 0 and "env.servo 'direct' != 'interpolated'" in bad.stderr, bad.stderr
    assert "competitor_pool" not in bad.stderr, bad.stderr
    bad = run_cli(
        "condground",
        "record",
        *common,
        "--dataset.num_episodes=3",
        "--env.competitor_pool=augmentation",
        check=False,
    )
    assert bad.returncode != 0 and "env.competitor_pool 'eval' != 'augmentation'" in bad.stderr, bad.stderr
    assert LeRobotDataset("local/resume", root=root).meta.total_episodes == 2

    # Episodes the record does not list were added by something else (a stock merge, a copy): their seeds
    # are unknown, so a resumed recording could repeat their layouts and its record would misname them.
    from lerobot_condground.cli import main

    files = {p: p.read_bytes() for p in root.rglob("*") if p.is_file() and p != root / RECORD_FILE}
    provenance["episodes"] = provenance["episodes"][:1]
    (root / RECORD_FILE).write_text(json.dumps(provenance))
    assert main(["record", *common, "--dataset.num_episodes=3"]) == 2
    assert f"holds 2 episodes and its {RECORD_FILE} lists 1" in capsys.readouterr().err
    (root / RECORD_FILE).unlink()
    assert main(["record", *common, "--dataset.num_episodes=3"]) == 2
    err = capsys.readouterr().err
    assert f"holds 2 episodes and no {RECORD_FILE}" in err and "`condground merge`" in err, err
    assert {p: p.read_bytes() for p in root.rglob("*") if p.is_file()} == files


def test_a_recording_that_saved_no_episode_does_not_block_the_corrected_rerun(tmp_path):
    root = tmp_path / "ds"
    common = ["--env.task=PickPlaceFixedBin-v0", "--dataset.repo_id=local/empty", f"--dataset.root={root}",
              "--progress=false", "--dataset.num_episodes=1"]  # fmt: skip
    failed = run_cli(
        "condground", "record", *common, "--env.observation_height=64", "--env.observation_width=80",
        "--env.episode_length=3", "--max_consecutive_failures=1", check=False,
    )  # fmt: skip
    assert failed.returncode == 2, failed.stderr[-2000:]
    assert "--env.episode_length=3" in failed.stderr.strip().splitlines()[-1]
    assert (root / RECORD_FILE).exists()  # the failed seed is on record until a rerun starts afresh
    # A user's file, or a link out of the folder: refused, and nothing is removed, here or behind the link.
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "precious.txt").write_text("mine")
    (root / "notes.txt").write_text("mine")
    shutil.rmtree(root / "images", ignore_errors=True)
    (root / "images").symlink_to(outside, target_is_directory=True)
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    refused = run_cli("condground", "record", *common, check=False)
    assert refused.returncode == 2, refused.stderr[-2000:]
    assert "notes.txt" in refused.stderr and "images (a link)" in refused.stderr
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before
    (root / "notes.txt").unlink()
    (root / "images").unlink()
    out = run_cli(
        "condground", "record", *common, "--env.observation_height=96", "--env.observation_width=128"
    )
    assert "expert success: 1/1" in out.stdout
    assert LeRobotDataset("local/empty", root=root).meta.total_episodes == 1


# Runs `condground record` and SIGKILLs it at one chosen moment of saving its second episode (index 1): the
# moments are LeRobot's own steps, wrapped in this process only, so the kill lands there on any machine.
KILL_AT = """
import os, signal, sys
from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata
from lerobot.datasets.dataset_writer import DatasetWriter
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot_condground.cli import main

moment = sys.argv.pop(1)
frames_seen = [0]

def kill_before(owner, name, when):
    original = getattr(owner, name)
    def wrapped(self, *args, **kwargs):
        if moment == name and when(self, *args):
            os.kill(os.getpid(), signal.SIGKILL)
        return original(self, *args, **kwargs)
    setattr(owner, name, wrapped)

def tenth_frame_of_episode_1(self, *args):
    frames_seen[0] += self.meta.total_episodes == 1
    return frames_seen[0] == 10

kill_before(LeRobotDataset, "add_frame", tenth_frame_of_episode_1)  # images of episode 1 being written
kill_before(DatasetWriter, "_save_episode_video", lambda self, key, index, *a: index == 1)  # its parquet open
kill_before(LeRobotDatasetMetadata, "_save_episode_metadata", lambda self, *a: self.total_episodes == 1)  # video in place
kill_before(LeRobotDatasetMetadata, "finalize", lambda self: self.total_episodes == 2)  # counted, index unwritten
sys.argv = ["condground", *sys.argv[1:]]
main()
"""


@pytest.mark.parametrize("moment", ["add_frame", "_save_episode_video", "_save_episode_metadata", "finalize"])
def test_a_killed_recording_keeps_every_finished_episode(tmp_path, moment):
    root = tmp_path / "ds"
    args = ["record", "--env.task=PickPlaceFixedBin-v0", "--dataset.repo_id=local/kill", f"--dataset.root={root}",
            "--progress=false", "--env.observation_height=96", "--env.observation_width=128"]  # fmt: skip
    killed = subprocess.run(
        [str(BIN / "python"), "-c", KILL_AT, moment, *args, "--dataset.num_episodes=3"],
        env={**os.environ, "MUJOCO_GL": "egl"},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-3000:]
    if moment == "add_frame":
        # What a kill inside the image writer can leave: a truncated frame of the episode in flight.
        (root / "images" / "observation.images.top" / "episode-000001" / "frame-000999.png").write_bytes(
            b"\x89PNG\r\n"
        )
    # A rerun that records nothing more leaves exactly the saved episode, readable by stock LeRobot.
    out = run_cli("condground", *args, "--dataset.num_episodes=1")
    assert "already holds 1 episodes" in out.stdout
    kept = LeRobotDataset("local/kill", root=root)
    assert kept.meta.total_episodes == 1 and kept.meta.total_frames == len(kept)
    assert int(kept.meta.stats["action"]["count"][0]) == len(kept)  # nothing of the killed episode
    assert sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.suffix in (".parquet", ".mp4")) == [
        "data/chunk-000/file-000.parquet", "meta/episodes/chunk-000/file-000.parquet", "meta/tasks.parquet",
        "videos/observation.images.top/chunk-000/file-000.mp4",
    ]  # fmt: skip
    out = run_cli("condground", *args, "--dataset.num_episodes=2")
    assert "expert success: 1/1" in out.stdout
    resumed = LeRobotDataset("local/kill", root=root)
    assert resumed.meta.total_episodes == 2
    resumed[len(resumed) - 1]  # every file the dataset names opens; the last frame decodes
    last = resumed.meta.episodes[1]
    video = "videos/observation.images.top"
    # No frame of the killed episode in the resumed one's video.
    assert (
        round((last[f"{video}/to_timestamp"] - last[f"{video}/from_timestamp"]) * resumed.fps)
        == last["length"]
    )
    assert resumed.meta.total_frames == len(resumed) and int(resumed.meta.stats["action"]["count"][0]) == len(
        resumed
    )
    seeds = [e["seed"] for e in read_json(root / RECORD_FILE)["episodes"]]
    assert len(seeds) == 2 and len(set(seeds)) == 2


def test_a_drift_recording_says_how_it_was_made_and_is_resumed_only_with_the_same_drift(tmp_path):
    root = tmp_path / "dart"
    common = ["--env.task=PickPlaceFixedBin-v0", "--dataset.repo_id=local/dart", f"--dataset.root={root}",
              "--progress=false", "--env.observation_height=96", "--env.observation_width=128"]  # fmt: skip
    run_cli("condground", "record", *common, "--dataset.num_episodes=1", "--drift.std=0.05")
    provenance = read_json(root / RECORD_FILE)
    assert provenance["drift"] == {"std": 0.05, "time_constant": 0.5}
    assert 0.05 < provenance["episodes"][0]["drift_largest_rad"] < 0.3
    bad = run_cli("condground", "record", *common, "--dataset.num_episodes=2", check=False)
    assert bad.returncode != 0 and "drift {'std': 0.05" in bad.stderr, bad.stderr[-2000:]
    assert LeRobotDataset("local/dart", root=root).meta.total_episodes == 1


def test_a_takeover_recording_keeps_the_experts_frames_from_the_policys_states(tmp_path, tiny_checkpoints):
    """DAgger by takeover: a checkpoint drives each episode first, the expert finishes it from where the arm
    was left, and only the expert's frames are kept; provenance names the policy, a resume needs the same."""
    root = tmp_path / "takeover"
    common = ["--env.task=PickPlaceFixedBin-v0", "--dataset.repo_id=local/takeover", f"--dataset.root={root}",
              "--progress=false", "--env.observation_height=96", "--env.observation_width=128", "--seed=5",
              "--takeover.min_steps=20", "--takeover.max_steps=60"]  # fmt: skip
    policy = f"--takeover.policy_path={tiny_checkpoints[0]}"
    out = run_cli("condground", "record", *common, "--dataset.num_episodes=2", policy)
    assert "after the takeover" in out.stdout, out.stdout
    provenance = read_json(root / RECORD_FILE)
    takeover = provenance["takeover"]
    assert takeover["policy_path"] == str(tiny_checkpoints[0]) and len(takeover["policy_hash"]) == 16
    steps = [e["takeover_step"] for e in provenance["episodes"]]
    assert len(steps) == 2 and all(20 <= s <= 60 for s in steps)
    dataset = LeRobotDataset("local/takeover", root=root)
    home = np.array(HOME_QPOS)
    for episode, step in zip(range(2), steps, strict=True):
        start = dataset.meta.episodes["dataset_from_index"][episode]
        first = dataset.hf_dataset[int(start)]["observation.state"].numpy()
        # The policy moved the arm before the expert's first frame.
        assert np.max(np.abs(first[:6] - home)) > 0.02
        assert dataset.meta.episodes["length"][episode] < 300 - step + 1
    bad = run_cli(
        "condground", "record", *common, "--dataset.num_episodes=3",
        f"--takeover.policy_path={tiny_checkpoints[1]}", check=False,
    )  # fmt: skip
    assert bad.returncode != 0 and "takeover {" in bad.stderr, bad.stderr[-2000:]
    assert LeRobotDataset("local/takeover", root=root).meta.total_episodes == 2


def test_bad_record_flags_fail_before_any_work(tmp_path, capsys):
    """In this process (the command's own entry point): eight subprocesses cost two minutes of imports."""
    from lerobot_condground.cli import main

    root = tmp_path / "never"
    for flag, fragment in (
        ("--env.condition=object_color_9", "Unknown condition 'object_color_9'"),
        ("--env.observation_height=1000", "Image height 1000 cannot be rendered"),
        ("--env.task=PickPlace-v0", "Unknown task 'PickPlace-v0'"),
        ("--drift.std=-0.1", "--drift.std=-0.1 is not allowed; allowed: 0 (none) to 0.15 rad"),
        ("--drift.time_constant=0", "--drift.time_constant=0.0 is not allowed"),
        (
            "--drift.std=0.03 --env.task=InstrumentRouting-v0",
            "not allowed with --env.task=InstrumentRouting-v0",
        ),
        (
            "--takeover.policy_path=ckpt --takeover.max_steps=300",
            "--takeover.max_steps=300 are not allowed; allowed: 0 <= min_steps <= max_steps < --env.episode_length=300",
        ),
        ("--seed=1000000", "--seed=1000000 is not allowed: from seed 1000000 on `condground sweep` draws"),
        ("--seed=999999 --dataset.num_episodes=2", "allowed: at most 1 episodes from this seed"),
        (
            "--takeover.policy_path=ckpt --env.task=InstrumentRouting-v0",
            "--takeover.policy_path is not allowed with --env.task=InstrumentRouting-v0",
        ),
    ):
        assert main(["record", *flag.split(), f"--dataset.root={root}"]) == 2, flag
        err = capsys.readouterr().err
        assert fragment in err, err[-2000:]
        assert not root.exists()


def test_retries_never_reach_the_held_out_layouts(tmp_path, capsys):
    """A failed episode is retried with the next seed: from 999999 that would be the sweep's first held-out
    layout, so the recording stops there with one line instead of training on it."""
    from lerobot_condground.cli import main

    root = tmp_path / "ds"
    flags = ["--env.task=PickPlaceFixedBin-v0", "--dataset.repo_id=local/edge", f"--dataset.root={root}",
             "--progress=false", "--dataset.num_episodes=1", "--seed=999999", "--env.observation_height=64",
             "--env.observation_width=80", "--env.episode_length=3"]  # fmt: skip
    assert main(["record", *flags]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "seed 1000000 is a held-out layout" in err and "1 failed episodes" in err, err


def test_every_frame_reaches_the_video(recorded_dataset):
    import av
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset("local/test_full_mixed", root=recorded_dataset)
    for ep in range(ds.meta.total_episodes):
        path = recorded_dataset / ds.meta.get_video_file_path(ep, "observation.images.top")
        with av.open(str(path)) as container:
            decoded = sum(1 for _ in container.decode(video=0))
        episode = ds.meta.episodes[ep]
        assert decoded >= episode["dataset_to_index"] - episode["dataset_from_index"], ep


def test_training_frames_are_the_renders_evaluation_sees(recorded_dataset):
    """Training decodes the recording's video (AV1, 4:2:0 chroma); evaluation feeds the env's renders. Replaying
    each episode's actions in its layout reproduces the states exactly, and the decoded frames stay within
    the stated tolerance of the renders: PSNR >= 32 dB over an episode, >= 30 dB on every frame (measured
    2026-12-01: 34.8-34.9 dB and >= 33.2 dB per frame at 96x128 on Task 1). The prompt crops are equal."""
    from lerobot_condground.envs.configs import CondGroundEnvConfig

    ds = LeRobotDataset("local/test_full_mixed", root=recorded_dataset)
    provenance = read_json(recorded_dataset / RECORD_FILE)
    env = CondGroundEnvConfig(**provenance["env"]).make_env()
    for ep, episode in enumerate(provenance["episodes"]):
        obs, _ = env.reset(seed=episode["seed"])
        errors = []
        for i in range(ds.meta.episodes["dataset_from_index"][ep], ds.meta.episodes["dataset_to_index"][ep]):
            item = decode_labels(ds[i])
            np.testing.assert_allclose(obs["agent_pos"], item["observation.state"].numpy(), atol=1e-5)
            decoded = item["observation.images.top"].permute(1, 2, 0).numpy() * 255
            errors.append(((decoded - obs["pixels"]["top"].astype(float)) ** 2).mean())
            # The prompt crops are stored losslessly: `full` conditions on the very crops in both.
            for key, name in (
                (OBS_PROMPT_OBJECT, "prompt_object"),
                (OBS_PROMPT_RECEPTACLE, "prompt_receptacle"),
            ):
                np.testing.assert_array_equal(item[key].numpy(), obs[name], err_msg=f"{key}, frame {i}")
            obs, *_ = env.step(item["action"].numpy())
        psnr = 10 * np.log10(255**2 / np.array(errors))
        assert 10 * np.log10(255**2 / np.mean(errors)) >= 32 and psnr.min() >= 30, (ep, psnr.min())


def test_a_takeover_checkpoint_is_untrusted_input(tmp_path, tiny_checkpoints, capsys):
    """--takeover.policy_path loads a checkpoint: one naming arbitrary code is refused before anything runs,
    with this command's own opt-in named; a missing one is named; nothing is written either way."""
    from lerobot_condground.cli import main

    evil = tmp_path / "evil"
    shutil.copytree(tiny_checkpoints[0], evil)
    pipeline = json.loads((evil / "policy_preprocessor.json").read_text())
    marker = tmp_path / "pwned"
    pipeline["steps"].insert(0, {"class": "subprocess.Popen", "config": {"args": ["touch", str(marker)]}})
    (evil / "policy_preprocessor.json").write_text(json.dumps(pipeline))
    root = tmp_path / "ds"
    flags = ["--env.task=PickPlaceFixedBin-v0", "--dataset.repo_id=local/t", f"--dataset.root={root}",
             "--env.observation_height=96", "--env.observation_width=128", "--progress=false"]  # fmt: skip
    for path, fragment in (
        (evil, "names class 'subprocess.Popen'"),
        (evil, "pass --takeover.trust_remote_code=true if you trust"),
        (tmp_path / "absent", f"Policy path '{tmp_path / 'absent'}' is not a checkpoint directory"),
    ):
        assert main(["record", *flags, f"--takeover.policy_path={path}"]) == 2
        err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("condground record:")]
        assert len(err) == 1 and fragment in err[0], err
    assert not marker.exists() and not root.exists()
