"""Hardware visual prompts: segmenters, the prompt tracker, `condground prompts` and its phase labels."""

import json
import re
import shutil

import numpy as np
import pytest

from helpers import read_json, run_cli
from lerobot_condground import cli
from lerobot_condground.core.labels import (
    OBS_PHASE,
    OBS_PROMPT_OBJECT,
    OBS_PROMPT_RECEPTACLE,
    OBS_SEGMENTATION,
    PNG_FEATURE,
    decode_png,
)
from lerobot_condground.core.provenance import PROMPTS_FILE
from lerobot_condground.envs.expert import ScriptedExpert
from lerobot_condground.envs.pickplace_env import PickPlaceEnv
from lerobot_condground.labelling.prompt_tracker import PromptTracker, labels_from_masks
from lerobot_condground.labelling.prompts import click_on, phase_from_gripper
from lerobot_condground.labelling.segmenters import (
    ColorSegmenter,
    Prompt,
    Sam2Segmenter,
    make_segmenter,
    parse_prompt,
    save_random_sam2,
)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


# ------------------------------------------------------------------------------------------- prompts
def test_prompt_parsing_and_bounds():
    assert Prompt.parse("120,80").center == (120, 80) and not Prompt.parse("120,80").is_box
    box = Prompt.parse(" 10, 20,60,90 ")
    assert box.is_box and box.center == (35, 55) and str(box) == "10,20,60,90"
    assert Prompt.parse((3, 4)) == Prompt.parse("3,4")
    for bad in ("12", "a,b", "1,2,3", "60,20,10,90"):
        with pytest.raises(ValueError):
            Prompt.parse(bad)
    Prompt.parse("159,119").check_inside(120, 160)
    with pytest.raises(ValueError, match=r"click 160,10 is outside the 160x120 image"):
        Prompt.parse("160,10").check_inside(120, 160)
    with pytest.raises(ValueError, match=r"box 0,0,161,50 is outside the 160x120 image"):
        Prompt.parse("0,0,161,50").check_inside(120, 160)
    assert parse_prompt("0,0,160,120", (120, 160)).is_box
    with pytest.raises(ValueError, match="outside the 160x120 image"):
        parse_prompt("10,120", (120, 160))
    with pytest.raises(ValueError, match="Unknown segmenter 'sam3'; allowed: sam2, color"):
        make_segmenter("sam3")


def test_a_click_outside_the_image_fails_before_segmenting():
    frame = np.zeros((96, 128, 3), np.uint8)
    tracker = PromptTracker(ColorSegmenter())
    with pytest.raises(ValueError, match=r"-1,5 is outside the 128x96 image"):
        tracker.start(frame, "-1,5", "10,10")
    assert not tracker.started and not tracker.segmenter.started
    with pytest.raises(RuntimeError, match="before start"):
        tracker.track(frame)


def test_label_map_paints_the_object_over_the_receptacle():
    masks = {k: np.zeros((4, 4), bool) for k in (1, 2, 3)}
    masks[2][:3, :3] = True
    masks[1][1, 1] = True
    masks[3][2:, 2:] = True
    labels = labels_from_masks(masks, (4, 4))
    assert labels[1, 1] == 1 and labels[0, 0] == 2 and labels[2, 2] == 2 and labels[3, 3] == 3


# ----------------------------------------------------------------------------- color tracking in sim
def test_color_tracker_matches_the_privileged_labels_and_crops():
    """Clicks on the targets of the first frame of an expert episode (clean scene): the tracked masks
    match MuJoCo's segmentation, and the crops cut from that frame are the env's own prompt crops
    (seed 5: the gripper starts away from both targets, so the first frame shows them unoccluded)."""
    env = PickPlaceEnv(
        task="PickPlaceRandomBin-v0",
        condition="clean",
        observation_height=240,
        observation_width=320,
        segmentation=True,
        prompts=True,
    )
    obs, _ = env.reset(seed=5)
    expert = ScriptedExpert()
    expert.reset(env)
    tracker = PromptTracker(ColorSegmenter())
    first_area = {label: int((obs["segmentation"] == label).sum()) for label in (1, 2)}
    scores = {1: [], 2: []}
    for step in range(200):
        frame, seg = obs["pixels"]["top"], obs["segmentation"]
        if step == 0:
            result = tracker.start(frame, click_on(seg, 1), click_on(seg, 2))
            assert result.object_crop.shape == result.receptacle_crop.shape == (64, 64, 3)
            np.testing.assert_allclose(result.object_crop, obs["prompt_object"], atol=2)
            np.testing.assert_allclose(result.receptacle_crop, obs["prompt_receptacle"], atol=2)
            crops = result.object_crop.copy(), result.receptacle_crop.copy()
        else:
            result = tracker.track(frame)
            # Positionless prompts: the crops stay those of the annotated frame.
            assert np.array_equal(result.object_crop, crops[0]) and np.array_equal(
                result.receptacle_crop, crops[1]
            )
        assert result.labels.shape == seg.shape and result.labels.dtype == np.uint8
        for label in (1, 2):
            if (seg == label).sum() >= 0.3 * first_area[label]:  # frames where the entity is mostly visible
                scores[label].append(iou(result.labels == label, seg == label))
        obs, _, terminated, truncated, info = env.step(expert.act(obs))
        if terminated or truncated:
            break
    env.close()
    assert info["is_success"] and step > 50
    for label, values in scores.items():
        values = np.array(values)
        assert len(values) > 30
        assert values.mean() > 0.85, (label, values.mean())
        assert np.mean(values > 0.7) > 0.9, (label, np.sort(values)[:10])


