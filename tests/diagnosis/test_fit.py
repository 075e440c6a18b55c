"""`condground fit`: teacher-forced errors in physical units, checked against answers computed here."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from helpers import garbage_checkpoints, make_checkpoint, read_json, run_cli
from lerobot_condground.core.ur3e import HOME_QPOS, forward_kinematics
from lerobot_condground.diagnosis.fit import frame_errors, parse_episodes, segments

# make_checkpoint's action normalization: a policy whose normalized output is zero commands this mean.
ACTION_MEAN = np.array([0.0, -1.2, 1.3, -1.6, -1.57, 0.0, 0.3])


def test_a_base_rotation_moves_the_tool_along_its_chord():
    demonstrated = np.tile(np.append(HOME_QPOS, 0.0), (1, 3, 1))
    predicted = demonstrated.copy()
    predicted[..., 0] += 0.1
    predicted[0, 2, :] += 5.0  # a padded step: must not count
    valid = np.array([[True, True, False]])
    errors = frame_errors(predicted, demonstrated, valid)
    radius = np.hypot(*forward_kinematics(HOME_QPOS)[0][:2])
    assert errors["joint0_rad"][0] == pytest.approx(0.1)
    assert errors["tcp_cm"][0] == pytest.approx(2 * radius * np.sin(0.05) * 100)
    assert errors["gripper"][0] == 0 and all(errors[f"joint{j}_rad"][0] == 0 for j in range(1, 6))


def test_segments_follow_the_phase_and_the_demonstrated_gripper():
    # gripper commands over 3 compared steps, and the phase of each frame
    gripper = np.array([[0, 0, 0], [0, 0, 1], [1, 1, 1], [1, 1, 1], [1, 0, 0], [0, 0, 0]], dtype=float)
    phase = np.array([0, 0, 0, 1, 1, 1])
    actions = np.zeros((6, 3, 7))
    actions[..., 6] = gripper
    assert list(segments(phase, actions)) == ["reach", "grasp", "lift", "carry", "release", "retreat"]


@pytest.mark.parametrize("text", ["0:9", "-1", "a", "", "1,1", "3:3"])
def test_bad_episode_lists_are_refused(text):
    with pytest.raises(ValueError, match="--fit.episodes="):
        parse_episodes(text, total=2)


def _constant_policy(path: Path, height: int, width: int) -> Path:
    """A standard act_modified checkpoint whose action head outputs zero: it commands the action mean."""
    from safetensors.torch import load_file, save_file

    make_checkpoint(path, variant="standard", height=height, width=width)
    weights = load_file(path / "model.safetensors")
    for key in ("model.action_head.weight", "model.action_head.bias"):
        weights[key].zero_()
    save_file(weights, path / "model.safetensors", metadata={"format": "pt"})
    return path


def test_fit_of_a_constant_policy_matches_the_recording(recorded_dataset, tmp_path):
    info = read_json(recorded_dataset / "meta" / "info.json")
    height, width, _ = info["features"]["observation.images.top"]["shape"]
    checkpoint = _constant_policy(tmp_path / "constant", height, width)
    out = tmp_path / "fit"
    run_cli(
        "condground", "fit", f"--policy.path={checkpoint}", f"--dataset.root={recorded_dataset}",
        "--fit.steps=5", "--fit.batch_size=16", f"--output_dir={out}", "--progress=false",
    )  # fmt: skip
    frames = pd.read_parquet(out / "frames.parquet").sort_values(["episode", "frame_index"])
    data = pd.concat(pd.read_parquet(f) for f in sorted((recorded_dataset / "data").rglob("*.parquet")))
    assert len(frames) == len(data) == info["total_frames"]
    # The expected errors from the recording's own rows: the next 5 actions of each frame, within its episode.
    expected_base, expected_tcp = [], []
    for _, episode in data.groupby("episode_index"):
        actions = np.stack(episode.sort_values("frame_index")["action"].to_numpy())
        for t in range(len(actions)):
            chunk = actions[t : t + 5]
            expected_base.append(np.abs(ACTION_MEAN[0] - chunk[:, 0]).mean())
            tool = forward_kinematics(chunk[:, :6])[0] - forward_kinematics(ACTION_MEAN[:6])[0]
            expected_tcp.append(np.linalg.norm(tool, axis=-1).mean() * 100)
    np.testing.assert_allclose(frames["joint0_rad"], expected_base, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(frames["tcp_cm"], expected_tcp, rtol=1e-4, atol=1e-3)
    result = read_json(out / "fit.json")
    assert result["segments"]["all"]["frames"] == len(frames)
    assert sum(v["frames"] for k, v in result["segments"].items() if k != "all") == len(frames)
    assert {"reach", "grasp", "carry", "release"} <= set(result["segments"])
    assert result["steps"] == 5 and result["episodes"] == [0, 1]


def test_bad_input_is_one_line(recorded_dataset, tmp_path, capsys):
    from lerobot_condground.cli import main

    checkpoint = _constant_policy(tmp_path / "constant", 96, 128)
    for flag, message in (
        ("--fit.episodes=0:9", "--fit.episodes='0:9'"),
        ("--fit.steps=50", "--fit.steps=50"),
    ):
        code = main(
            ["fit", f"--policy.path={checkpoint}", f"--dataset.root={recorded_dataset}", flag,
             f"--output_dir={tmp_path / 'out'}"]
        )  # fmt: skip
        err = capsys.readouterr().err
        assert code == 2 and message in err.strip().splitlines()[-1], err
        assert not (tmp_path / "out").exists()
    for garbage, message in garbage_checkpoints(checkpoint, tmp_path).items():
        code = main(
            ["fit", f"--policy.path={garbage}", f"--dataset.root={recorded_dataset}", f"--output_dir={tmp_path / 'out'}"]
        )  # fmt: skip
        err = capsys.readouterr().err
        assert code == 2 and message in err.strip().splitlines()[-1], err
        assert not (tmp_path / "out").exists()


def test_fit_reports_the_supervised_heads_camera_share_and_the_predicted_phase(recorded_dataset, tmp_path):
    """The share recomputed here from PyTorch's own per-head attention weights (need_weights), and the phase
    from the phase head's logits, frame by frame against what `condground fit` wrote."""
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.policies.factory import make_pre_post_processors

    from lerobot_condground.policies.act_modified.modeling_act_modified import ACTModifiedPolicy

    checkpoint = make_checkpoint(tmp_path / "full", variant="full", seed=3, phase_predictor=True)
    out = tmp_path / "fit"
    run_cli(
        "condground", "fit", f"--policy.path={checkpoint}", f"--dataset.root={recorded_dataset}",
        "--fit.episodes=0", "--fit.frame_stride=10", f"--output_dir={out}", "--progress=false",
    )  # fmt: skip
    frames = pd.read_parquet(out / "frames.parquet").sort_values("frame_index")
    policy = ACTModifiedPolicy.from_pretrained(checkpoint).eval()
    preprocessor, _ = make_pre_post_processors(policy.config, pretrained_path=checkpoint)
    dataset = LeRobotDataset("local/test_full_mixed", root=recorded_dataset, episodes=[0])
    index = [i for i in range(len(dataset)) if int(dataset.hf_dataset[i]["frame_index"]) % 10 == 0]
    batch = preprocessor(torch.utils.data.default_collate([dataset[i] for i in index]))
    mha = policy.model.decoder.layers[-1].multihead_attn
    captured = {}

    def weights(module, args, kwargs, output):
        names = ("query", "key", "value")
        inputs = {**dict(zip(names, args, strict=False)), **{n: kwargs[n] for n in names if n in kwargs}}
        handle.remove()  # the call below must not come back here
        captured["w"] = module(**inputs, need_weights=True, average_attn_weights=False)[1]

    handle = mha.register_forward_hook(weights, with_kwargs=True)
    with torch.inference_mode():
        image = batch["observation.images.top"]
        grid = policy.model.backbone(image)["feature_map"].shape[-2:]
        logits = policy.model({**batch, "observation.images": [image]})[2]["phase_logits"]
    n_1d = 2  # the latent and the robot state come first, the camera's tokens next
    share = captured["w"][:, policy.config.attention_head, :, n_1d : n_1d + grid.numel()].sum(-1).mean(-1)
    np.testing.assert_allclose(frames["head_camera_share"], share.numpy(), rtol=1e-4, atol=1e-6)
    np.testing.assert_array_equal(frames["phase_predicted"], logits.argmax(-1).numpy())
    segments_ = read_json(out / "fit.json")["segments"]
    assert segments_["all"]["phase_accuracy"] == pytest.approx(
        (frames["phase_predicted"] == frames["phase"]).mean()
    )
    assert 0 < segments_["all"]["head_camera_share_median"] < 1
