"""Can a detached phase head tell the phase without the gripper? On a checkpoint's own backbone features of the
recorded frames (every --stride-th frame), heads of the checkpoint's phase-head shape are fitted post hoc on four
inputs and scored on held-out episodes (every fifth): the checkpoint's own head (pooled features and the full
robot state, as trained), and refitted heads on the pooled features alone, the flattened feature map alone, and
the flattened map with the arm's joints but not the gripper. With `phase_head_detach` the head shapes nothing
else, so a head refitted on other inputs is the head that training would have found on them.

    python docs/learning-curve/v3/phase_features.py --dataset=DATA_ROOT CHECKPOINT_DIR [...]
"""

import argparse
from pathlib import Path

import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.factory import get_policy_class, make_pre_post_processors

import lerobot_policy_condground  # noqa: F401  (registers act_modified)

parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
parser.add_argument("checkpoints", nargs="+")
parser.add_argument("--dataset", type=Path, required=True)
parser.add_argument("--stride", type=int, default=4)
parser.add_argument("--epochs", type=int, default=60)
args = parser.parse_args()
torch.set_num_threads(1)


def frames(checkpoint: str):
    """(flattened feature maps, state, phase label, episode) of every --stride-th frame, and the policy."""
    cfg = PreTrainedConfig.from_pretrained(checkpoint)
    cfg.pretrained_path, cfg.device = Path(checkpoint), "cpu"
    policy = get_policy_class(cfg.type).from_pretrained(checkpoint, config=cfg).eval()
    preprocessor, _ = make_pre_post_processors(
        policy_cfg=cfg,
        pretrained_path=checkpoint,
        preprocessor_overrides={"device_processor": {"device": "cpu"}},
    )
    dataset = LeRobotDataset(args.dataset.name, root=args.dataset)
    model, camera = policy.acting_model, next(iter(cfg.image_features))
    maps, states, labels, episodes = [], [], [], []
    indices = range(0, len(dataset), args.stride)
    for start in range(0, len(indices), 64):
        batch = torch.utils.data.default_collate([dataset[i] for i in indices[start : start + 64]])
        processed = preprocessor(batch)
        # The backbone's own pre-hook puts the frames in channels-last order; bf16 is lerobot-train's, not the model's.
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=cfg.use_amp):
            maps.append(model.backbone(processed[camera])["feature_map"].float().flatten(2))
        states.append(processed["observation.state"].float())
        labels.append(batch["observation.phase"].reshape(-1).long())
        episodes.append(batch["episode_index"].reshape(-1))
    arm = [
        i
        for i, name in enumerate(dataset.meta.features["observation.state"]["names"])
        if "gripper" not in name
    ]
    return policy, torch.cat(maps), torch.cat(states), arm, torch.cat(labels), torch.cat(episodes)


def fitted_accuracy(x, y, train, width: int) -> float:
    torch.manual_seed(0)
    head = torch.nn.Sequential(torch.nn.Linear(x.shape[1], width), torch.nn.ReLU(), torch.nn.Linear(width, 2))
    optimizer = torch.optim.Adam(head.parameters(), 1e-3)
    xt, yt = x[train], y[train]
    for _ in range(args.epochs):
        order = torch.randperm(len(xt))
        for start in range(0, len(xt), 256):
            b = order[start : start + 256]
            loss = torch.nn.functional.cross_entropy(head(xt[b]), yt[b])
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    with torch.no_grad():
        return (head(x[~train]).argmax(-1) == y[~train]).float().mean().item()


for checkpoint in args.checkpoints:
    policy, maps, state, arm, label, episode = frames(checkpoint)
    held_out = episode % 5 == 0
    pooled, flat = maps.mean(-1), maps.flatten(1)
    with torch.no_grad():
        own = policy.acting_model.phase_head(torch.cat([pooled, state], 1)).argmax(-1)
    width = policy.config.phase_head_dim
    print(f"{checkpoint}: {len(label)} frames, phase 1 on {label.float().mean():.0%}; held-out accuracy:")
    print(
        f"  own head (pooled features + robot state, gripper included): {(own == label)[held_out].float().mean():.3f}"
    )
    print(
        f"  refitted on pooled features:                                  {fitted_accuracy(pooled, label, ~held_out, width):.3f}"
    )
    print(
        f"  refitted on the flattened feature map:                        {fitted_accuracy(flat, label, ~held_out, width):.3f}"
    )
    joints = torch.cat([flat, state[:, arm]], 1)
    print(
        f"  refitted on the flattened map + arm joints (no gripper):      {fitted_accuracy(joints, label, ~held_out, width):.3f}"
    )