def test_phase_from_gripper_reproduces_the_experts_phase_labels():
    assert phase_from_gripper([0, 0, 0.9, 0.1, 0.9, 0.9, 0.9, 0, 0], fps=20, hold_s=0.1).tolist() == [
        0,
        0,
        0,
        0,
        0,
        0,
        1,
        1,
        1,
    ]  # a one-frame twitch does not count; a release does not go back
    assert not phase_from_gripper(np.zeros(10), fps=20).any()
    env = PickPlaceEnv(task="PickPlaceRandomBin-v0", obs_type="agent_pos")
    expert = ScriptedExpert()
    for seed in range(3):
        obs, _ = env.reset(seed=seed)
        expert.reset(env)
        actions, labels = [], []
        for _ in range(300):
            action = expert.act(obs)
            actions.append(action)
            labels.append(expert.phase_label)
            obs, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                break
        derived = phase_from_gripper(np.array(actions)[:, 6], fps=env.fps)
        assert np.mean(derived == np.array(labels)) > 0.97


# ------------------------------------------------------------------------------------- SAM 2 plumbing
@pytest.fixture(scope="module")
def random_sam2(tmp_path_factory):
    return save_random_sam2(tmp_path_factory.mktemp("sam2") / "random-sam2", size="small")


def test_sam2_streams_masks_and_crops_from_a_saved_checkpoint(random_sam2):
    """Random weights, so only the plumbing is checked: loading through from_pretrained, points and a
    box on the first frame, masks at the frame's size for every id on each streamed frame."""
    env = PickPlaceEnv(
        task="PickPlaceRandomBin-v0",
        condition="clean",
        observation_height=96,
        observation_width=128,
        segmentation=True,
    )
    obs, _ = env.reset(seed=5)
    expert = ScriptedExpert()
    expert.reset(env)
    tracker = PromptTracker(Sam2Segmenter(model_id=str(random_sam2)))
    seg = obs["segmentation"]
    for step in range(4):
        frame = obs["pixels"]["top"]
        if step == 0:
            result = tracker.start(frame, click_on(seg, 1), "5,5,60,60", competitor_prompts=["100,80"])
        else:
            result = tracker.track(frame)
        assert sorted(result.masks) == [1, 2, 3]
        assert all(m.shape == (96, 128) and m.dtype == bool for m in result.masks.values())
        assert result.object_crop.shape == result.receptacle_crop.shape == (64, 64, 3)
        assert result.labels.shape == (96, 128) and set(np.unique(result.labels)) <= {0, 1, 2, 3}
        obs, *_ = env.step(expert.act(obs))
    env.close()
    with pytest.raises(ValueError, match="differs from the annotated frame"):
        tracker.track(np.zeros((48, 64, 3), np.uint8))


def test_sam2_weights_missing_offline_is_one_clear_error(tmp_path):
    import huggingface_hub.constants

    with pytest.raises(FileNotFoundError, match="are not available locally") as err:
        Sam2Segmenter(model_id="condground-tests/sam2-never-cached")
    assert "--sam2.model_id=" in str(err.value)
    if huggingface_hub.constants.HF_HUB_OFFLINE:
        assert "HF_HUB_OFFLINE=1" in str(err.value)
    with pytest.raises(FileNotFoundError, match="no such directory"):
        Sam2Segmenter(model_id=str(tmp_path / "missing"))


