"""LeRobot's stock console scripts resolve the plugin's env type with no extra flag."""

import json

import pytest

from helpers import read_json, run_cli

TINY_ACT = [
    "--policy.type=act",
    "--policy.device=cpu",
    "--policy.push_to_hub=false",
    "--policy.pretrained_backbone_weights=null",
    "--policy.dim_model=64",
    "--policy.n_heads=2",
    "--policy.dim_feedforward=128",
    "--policy.n_encoder_layers=1",
    "--policy.n_decoder_layers=1",
    "--policy.chunk_size=10",
    "--policy.n_action_steps=10",
]


@pytest.fixture(scope="module")
def stock_act_checkpoint(plain_dataset, tmp_path_factory):
    """A stock ACT trained 2 steps by lerobot-train on a label-free recording, with lerobot-train's own
    periodic env eval."""
    out = tmp_path_factory.mktemp("train") / "run"
    run_cli(
        "lerobot-train",
        *TINY_ACT,
        "--dataset.repo_id=local/test_plain",
        f"--dataset.root={plain_dataset}",
        "--batch_size=2",
        "--steps=2",
        "--save_freq=2",
        "--log_freq=1",
        "--num_workers=0",
        "--env.type=condground",
        "--env.task=PickPlaceRandomBin-v0",
        "--env.condition=full_mixed",
        "--env.episode_length=8",
        "--env_eval_freq=2",
        "--eval.n_episodes=1",
        "--eval.batch_size=1",
        f"--output_dir={out}",
        "--wandb.enable=false",
    )
    ckpt = out / "checkpoints" / "last" / "pretrained_model"
    config = read_json(ckpt / "config.json")
    assert config["type"] == "act"
    assert set(config["input_features"]) == {"observation.images.top", "observation.state"}
    return ckpt


@pytest.mark.parametrize("async_envs", [True, False])
def test_stock_lerobot_eval_runs_our_env(stock_act_checkpoint, tmp_path, async_envs):
    out = tmp_path / "eval"
    run_cli(
        "lerobot-eval",
        f"--policy.path={stock_act_checkpoint}",
        "--env.type=condground",
        "--env.task=PickPlaceFixedBin-v0",
        "--env.condition=object_shape_2",
        "--env.episode_length=15",
        "--eval.n_episodes=2",
        "--eval.batch_size=2",
        f"--eval.use_async_envs={str(async_envs).lower()}",
        f"--output_dir={out}",
    )
    info = json.loads((out / "eval_info.json").read_text())
    metrics = info["per_task"][0]["metrics"]
    assert len(metrics["max_rewards"]) == 2
    # The reward is the stage index, so max reward is the stage reached (0..3).
    assert all(r in (0.0, 1.0, 2.0, 3.0) for r in metrics["max_rewards"])
    assert info["overall"]["n_episodes"] == 2
    assert "condground" in info["per_group"]


@pytest.mark.parametrize(
    "flag, message",
    [
        ("--env.condition=object_color_7", "error: Unknown condition 'object_color_7'; allowed: clean,"),
        ("--env.fps=33", "error: Control rate fps=33 is not allowed; allowed: divisors of 500 from 5 to 100"),
    ],
)
def test_bad_env_flags_are_the_last_line_under_lerobot_eval(stock_act_checkpoint, tmp_path, flag, message):
    """Our env config's message ends the stock script's output as one line (no draccus traceback)."""
    out = run_cli(
        "lerobot-eval", f"--policy.path={stock_act_checkpoint}", "--env.type=condground", flag,
        "--eval.n_episodes=1", f"--output_dir={tmp_path}", check=False,
    )  # fmt: skip
    assert out.returncode != 0 and out.stderr.strip().splitlines()[-1].startswith(message), out.stderr[-2000:]
    assert "Traceback" not in out.stderr


def test_bad_robot_flags_are_the_last_line_under_lerobot_record(tmp_path):
    out = run_cli(
        "lerobot-record", "--robot.type=ur3e", "--robot.backend=rtde", "--dataset.repo_id=local/x",
        f"--dataset.root={tmp_path / 'x'}", "--dataset.single_task=t", check=False,
    )  # fmt: skip
    last = out.stderr.strip().splitlines()[-1]
    assert out.returncode != 0 and last.startswith("error: Invalid ur3e robot config: host is required"), last
    assert "Traceback" not in out.stderr and not (tmp_path / "x").exists()


