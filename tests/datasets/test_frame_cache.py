"""Decoded frames held in memory (`FrameCache`, `condground train`): the same samples as LeRobot's own
decoding, read from memory after the first time, within the budget."""

import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from helpers import run_cli
from lerobot_condground.datasets.frame_cache import FrameCache

INDICES = [0, 7, 31, 7, 0, 50]


def _samples(root) -> list[dict]:
    dataset = LeRobotDataset(
        "local/test_full_mixed", root=root, delta_timestamps={"action": [i / 20 for i in range(5)]}
    )
    return [dataset[i] for i in INDICES]


def _assert_same(samples: list[dict], reference: list[dict]) -> None:
    for sample, expected in zip(samples, reference, strict=True):
        assert sample.keys() == expected.keys()
        for key, value in expected.items():
            if isinstance(value, torch.Tensor):
                assert torch.equal(sample[key], value), key
            else:
                assert sample[key] == value, key


def test_cached_samples_are_the_decoded_samples(recorded_dataset):
    reference = _samples(recorded_dataset)
    with FrameCache(max_gb=1) as cache:
        first = _samples(recorded_dataset)
        second = _samples(recorded_dataset)
    _assert_same(first, reference)
    _assert_same(second, reference)
    unique = len(set(INDICES))
    assert cache.misses == unique and cache.hits == 2 * len(INDICES) - unique
    assert cache.bytes == unique * reference[0]["observation.images.top"].nbytes
    # Outside the block LeRobot decodes again, uncached.
    _assert_same(_samples(recorded_dataset), reference)
    assert cache.misses == unique


def test_the_budget_caps_memory_not_correctness(recorded_dataset):
    reference = _samples(recorded_dataset)
    with FrameCache(max_gb=1e-9) as cache:
        _assert_same(_samples(recorded_dataset), reference)
    assert cache.bytes == 0 and cache.hits == 0


@pytest.mark.parametrize("size", [0, -1, float("nan"), "8", True])
def test_a_bad_budget_is_refused(size):
    with pytest.raises(ValueError, match="max_gb"):
        FrameCache(max_gb=size)


@pytest.mark.parametrize("steps", ["0", "-5", "1.5", "ten"])
def test_condground_train_refuses_a_step_count_that_trains_nothing(steps, tmp_path):
    proc = run_cli("condground", "train", f"--steps={steps}", f"--output_dir={tmp_path / 'run'}", check=False)
    assert proc.returncode == 2 and f"--steps={steps} is not allowed" in proc.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "run").exists()


def test_condground_train_is_lerobot_train(recorded_dataset, tmp_path):
    """Same flags as lerobot-train, same checkpoint layout; its one flag of its own is checked first."""
    bad = run_cli("condground", "train", "--frame_cache_gb=lots", check=False)
    assert bad.returncode == 2 and "--frame_cache_gb=lots" in bad.stderr
    run_cli(
        "condground",
        "train",
        "--frame_cache_gb=0.5",
        "--policy.type=act_modified",
        "--policy.variant=standard",
        "--policy.device=cpu",
        "--policy.push_to_hub=false",
        "--policy.pretrained_backbone_weights=null",
        "--policy.backbone_width=8",
        "--policy.backbone_norm=batchnorm",
        "--policy.dim_model=32",
        "--policy.n_heads=2",
        "--policy.dim_feedforward=64",
        "--policy.n_encoder_layers=1",
        "--policy.use_vae=false",
        "--policy.chunk_size=5",
        "--policy.n_action_steps=5",
        "--dataset.repo_id=local/test_full_mixed",
        f"--dataset.root={recorded_dataset}",
        "--batch_size=2",
        "--steps=2",
        "--save_freq=2",
        "--num_workers=0",
        f"--output_dir={tmp_path / 'train'}",
        "--wandb.enable=false",
    )
    saved = tmp_path / "train" / "checkpoints" / "last" / "pretrained_model"
    assert {"config.json", "model.safetensors", "train_config.json"} <= {p.name for p in saved.iterdir()}
