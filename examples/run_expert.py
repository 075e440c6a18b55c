"""Run the scripted expert for one episode and save the first frame with its segmentation overlay.

python examples/run_expert.py --condition full_mixed --out expert_frame.png
"""

import argparse

import cv2
import gymnasium as gym
import numpy as np

from lerobot_condground.envs.expert import ScriptedExpert  # importing envs registers gym_condground/*


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--task", default="PickPlaceRandomBin-v0")
    parser.add_argument("--condition", default="full_mixed")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="expert_frame.png")
    args = parser.parse_args()

    env = gym.make(f"gym_condground/{args.task}", condition=args.condition, segmentation=True)
    expert = ScriptedExpert()
    obs, info = env.reset(seed=args.seed)
    expert.reset(env)
    first_rgb, first_seg = obs["pixels"]["top"], obs["segmentation"]
    print(env.unwrapped.task_description)
    while True:
        obs, reward, terminated, truncated, info = env.step(expert.act(obs))
        if terminated or truncated:
            break
    print(f"stage reached: {int(reward)} (0 none, 1 pick, 2 lift, 3 place), success: {info['is_success']}")

    palette = np.random.default_rng(0).integers(0, 255, (256, 3), dtype=np.uint8)
    palette[0] = 0
    overlay = np.where(first_seg[..., None] > 0, palette[first_seg] // 2 + first_rgb // 2, first_rgb)
    cv2.imwrite(args.out, cv2.cvtColor(np.concatenate([first_rgb, overlay], axis=1), cv2.COLOR_RGB2BGR))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
