"""Where do copy-paste's pastes land: on the robot, or against the target? (issue 55, suspect 2)

The recorded segmentation labels the robot as background (0), so the copy-paste step protects only the two
targets' pixels. This runs the scripted expert on N training layouts at a frame size, renders the robot's
own mask beside every sampled frame (MuJoCo's geom groups of the arm and the gripper), pastes with the policy's
default copy-paste settings, and counts, over the frames a paste went into:

- how often a paste covers robot pixels, and what share of the robot's visible pixels it covers;
- how often it covers the gripper, and what share of the gripper's visible pixels;
- how often a paste touches the target object (within one pixel of its mask), and how often one lies within
  `--near` pixels of it;

each split by phase (0: acquire, 1: place) and, in phase 0, for the frames where the gripper is within
`--near` pixels of the cube (the grasp, where `full` loses its points).

    python docs/learning-curve/v3/paste_overlap.py --task=PickPlaceFixedBin-v0 --episodes=20 --output=docs/learning-curve/v3/paste_overlap.csv
"""

import argparse
from pathlib import Path

import mujoco
import numpy as np
import pandas as pd
import torch
import torch.nn.functional as F
from tqdm import tqdm

from lerobot_condground.core.labels import SYNTHETIC_DISTRACTOR, TARGET_OBJECT
from lerobot_condground.envs import robot
from lerobot_condground.envs.expert import ScriptedExpert, run_expert_episode
from lerobot_condground.envs.pickplace_env import PickPlaceEnv
from lerobot_condground.processors.copy_paste import CopyPasteDistractorStep


def robot_masks(env: PickPlaceEnv) -> tuple[np.ndarray, np.ndarray]:
    """(arm, gripper) pixel masks of the scene camera."""
    r = env._get_renderer()
    r.enable_segmentation_rendering()
    try:
        r.update_scene(env.data, camera="top")
        seg = r.render()
    finally:
        r.disable_segmentation_rendering()
    ids, types = seg[..., 0], seg[..., 1]
    is_geom = (types == int(mujoco.mjtObj.mjOBJ_GEOM)) & (ids >= 0)
    group = np.full(ids.shape, -1)
    group[is_geom] = env.model.geom_group[ids[is_geom]]
    return group == robot.ARM_GROUP, group == robot.GRIPPER_GROUP


def near(mask: torch.Tensor, pixels: int) -> torch.Tensor:
    """(B, H, W) bool mask dilated by `pixels` (a square)."""
    side = 2 * pixels + 1
    return F.max_pool2d(mask.unsqueeze(1).float(), side, stride=1, padding=pixels).squeeze(1) > 0


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="PickPlaceFixedBin-v0")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--every", type=int, default=4, help="keep every k-th frame of an episode")
    parser.add_argument("--size", default="96x128")
    parser.add_argument("--near", type=int, default=4, help="pixels")
    parser.add_argument("--repeats", type=int, default=4, help="paste draws per frame")
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args()
    torch.set_num_threads(1)
    height, width = (int(v) for v in args.size.split("x"))
    env = PickPlaceEnv(
        task=args.task,
        condition="clean",
        observation_height=height,
        observation_width=width,
        segmentation=True,
    )
    frames, segs, arms, grippers, phases = [], [], [], [], []
    count = [0]

    def keep(obs, action, phase):
        count[0] += 1
        if count[0] % args.every:
            return
        arm, gripper = robot_masks(env)
        frames.append(obs["pixels"]["top"])
        segs.append(obs["segmentation"])
        arms.append(arm | gripper)
        grippers.append(gripper)
        phases.append(phase)

    for seed in tqdm(range(args.episodes), desc="expert episodes"):
        run_expert_episode(env, ScriptedExpert(), seed=seed, max_steps=400, on_step=keep)
    env.close()
    images = torch.from_numpy(np.stack(frames)).permute(0, 3, 1, 2).float() / 255
    seg = torch.from_numpy(np.stack(segs))
    arm, gripper = torch.from_numpy(np.stack(arms)), torch.from_numpy(np.stack(grippers))
    phase = torch.tensor(phases)
    cube = seg == TARGET_OBJECT
    at_grasp = (phase == 0) & (near(gripper, args.near) & cube).flatten(1).any(1)

    totals: dict[str, list[torch.Tensor]] = {}
    for repeat in range(args.repeats):
        _, labels = CopyPasteDistractorStep(seed=repeat).augment(images, seg)
        pasted = labels == SYNTHETIC_DISTRACTOR
        arm_hit = (pasted & arm).flatten(1).sum(1)
        grip_hit = (pasted & gripper).flatten(1).sum(1)
        per_frame = {
            "pasted": pasted.flatten(1).any(1),
            "robot_covered": arm_hit > 0,
            "robot_share": arm_hit / arm.flatten(1).sum(1).clamp(min=1),
            "gripper_covered": grip_hit > 0,
            "gripper_share": grip_hit / gripper.flatten(1).sum(1).clamp(min=1),
            "touches_cube": (pasted & near(cube, 1)).flatten(1).any(1),
            "near_cube": (pasted & near(cube, args.near)).flatten(1).any(1),
        }
        for key, value in per_frame.items():
            totals.setdefault(key, []).append(value.float())
    stacked = {k: torch.stack(v) for k, v in totals.items()}  # (repeats, frames)
    rows = []
    for split, frames_in in (
        ("all", torch.ones_like(phase, dtype=torch.bool)),
        ("acquire", phase == 0),
        ("grasp", at_grasp),
        ("place", phase == 1),
    ):
        augmented = (stacked["pasted"] > 0) & frames_in
        n = int(augmented.sum())
        row = {"task": args.task, "frame": args.size, "split": split, "n": n}
        for key in list(stacked)[1:]:
            row[key] = round(float(stacked[key][augmented].mean()), 4) if n else float("nan")
        rows.append(row)
        tqdm.write(", ".join(f"{k} {v}" for k, v in row.items()))
    args.output.parent.mkdir(parents=True, exist_ok=True)
    pd.DataFrame(rows).to_csv(args.output, index=False, float_format="%.4f")


if __name__ == "__main__":
    main()
