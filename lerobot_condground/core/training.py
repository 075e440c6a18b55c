"""The training configuration that learns on a 2-core CPU, as `lerobot-train` flags.

Measured in `docs/learning-curve/` (docs/measurements.md, "Learning from scratch on this CPU"). ACT's own
model (a full-width ResNet-18, transformer width 512, feed-forward 2048, four encoder layers, one decoder
layer) trained from scratch with batch norm (ImageNet weights cannot be downloaded everywhere, and
LeRobot's frozen batch norm is an identity without them), no CVAE (the demonstrations are scripted, one
mode per state), 96x128 frames, 6000 steps of batch 16: against the configuration before it (a quarter-width
backbone, width 128, two encoder layers, 12000 steps), two seeds each, three late checkpoints pooled on 300
paired held-out rollouts, Task 2 51.3 % -> 60.0 % (+8.7 points [+1.1, +16.1], McNemar p = 0.032), Task 1
73.3 % -> 75.3 % (+2.0 [-4.4, +8.3], p = 0.61; its last checkpoints 78 % -> 89 %, a post-hoc reading), in
about 100 minutes a run on one core of the 2-core EPYC against 44 (docs/learning-curve/v2/, nineteenth and
twentieth sessions).
The learning rate anneals on a cosine to zero at the run's `--steps` (after 500 warm-up steps): measured
against the constant rate on Task 1, +6.7 points [+0.8, +12.5] (p = 0.033), so `--steps` must be the run's
real budget. No dropout (ACT's default is 0.1): +16.0 points [+9.4, +22.5] (p = 4e-6): the policy underfits,
and dropout regularizes what it cannot spare. It learns from demonstrations recorded with a 0.06 rad joint
drift (DART, `condground record --drift.std`): +16.7 points [+9.8, +23.3] against clean demonstrations
(p = 4e-6); 200 of them instead of 100: Task 1 +7.7 [+1.5, +13.8] (p = 0.019), Task 2 +24.7 [+17.0, +31.9]
(p = 9e-10); 400 add +4.3 [-2.4, +11.0] on Task 2 (p = 0.25). Those levers were measured on the smaller
model. Recovery data are not in the paper.
Not settled: a DAgger round (the expert taking over from a trained policy's states, `condground record
--takeover.*`) paid on the smaller model at 12000 steps (Task 1 87.7 % against 73.3 % with a prompted
driver, Task 2 60.7 % against 51.3 % with a `standard` one), but not at 6000 steps or with reproduce's
6000-step driver; on this model Task 2's round from its own 6000-step policy gave +3.0 points [-4.4, +10.3]
(p = 0.48) at 6000 steps, 86 % and 80 % at its last checkpoints (docs/learning-curve/v2, twenty-first session).
The p-values above are the lever protocol's Newcombe/McNemar figures, which took 300 pooled rollouts as
independent pairs. Read again with the layout as the pairing unit and the training runs' spread added
(`evaluation.statistics.clustered_difference`, Holm over the lever table; issue 57), none of these levers
is resolved with two runs an arm: the configuration rests on effects that point the same way in both
seeds (all but ACT's own size on Task 1, kept for Task 2), not on significance (docs/learning-curve/v2/README.md).
The quickstart, the learning-curve example, `reproduce --preset=cpu` and the benchmark
all read it from here.
"""

from __future__ import annotations

from pathlib import Path

# Frame size the configuration was measured at (condground record --env.observation_height/width).
CPU_FRAME_SIZE = (96, 128)

CPU_POLICY = {
    "pretrained_backbone_weights": None,
    "backbone_width": 64,
    "backbone_norm": "batchnorm",
    "dim_model": 512,
    "n_heads": 8,
    "dim_feedforward": 2048,
    "n_encoder_layers": 4,
    "use_vae": False,
    "chunk_size": 20,
    "n_action_steps": 10,
    "optimizer_lr": 3e-4,
    "optimizer_lr_backbone": 3e-4,
    "scheduler_name": "cosine",
    "dropout": 0.0,
}
CPU_BATCH_SIZE = 16
# The step budget (the cosine schedule ends there): about 100 minutes a run on one core of the 2-core EPYC.
CPU_STEPS = 6_000
# Demonstrations per task, and the drift (rad, `--drift.std`) they are recorded with.
CPU_EPISODES = 200
CPU_DRIFT_STD = 0.06


def _cpu_flags(cpuinfo: Path) -> str:
    try:
        return cpuinfo.read_text()
    except OSError:  # not Linux: no way to tell, fp32 is never the slow choice
        return ""


def native_bf16(cpuinfo: Path = Path("/proc/cpuinfo")) -> bool:
    """Whether this CPU multiplies bf16 natively: AMX tiles (Xeon) or AVX-512 BF16 dot products (AMD's Zen 4 and 5).
    Only there can bf16 be faster than fp32; without them (AVX2) a step under autocast was 23 times slower."""
    return any(f" {flag}" in _cpu_flags(cpuinfo) for flag in ("amx_bf16", "avx512_bf16"))


def amp_flags(cpuinfo: Path = Path("/proc/cpuinfo")) -> list[str]:
    """bf16 autocast in training where this CPU multiplies bf16 natively (`native_bf16`): a step 1.87 times as
    fast as fp32 on the Zen 5 EPYC (AVX-512 BF16), 1.25 on the AMX Xeon (`condground bench`,
    docs/measurements.md). What the policy learns stays within the seeds' spread: the training loss over the
    first 500 steps, and Task 1 by the protocol, two seeds each (docs/learning-curve/timed/). Evaluation
    stays fp32."""
    return ["--policy.use_amp=true"] if native_bf16(cpuinfo) else []


def speed_flags(cpuinfo: Path = Path("/proc/cpuinfo")) -> list[str]:
    """How a training step runs fastest here: channels-last frames into the backbone, and bf16 where
    `amp_flags` turns it on. Speed settings, not the configuration: `policy_flags` (which a reproduction pins)
    leaves them out, every training command here adds them."""
    return ["--policy.channels_last=true", *amp_flags(cpuinfo)]


def policy_flags() -> list[str]:
    """The configuration as `--policy.key=value` flags for lerobot-train (None as null, booleans lowercase)."""
    flags = []
    for key, value in CPU_POLICY.items():
        text = "null" if value is None else str(value).lower() if isinstance(value, bool) else str(value)
        flags.append(f"--policy.{key}={text}")
    return flags


if __name__ == "__main__":  # for shell scripts: `python -m lerobot_condground.core.training`
    print(" ".join([*policy_flags(), *speed_flags(), f"--batch_size={CPU_BATCH_SIZE}"]))
