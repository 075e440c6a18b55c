"""Does a checkpoint read where the cube is from its first frame? Every episode starts at the same home pose,
so the first action chunk can only turn toward the cube if the policy localizes it in the image. Over N
held-out layouts (the sweep's, seeds 1 000 000 on) this prints, per checkpoint, the base joint at the end of
the first chunk against the cube's bearing from the robot's base: their correlation and slope (a policy that
follows the cube: r near 1; one that ignores the image: r near 0, the same chunk in every layout).

    python docs/learning-curve/v3/first_chunk_check.py --task=PickPlaceFixedBin-v0 --layouts=20 CHECKPOINT_DIR [...]

--camera_codec=video shows the policy its frames through the dataset's video codec (`--env.camera_codec`);
--seed_offset=0 checks the first layouts a recording draws (its training demonstrations' own, seed 0 on) instead.
"""

import argparse

import numpy as np
import torch

import lerobot_policy_condground  # noqa: F401  (registers act_modified and the env)
from lerobot_condground.core.training import CPU_FRAME_SIZE
from lerobot_condground.envs.configs import CondGroundEnvConfig
from lerobot_condground.evaluation.checkpoints import load_policy
from lerobot_condground.evaluation.rollout import policy_batch

SEED_OFFSET = 1_000_000

parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
parser.add_argument("checkpoints", nargs="+")
parser.add_argument("--task", default="PickPlaceFixedBin-v0")
parser.add_argument("--layouts", type=int, default=20)
parser.add_argument("--camera_codec", default="none")
parser.add_argument("--seed_offset", type=int, default=SEED_OFFSET)
args = parser.parse_args()
torch.set_num_threads(1)
height, width = CPU_FRAME_SIZE
env_cfg = CondGroundEnvConfig(
    task=args.task,
    condition="clean",
    observation_height=height,
    observation_width=width,
    camera_codec=args.camera_codec,
)
env = env_cfg.make_env()
for checkpoint in args.checkpoints:
    loaded = load_policy(checkpoint, env_cfg)
    bearings, turns = [], []
    for seed in range(args.seed_offset, args.seed_offset + args.layouts):
        obs, _ = env.reset(seed=seed)
        cube = env.unwrapped.entity_pose(1)[0] - env.unwrapped.data.body("ur3e_base").xpos
        loaded.policy.reset()
        with torch.inference_mode():
            chunk = loaded.postprocessor(
                loaded.policy.predict_action_chunk(policy_batch(loaded, [obs], [env]))[0]
            )
        bearings.append(np.arctan2(cube[1], cube[0]))
        turns.append(float(chunk[-1, 0]))
    r = np.corrcoef(bearings, turns)[0, 1]
    slope = np.polyfit(bearings, turns, 1)[0]
    print(
        f"{checkpoint} (camera_codec={args.camera_codec}, layouts {args.seed_offset}+): r = {r:.2f}, slope {slope:.2f} rad/rad, base joint at the chunk's end "
        f"{np.min(turns):+.2f}..{np.max(turns):+.2f} rad for bearings {np.min(bearings):+.2f}..{np.max(bearings):+.2f}"
    )
