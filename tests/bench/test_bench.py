import json

from helpers import run_cli
from lerobot_condground.core.training import native_bf16


def test_bench_json_reports_every_figure():
    out = run_cli(
        "condground",
        "bench",
        "--json=true",
        "--seconds=0.3",
        "--rounds=2",
        "--record_episodes=1",
        "--observation_height=96",
        "--observation_width=128",
        "--policy.dim_model=64",
        "--policy.chunk_size=10",
        "--policy.batch_size=2",
        "--policy.steps=1",
        "--sweep.workers=1,2",
        "--sweep.episodes=4",
        "--sweep.batch_size=2",
        "--sweep.episode_length=10",
        "--sweep.dim_model=64",
        "--train.episodes=1",
        "--train.batch_size=2",
        "--train.steps=1",
        "--train.dim_model=32",
        "--train.batch_sizes=4",
        "--train.peak_seconds=0.3",
        "--train.compile=false",  # inductor compiles for minutes; the option is timed by the bench's own runs
    )
    result = json.loads(out.stdout.strip().splitlines()[-1])
    for key in (
        "physics_steps_per_s",
        "render_fps",
        "env_steps_per_s",
        "env_steps_per_s_with_segmentation",
        "env_steps_per_s_expert",
        "env_steps_per_s_expert_servo_direct",
        "servo_interpolated_over_direct_ratio",
        "record_frames_per_s",
    ):
        assert result[key] > 0, key
    assert result["resolution"] == [96, 128]
    assert result["physics_steps_per_s"] > result["env_steps_per_s"]
    for policy in ("act", "standard", "augmentation", "augmentation_attention", "full"):
        assert result[f"{policy}_train_step_s"] > 0 and result[f"{policy}_inference_s"] > 0, policy
    assert result["act_modified_train_step_ratio"] == result["full_train_step_ratio"] > 0
    assert result["act_modified_inference_ratio"] == result["full_inference_ratio"] > 0
    for workers in (1, 2):
        assert result[f"sweep_rollouts_per_min_{workers}_workers"] > 0
        assert result[f"sweep_env_steps_per_s_{workers}_workers"] > 0
    assert (
        result["sweep_speedup_2_workers"]
        == result["sweep_rollouts_per_min_2_workers"] / result["sweep_rollouts_per_min_1_workers"]
    )
    # Training throughput at the CPU configuration, beside stock ACT and today's path, in the same run.
    assert set(result["train_samples_per_s"]) == {
        "standard",
        "augmentation",
        "augmentation_attention",
        "full",
    }
    assert all(rate > 0 for rate in result["train_samples_per_s"].values())
    assert result["train_samples_per_s_act"] > 0 and result["train_samples_per_s_full_plain"] > 0
    assert result["train_speedup_vs_plain"] > 0 and result["train_cache_speedup"] > 0
    assert result["train_threads"] == 1 and result["train_batch_size"] == 2
    split = result["train_step_split_s"]["full"]
    assert split["data"] > 0 and split["preprocess"] > 0 and split["update"] > 0
    # The ceiling and the speed options, against the current path and LeRobot's, in the same rounds.
    assert result["train_flops_per_sample"]["full"] > result["train_flops_per_sample"]["standard"] > 0
    peaks = result["train_peak_gflops"]
    assert set(peaks) == ({"fp32", "bf16"} if native_bf16() else {"fp32"})
    assert all(set(p) == {"matmul", "conv3x3"} and min(p.values()) > 0 for p in peaks.values())
    options = {"lerobot", "current", "channels_last", "kept"} | (
        {"onednn_bf16", "bf16", "bf16_channels_last"} if native_bf16() else set()
    )
    expected = {f"{variant}.{option}" for variant in ("standard", "full") for option in options}
    assert set(result["train_option_samples_per_s"]) == set(result["train_option_speedup"]) == expected
    assert (
        result["train_option_speedup"]["standard.current"]
        == result["train_option_speedup"]["full.current"]
        == 1
    )
    assert result["train_compile_s"] == {}
    assert "channels_last" in result["train_kept_options"]
    assert result["train_config_speedup"] > 0 and 0 < result["train_flop_fraction"] < 1
    assert set(result["train_batch_samples_per_s"]) == set(result["train_batch_speedup"]) == {"2", "4"}
    assert result["train_batch_speedup"]["2"] == 1 and result["train_batch_samples_per_s"]["4"] > 0
    profile = result["train_profile"]
    assert set(profile["phases_s"]) == {"data", "preprocess", "forward", "backward", "optimizer"}
    assert profile["operators_s"]["convolution"] > 0 and all(s >= 0 for s in profile["operators_s"].values())
    layouts = result["train_thread_layouts_samples_per_s"]
    assert layouts["1x2"] > 0 and layouts["2x1"] > 0
    assert result["train_2x1_over_1x2"] == layouts["2x1"] / layouts["1x2"]