# ----------------------------------------------------------------------------- condground prompts
@pytest.fixture(scope="module")
def hardware_like_dataset(tmp_path_factory):
    """Two expert episodes of a clean scene without labels (what lerobot-record writes on hardware),
    and the clicks a user would give on their first frames (from the env's privileged labels)."""
    root = tmp_path_factory.mktemp("hw") / "plain"
    run_cli(
        "condground",
        "record",
        "--env.task=PickPlaceRandomBin-v0",
        "--env.condition=clean",
        "--env.observation_height=120",
        "--env.observation_width=160",
        "--dataset.repo_id=local/test_hw",
        f"--dataset.root={root}",
        "--dataset.num_episodes=2",
        "--dataset.labels=false",
        "--progress=false",
        "--seed=5",
    )
    seeds = [e["seed"] for e in read_json(root / "meta" / "condground_record.json")["episodes"]]
    env = PickPlaceEnv(
        task="PickPlaceRandomBin-v0",
        condition="clean",
        observation_height=120,
        observation_width=160,
        segmentation=True,
    )
    clicks = {}
    for episode, seed in enumerate(seeds):
        obs, _ = env.reset(seed=seed)
        clicks[episode] = {
            "object": click_on(obs["segmentation"], 1),
            "receptacle": click_on(obs["segmentation"], 2),
        }
    env.close()
    return root, seeds, clicks


def _tree(root):
    return {p.relative_to(root): p.stat().st_mtime_ns for p in sorted(root.rglob("*"))}