@pytest.fixture(scope="module")
def act_modified_checkpoint(recorded_dataset, tmp_path_factory):
    """The full act_modified variant trained 3 steps by the stock lerobot-train, with its periodic env eval,
    the cosine learning-rate schedule of its training preset and a moving average of its weights."""
    out = tmp_path_factory.mktemp("train_modified") / "run"
    tiny = [a.replace("--policy.type=act", "--policy.type=act_modified") for a in TINY_ACT]
    run_cli(
        "lerobot-train",
        *tiny,
        "--policy.variant=full",
        "--policy.n_vae_encoder_layers=1",
        "--policy.scheduler_name=cosine",
        "--policy.scheduler_warmup_steps=1",
        "--policy.ema_decay=0.9",
        "--dataset.repo_id=local/test_full_mixed",
        f"--dataset.root={recorded_dataset}",
        "--batch_size=2",
        "--steps=3",
        "--save_freq=3",
        "--log_freq=1",
        "--num_workers=0",
        f"--output_dir={out}",
        "--wandb.enable=false",
        "--env.type=condground",
        "--env.task=PickPlaceRandomBin-v0",
        "--env.condition=full_mixed",
        "--env.episode_length=6",
        "--env_eval_freq=3",
        "--eval.n_episodes=1",
        "--eval.batch_size=1",
    )
    return out / "checkpoints" / "last" / "pretrained_model"


def test_act_modified_checkpoint_is_a_standard_lerobot_checkpoint(act_modified_checkpoint):
    config = read_json(act_modified_checkpoint / "config.json")
    assert config["type"] == "act_modified" and config["variant"] == "full"
    assert set(config["input_features"]) == {"observation.images.top", "observation.state"}
    assert "observation.segmentation" in config["label_keys"]
    steps = read_json(act_modified_checkpoint / "policy_preprocessor.json")["steps"]
    names = [s.get("registry_name") for s in steps]
    copy_paste = names.index("condground_copy_paste")
    assert names.index("device_processor") < copy_paste < names.index("normalizer_processor")
    assert (act_modified_checkpoint / steps[copy_paste]["state_file"]).exists()
    assert (act_modified_checkpoint / "model.safetensors").exists()


def test_act_modified_cosine_schedule_anneals_to_zero_at_the_last_step(act_modified_checkpoint):
    train_config = read_json(act_modified_checkpoint / "train_config.json")
    assert train_config["scheduler"] == {"type": "cosine_annealing_with_warmup", "num_warmup_steps": 1}
    state = read_json(act_modified_checkpoint.parent / "training_state" / "scheduler_state.json")
    assert state["last_epoch"] == 3
    # Two parameter groups (backbone and the rest), both annealed to zero by step 3 of 3.
    assert len(state["base_lrs"]) == 2 and all(lr > 0 for lr in state["base_lrs"])
    assert state["_last_lr"] == [0.0, 0.0]


def test_lerobot_train_updates_the_moving_average_after_every_step(act_modified_checkpoint):
    import torch
    from safetensors.torch import load_file

    weights = load_file(act_modified_checkpoint / "model.safetensors")
    assert weights["ema_updates"].item() == 3
    raw = {k: v for k, v in weights.items() if k.startswith("model.")}
    assert raw.keys() == {k.replace("ema_model.", "model.", 1) for k in weights if k.startswith("ema_model.")}
    moved = [k for k, v in raw.items() if v.is_floating_point() and not torch.equal(v, weights["ema_" + k])]
    assert moved, "the average never trailed the trained weights"


def test_stock_lerobot_eval_runs_act_modified(act_modified_checkpoint, tmp_path):
    out = tmp_path / "eval"
    run_cli(
        "lerobot-eval",
        f"--policy.path={act_modified_checkpoint}",
        "--env.type=condground",
        "--env.task=PickPlaceRandomBin-v0",
        "--env.condition=full_mixed",
        "--env.episode_length=12",
        "--eval.n_episodes=2",
        "--eval.batch_size=2",
        f"--output_dir={out}",
    )
    info = read_json(out / "eval_info.json")
    assert info["overall"]["n_episodes"] == 2
    assert all(r in (0.0, 1.0, 2.0, 3.0) for r in info["per_task"][0]["metrics"]["max_rewards"])


def one_episode_eval(checkpoint, out, *flags: str):
    """Stock lerobot-eval, one short episode of the condground env with `flags`; may fail."""
    return run_cli(
        "lerobot-eval",
        f"--policy.path={checkpoint}",
        "--env.type=condground",
        *flags,
        "--env.episode_length=4",
        "--eval.n_episodes=1",
        "--eval.batch_size=1",
        "--eval.use_async_envs=false",
        f"--output_dir={out}",
        check=False,
    )


def test_act_modified_needs_prompts_from_the_env(act_modified_checkpoint, tmp_path):
    out = one_episode_eval(act_modified_checkpoint, tmp_path, "--env.prompts=false")
    assert out.returncode != 0 and "--env.prompts=true" in out.stdout + out.stderr


def test_act_modified_refuses_frames_of_another_size(act_modified_checkpoint, tmp_path):
    out = one_episode_eval(
        act_modified_checkpoint, tmp_path, "--env.observation_height=96", "--env.observation_width=128"
    )
    # The traceback's last word (before tqdm's bar clean-up) is the fix.
    last = [line for line in out.stderr.splitlines() if line.startswith("ValueError")][-1]
    assert (
        out.returncode != 0
        and "frames are 96x128, but this act_modified checkpoint was trained on 240x320" in last
    )
    assert "--env.observation_height=240 --env.observation_width=320" in last
    # ... and it is said before the traceback too.
    assert out.stderr.index("this act_modified checkpoint was trained on") < out.stderr.index("Traceback")
