"""`condground attention`: the per-step attention video of act_modified and stock ACT checkpoints, the
attention recomputed at every step while ACT executes a chunk, agreement with act_modified's own
supervised attention, bad input."""

import json
import math
from pathlib import Path

import av
import numpy as np
import pytest
import torch

from lerobot_condground.core.configs import EvalEnvConfig, PolicyRefConfig
from lerobot_condground.core.provenance import command_line
from lerobot_condground.diagnosis.attention import (
    AttentionConfig,
    AttentionOptions,
    attention_masses,
    json_safe,
    run_attention,
)
from lerobot_condground.diagnosis.hooks import (
    ACTProbe,
    camera_attention,
    load_act_family,
    model_inputs,
    resolve_target,
)
from lerobot_condground.evaluation.rollout import policy_batch, run_episodes

STEPS = 23  # chunks of 10 actions: 3 chunk predictions


def _run(checkpoint, out, **options) -> tuple[Path, dict]:
    cfg = AttentionConfig(
        policy=PolicyRefConfig(path=str(checkpoint)),
        env=EvalEnvConfig(condition="full_mixed", episode_length=STEPS),
        attention=AttentionOptions(seed=2, **options),
        output_dir=str(out),
        progress=False,
    )
    path = run_attention(cfg)
    return path, json.loads((path / "attention.json").read_text())


def _check_outputs(path: Path, result: dict, chunk: int = 10) -> np.ndarray:
    for key in (
        "kind",
        "policy_label",
        "checkpoint",
        "task",
        "condition",
        "seed",
        "head",
        "frames",
        "video",
        "stills",
        "phase_predicted",
        "command",
        "versions",
    ):
        assert key in result, key
    assert result["kind"] == "attention" and result["frames"] == STEPS and result["condition"] == "full_mixed"
    with av.open(str(path / result["video"])) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(frames) == STEPS
    assert all(f.shape == (96, 128, 3) for f in frames)
    maps = np.load(path / result["maps"])
    assert maps.shape == (STEPS, *result["grid"]) == (STEPS, 3, 4)  # ResNet stride 32 on 96x128
    np.testing.assert_allclose(maps.sum(axis=(1, 2)), 1.0, atol=1e-5)
    # One extra forward per step, while the policy itself predicted one chunk per `chunk` steps.
    assert result["forward_passes"] == STEPS
    assert result["chunk_forward_passes"] == math.ceil(STEPS / chunk)
    # Recomputed every step: maps change inside a chunk (steps 1..9 reuse chunk 0's actions).
    assert all(not np.allclose(maps[t], maps[t + 1], atol=1e-7) for t in range(1, 5))
    assert len(result["phase_predicted"]) == len(result["stage"]) == STEPS
    masses = result["attention_mass"]
    total = np.sum([masses[k] for k in ("target_object", "target_receptacle", "competitors")], axis=0)
    assert np.all(total >= 0) and np.all(total <= 1 + 1e-6) and np.all(np.asarray(masses["competitors"]) > 0)
    assert (
        result["stills"][0] == "stills/step_0000.png"
        and result["stills"][-1] == f"stills/step_{STEPS - 1:04d}.png"
    )
    assert all((path / s).is_file() for s in result["stills"])
    return maps


def test_act_modified_attention_video(tiny_checkpoints, tmp_path):
    path, result = _run(tiny_checkpoints[0], tmp_path / "mod")
    _check_outputs(path, result)
    assert result["policy_label"] == "act_modified/full" and result["head"] == 0 and result["camera"] == "top"
    assert all(p in (0, 1) for p in result["phase_predicted"])
    assert all(0 <= p <= 1 for p in result["phase_probability_place"])
    # The extra forward passes leave the executed episode exactly as a plain rollout runs it.
    loaded, spec = load_act_family(
        PolicyRefConfig(path=str(tiny_checkpoints[0])),
        EvalEnvConfig(condition="full_mixed", episode_length=STEPS),
    )
    env = spec.make()
    assert json_safe(run_episodes(loaded, [env], [2], max_steps=STEPS)[0]) == result["outcome"]
    env.close()


def test_flags_parse_and_command_round_trips():
    import draccus

    cfg = draccus.parse(
        AttentionConfig,
        args=[
            "--policy.path=some/ckpt",
            "--env.task=PickPlaceFixedBin-v0",
            "--env.condition=object_color_2",
            "--attention.head=2",
            "--attention.seed=7",
            "--attention.layer=-1",
            "--attention.camera=top",
            "--output_dir=d",
        ],
    )
    assert (cfg.policy.path, cfg.env.task, cfg.env.condition, cfg.attention.head, cfg.attention.seed) == (
        "some/ckpt",
        "PickPlaceFixedBin-v0",
        "object_color_2",
        2,
        7,
    )
    assert cfg.env.observation_height is None  # the checkpoint's camera size
    line = command_line("attention", cfg)
    assert line[:2] == ["condground", "attention"] and draccus.parse(AttentionConfig, args=line[2:]) == cfg