def test_condground_prompts_writes_a_labelled_copy(hardware_like_dataset, tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root, seeds, clicks = hardware_like_dataset
    before = _tree(root)
    annotations = tmp_path / "annotations.json"
    annotations.write_text(json.dumps({str(k): v for k, v in clicks.items()}))
    out = tmp_path / "labelled"
    proc = run_cli(
        "condground",
        "prompts",
        "--dataset.repo_id=local/test_hw",
        f"--dataset.root={root}",
        "--segmenter=color",
        "--camera=observation.images.top",
        f"--annotations={annotations}",
        f"--output.root={out}",
        "--output.repo_id=local/test_hw_prompts",
        "--progress=false",
    )
    assert "labelled 2 episodes" in proc.stdout
    assert _tree(root) == before  # the input is untouched

    source = LeRobotDataset("local/test_hw", root=root)
    labelled = LeRobotDataset("local/test_hw_prompts", root=out)
    assert labelled.meta.total_frames == source.meta.total_frames
    assert labelled.meta.total_episodes == 2
    for key in (
        OBS_SEGMENTATION,
        OBS_PROMPT_OBJECT,
        OBS_PROMPT_RECEPTACLE,
    ):  # as `condground record` writes them
        assert labelled.meta.features[key]["dtype"] == PNG_FEATURE["dtype"]
        assert tuple(labelled.meta.features[key]["shape"]) == PNG_FEATURE["shape"]
    assert labelled.meta.features[OBS_PHASE]["dtype"] == "int64"
    assert tuple(labelled.meta.features[OBS_PHASE]["shape"]) == (1,)
    item = labelled[0]
    assert decode_png(item[OBS_SEGMENTATION]).shape == (120, 160)
    assert decode_png(item[OBS_PROMPT_OBJECT]).shape == (64, 64, 3)
    first_labels = decode_png(item[OBS_SEGMENTATION])
    assert (first_labels == 1).any() and (first_labels == 2).any()
    # Phase from the gripper command agrees with the expert's own labels of the same episodes.
    raw = labelled.hf_dataset.with_format(None)
    phases = np.array([row[OBS_PHASE] for row in raw]).reshape(-1)
    env = PickPlaceEnv(task="PickPlaceRandomBin-v0", condition="clean", obs_type="agent_pos")
    expert, expected = ScriptedExpert(), []
    for episode, seed in enumerate(seeds):
        obs, _ = env.reset(seed=seed)
        expert.reset(env)
        for _ in range(int(labelled.meta.episodes[episode]["length"])):
            action = expert.act(obs)
            expected.append(expert.phase_label)
            obs, *_ = env.step(action)
    assert np.mean(phases == np.array(expected)) > 0.97
    provenance = read_json(out / PROMPTS_FILE)
    assert provenance["segmenter"] == "color" and provenance["prompts"]["0"]["object"] == clicks[0]["object"]


def test_condground_prompts_one_episode_and_one_set_of_prompts(hardware_like_dataset, tmp_path, capsys):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root, _, clicks = hardware_like_dataset
    out = tmp_path / "one"
    args = [
        "prompts",
        "--dataset.repo_id=local/test_hw",
        f"--dataset.root={root}",
        "--segmenter=color",
        f"--object={clicks[1]['object']}",
        f"--receptacle={clicks[1]['receptacle']}",
        "--competitors=5,5;0,0,10,10",
        "--episodes=1",
        f"--output.root={out}",
        "--progress=false",
    ]
    # The copy is written beside the output and renamed when whole: a killed run's leftover is cleared.
    leftover = tmp_path / ".one.partial"
    (leftover / "meta").mkdir(parents=True)
    assert cli.main(args) == 0
    assert not leftover.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["one"]
    one = LeRobotDataset("local/test_hw_prompts", root=out)
    assert one.meta.total_episodes == 1
    assert one.meta.total_frames == int(LeRobotDataset("local/test_hw", root=root).meta.episodes[1]["length"])
    assert read_json(out / PROMPTS_FILE)["prompts"]["1"]["competitors"] == ["5,5", "0,0,10,10"]


@pytest.mark.parametrize(
    "flags, message",
    [
        (
            ["--object=160,10", "--receptacle=5,5"],
            "object prompt: The click 160,10 is outside the 160x120 image",
        ),
        (
            ["--object=5,5", "--receptacle=5,5", "--camera=observation.images.wrist"],
            "--camera='observation.images.wrist' is not a camera of .*; allowed: observation.images.top",
        ),
        (
            ["--object=5,5", "--receptacle=5,5", "--episodes=0,7"],
            r"episodes \[7\] are not in the dataset; allowed: 0..1",
        ),
        (
            ["--object=5,5", "--receptacle=5,5", "--segmenter=sam3"],
            "Unknown --segmenter='sam3'; allowed: sam2, color",
        ),
        ([], "No prompts"),
    ],
)
def test_condground_prompts_bad_input_is_one_line(hardware_like_dataset, tmp_path, capsys, flags, message):
    root, _, _ = hardware_like_dataset
    code = cli.main(
        [
            "prompts",
            "--dataset.repo_id=local/test_hw",
            f"--dataset.root={root}",
            "--segmenter=color",
            f"--output.root={tmp_path / 'out'}",
            *flags,
        ]
    )
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    assert err.startswith("condground prompts: ")
    assert re.search(message, err), err
    assert not (tmp_path / "out").exists()


def test_condground_prompts_needs_a_gripper_in_action(hardware_like_dataset, tmp_path, capsys):
    """A dataset whose action has no gripper.pos (a copy of the test dataset with renamed motors)."""
    root, _, _ = hardware_like_dataset
    copy = tmp_path / "no_gripper"
    shutil.copytree(root, copy)
    info = read_json(copy / "meta" / "info.json")
    info["features"]["action"]["names"] = [f"joint_{i}" for i in range(7)]
    (copy / "meta" / "info.json").write_text(json.dumps(info))
    code = cli.main(
        [
            "prompts",
            "--dataset.repo_id=local/test_hw",
            f"--dataset.root={copy}",
            "--segmenter=color",
            "--object=5,5",
            "--receptacle=9,9",
            f"--output.root={tmp_path / 'out'}",
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and "has no 'gripper.pos' entry" in err and "joint_0" in err


@pytest.mark.slow
def test_labelled_hardware_dataset_trains_act_modified(hardware_like_dataset, tmp_path):
    """lerobot-train runs the full act_modified variant on the labelled copy, as on simulated data."""
    root, _, clicks = hardware_like_dataset
    out = tmp_path / "labelled"
    run_cli(
        "condground",
        "prompts",
        "--dataset.repo_id=local/test_hw",
        f"--dataset.root={root}",
        "--segmenter=color",
        f"--object={clicks[0]['object']}",
        f"--receptacle={clicks[0]['receptacle']}",
        f"--output.root={out}",
        "--progress=false",
    )
    run_cli(
        "lerobot-train",
        "--policy.type=act_modified",
        "--policy.variant=full",
        "--policy.device=cpu",
        "--policy.push_to_hub=false",
        "--policy.pretrained_backbone_weights=null",
        "--policy.dim_model=64",
        "--policy.n_heads=2",
        "--policy.dim_feedforward=128",
        "--policy.n_encoder_layers=1",
        "--policy.n_decoder_layers=1",
        "--policy.n_vae_encoder_layers=1",
        "--policy.chunk_size=10",
        "--policy.n_action_steps=10",
        "--dataset.repo_id=local/test_hw_prompts",
        f"--dataset.root={out}",
        "--batch_size=2",
        "--steps=2",
        "--save_freq=2",
        "--log_freq=1",
        "--num_workers=0",
        f"--output_dir={tmp_path / 'train'}",
        "--wandb.enable=false",
    )
    assert (tmp_path / "train" / "checkpoints" / "last" / "pretrained_model" / "model.safetensors").exists()
