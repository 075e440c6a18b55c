"""The training configuration that learns on a 2-core CPU, as `lerobot-train` flags.

Measured in `docs/learning-curve/` (docs/measurements.md, "Learning from scratch on this CPU"): a quarter-width
ResNet-18 with batch norm trained from scratch (ImageNet weights cannot be downloaded everywhere,
and LeRobot's frozen batch norm is an identity without them), a small transformer (width 128, two
encoder layers), no CVAE (the demonstrations are scripted, one mode per state), 96x128 frames.
The learning rate anneals on a cosine to zero at the run's `--steps` (after 500 warm-up steps): measured
against the constant rate on Task 1, two seeds each, three late checkpoints pooled on 300 paired held-out
rollouts, +6.7 points [+0.8, +12.5] (McNemar p = 0.033; docs/learning-curve/v2/). So `--steps` must be the
run's real budget. No dropout (ACT's default is 0.1): against the cosine configuration, same protocol,
+16.0 points [+9.4, +22.5] (p = 4e-6): the policy underfits, and dropout regularizes what it cannot spare.
It learns from demonstrations recorded with a 0.06 rad joint drift (DART, `condground record
--drift.std`): +16.7 points [+9.8, +23.3] against clean demonstrations (p = 4e-6), and trains 12000 steps:
+17.3 points [+11.1, +23.4] against 6000 (p = 1e-7), while 20000 add +0.3 [-5.6, +6.2] (p = 1.0). 200
demonstrations instead of 100: Task 1 70.3 % -> 78.0 % of 300 held-out rollouts (+7.7 [+1.5, +13.8],
p = 0.019; the layouts beyond the bowl 28 % -> 73 %), Task 2 27.7 % -> 52.3 % (+24.7 [+17.0, +31.9],
p = 9e-10); 400 add +4.3 [-2.4, +11.0] on Task 2 (p = 0.25). Recovery data are not in the paper.
Not settled: on Task 1, 100 of these and 100 expert takeovers from a weak prompted policy's states beat 200
of these trained beside them (87.7 % against 73.3 %, +14.3 [+8.5, +20.1], p = 2e-6), but takeovers from a
`standard` driver added nothing measurable at 6000 steps on either task (Task 1 +2.7, p = 0.56; Task 2 -0.3
[-7.7, +7.1], p = 1.0); at 12000 steps on Task 2, driven by the 12000-step baseline, 51.3 % -> 60.7 % (+9.3
[+2.5, +16.0], p = 0.0097), but with reproduce's 6000-step driver +5.3 (p = 0.16), and no size control ran at
12000. ACT's own size (full-width backbone, width 512, four encoder layers) trained 6000 steps beats this
configuration on Task 2 (51.3 % -> 60.0 %, +8.7 [+1.1, +16.1], p = 0.032) at about twice the minutes (100
against 44 a run); Task 1 with it is unmeasured.
The quickstart, the learning-curve example, `reproduce --preset=cpu` and the benchmark
all read it from here.
"""

from __future__ import annotations

from pathlib import Path

# Frame size the configuration was measured at (condground record --env.observation_height/width).
CPU_FRAME_SIZE = (96, 128)

CPU_POLICY = {
    "pretrained_backbone_weights": None,
    "backbone_width": 16,
    "backbone_norm": "batchnorm",
    "dim_model": 128,
    "n_heads": 8,
    "dim_feedforward": 512,
    "n_encoder_layers": 2,
    "use_vae": False,
    "chunk_size": 20,
    "n_action_steps": 10,
    "optimizer_lr": 3e-4,
    "optimizer_lr_backbone": 3e-4,
    "scheduler_name": "cosine",
    "dropout": 0.0,
}
CPU_BATCH_SIZE = 16
# The step budget where Task 1's held-out success stops rising (the cosine schedule ends there).
CPU_STEPS = 12_000
# Demonstrations per task, and the drift (rad, `--drift.std`) they are recorded with.
CPU_EPISODES = 200
CPU_DRIFT_STD = 0.06


def amp_flags(cpuinfo: Path = Path("/proc/cpuinfo")) -> list[str]:
    """bf16 autocast where the CPU has AMX tiles: a training step 1.25 times as fast as fp32 there
    (`condground bench`, docs/measurements.md); without them (AVX2) a step under autocast was 23 times slower. Every
    `act_modified` loss term stays within bf16 rounding of fp32 (tested), so this is a speed setting."""
    try:
        flags = cpuinfo.read_text()
    except OSError:  # not Linux: no way to tell, fp32 is never the slow choice
        return []
    return ["--policy.use_amp=true"] if " amx_bf16" in flags else []


def policy_flags() -> list[str]:
    """The configuration as `--policy.key=value` flags for lerobot-train (None as null, booleans lowercase)."""
    flags = []
    for key, value in CPU_POLICY.items():
        text = "null" if value is None else str(value).lower() if isinstance(value, bool) else str(value)
        flags.append(f"--policy.{key}={text}")
    return flags


if __name__ == "__main__":  # for shell scripts: `python -m lerobot_condground.core.training`
    print(" ".join([*policy_flags(), f"--batch_size={CPU_BATCH_SIZE}"]))
