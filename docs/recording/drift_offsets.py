"""How far `condground record --drift.std` moves the tool off the expert's path, phase by phase.

    python docs/recording/drift_offsets.py --task=PickPlaceFixedBin-v0 --std=0.03 --layouts=20

Each layout runs twice with the same seed, without drift and with it (same expert targets); the table is the
distance between the two tools at each step (cm), by the expert's phase, and how often the drifted expert
still succeeds. No rendering: a few seconds a layout.
"""

from __future__ import annotations

import argparse
from collections import defaultdict

import numpy as np

from lerobot_condground.envs.expert import JointDrift, ScriptedExpert, run_expert_episode
from lerobot_condground.envs.pickplace_env import PickPlaceEnv


def tool_path(env, expert, seed: int, drift: JointDrift | None) -> tuple[list, bool]:
    """(phase, tool position) at every step of one expert episode, and whether it succeeded."""
    path = []
    info = run_expert_episode(
        env, expert, seed, 300, drift=drift,
        on_step=lambda obs, action, phase: path.append((expert.phase, env.tcp_pose()[0].copy())),
    )  # fmt: skip
    return path, bool(info["is_success"])


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--task", default="PickPlaceFixedBin-v0")
    parser.add_argument("--std", type=float, default=0.03)
    parser.add_argument("--time_constant", type=float, default=0.5)
    parser.add_argument("--layouts", type=int, default=20)
    args = parser.parse_args()
    env = PickPlaceEnv(task=args.task, condition="clean", obs_type="agent_pos")
    expert = ScriptedExpert()
    offsets, successes = defaultdict(list), 0
    for seed in range(args.layouts):
        clean, _ = tool_path(env, expert, seed, None)
        drifted, success = tool_path(
            env, expert, seed, JointDrift(args.std, args.time_constant, env.fps, seed)
        )
        successes += success
        for (phase, a), (_, b) in zip(clean, drifted, strict=False):
            offsets[phase].append(100 * float(np.linalg.norm(a - b)))
    print(
        f"{args.task}, drift {args.std} rad over {args.time_constant} s: expert success {successes}/{args.layouts}"
    )
    print("phase      mean cm  p90 cm")
    for phase, values in offsets.items():
        print(f"{phase:<10} {np.mean(values):7.2f} {np.percentile(values, 90):7.2f}")
    env.close()


if __name__ == "__main__":
    main()