def test_stock_act_attention_video(act_checkpoint, tmp_path):
    path, result = _run(act_checkpoint, tmp_path / "act", head=3)
    _check_outputs(path, result)
    assert result["policy_label"] == "act" and result["head"] == 3
    assert result["phase_predicted"] == [None] * STEPS  # stock ACT has no phase head


def test_matches_act_modified_supervised_attention(tiny_checkpoints):
    """The hook-based read-out equals what act_modified's attention loss supervises."""
    loaded, spec = load_act_family(
        PolicyRefConfig(path=str(tiny_checkpoints[0])), EvalEnvConfig(condition="full_mixed")
    )
    env = spec.make()
    obs, _ = env.reset(seed=4)
    policy = loaded.policy
    target = resolve_target(policy.config)
    with torch.inference_mode():
        batch = policy_batch(loaded, [obs], [env])
        with ACTProbe(policy.model, attention_layer=target.layer) as probe:
            probe.forward(policy, batch)
            ours, share = camera_attention(probe, target)
        supervised = policy.model(model_inputs(policy, batch), with_attention=True)[2]["attention"]
    np.testing.assert_allclose(ours, supervised.numpy(), atol=1e-6)
    assert 0 < share[0] <= 1
    # Attention mass: uniform attention puts on each entity its share of the frame's pixels.
    seg = env.render_segmentation()
    masses = attention_masses(np.full((3, 4), 1 / 12), seg)
    assert masses["target_object"] == pytest.approx((seg == 1).mean(), rel=1e-4)
    assert masses["competitors"] == pytest.approx((seg >= 3).mean(), rel=1e-4)
    env.close()


def test_the_probe_reads_the_camera_features_of_a_policy_trained_channels_last(tiny_checkpoints):
    """`--policy.channels_last` swaps each frame for a channels-last copy before the backbone; the probe still
    tells the camera's pass from the prompt crops' and reads the same features."""
    from lerobot_condground.policies.act_modified.modeling_act_modified import _channels_last_input

    loaded, spec = load_act_family(
        PolicyRefConfig(path=str(tiny_checkpoints[0])), EvalEnvConfig(condition="full_mixed")
    )
    env = spec.make()
    obs, _ = env.reset(seed=4)
    policy = loaded.policy
    read = []
    with torch.inference_mode():
        batch = policy_batch(loaded, [obs], [env])
        for channels_last in (False, True):
            handle = (
                policy.model.backbone.register_forward_pre_hook(_channels_last_input)
                if channels_last
                else None
            )
            with ACTProbe(policy.model) as probe:
                probe.forward(policy, batch)
                assert len(probe.feature_maps) == 1  # the camera's pass, not the two prompt crops'
                read.append(probe.activations()["vision_encoder"])
            if handle:
                handle.remove()
    np.testing.assert_allclose(read[1], read[0], atol=1e-4)
    env.close()


def test_bad_input(tiny_checkpoints, act_checkpoint, tmp_path):
    with pytest.raises(ValueError, match=r"--attention.head=4 is out of range; allowed: 0..3"):
        _run(act_checkpoint, tmp_path / "x", head=4)
    with pytest.raises(ValueError, match=r"--attention.head=-1 is out of range"):
        _run(tiny_checkpoints[0], tmp_path / "x", head=-1)
    with pytest.raises(ValueError, match=r"--attention.layer=1 is out of range; allowed: -1..0"):
        _run(tiny_checkpoints[0], tmp_path / "x", layer=1)
    with pytest.raises(
        ValueError, match=r"--attention.camera='wrist' is not a camera of the policy; allowed: top"
    ):
        _run(tiny_checkpoints[0], tmp_path / "x", camera="wrist")
    with pytest.raises(ValueError, match=r"--attention.codec='h265'.*allowed: libx264, mpeg4"):
        _run(tiny_checkpoints[0], tmp_path / "x", codec="h265")
    with pytest.raises(ValueError, match=r"Unknown condition 'full'"):
        run_attention(
            AttentionConfig(
                policy=PolicyRefConfig(path=str(act_checkpoint)),
                env=EvalEnvConfig(condition="full"),
                output_dir=str(tmp_path / "x"),
            )
        )
    assert not (tmp_path / "x").exists(), "bad input must fail before any output"
