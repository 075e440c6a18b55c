"""Can the policy's own backbone, trained from scratch to do only this, tell the target cube from a look-alike?
(issue 55, suspect 3)

The linear probes of `separability.py` found the red cylinder at chance in the token of every 6000-step policy,
while a classifier on the raw pixels tells it from the cube 80-92 % of the time. This separates the two readings:
the architecture and frame size cannot keep the difference, or imitation never asks for it. The backbone the
CPU configuration trains (torchvision's ResNet-18 with batch norm, no ImageNet weights, cut at `--layer`) gets a
1x1 convolution on its feature map, and both are trained together on one job: tell the token whose cell holds the
cube (label 1) from the one holding a look-alike (label 0); pairs whose two objects share a cell are dropped.
`--train_source` picks the look-alikes it trains on: `scene`, the scored kind itself (`--condition`'s competitor,
rendered); `augmentation_pool`, the same condition's competitors drawn from the copy-paste pool (rendered in 3D,
no shape or colour an evaluation scene holds); `paste_<category>`, one copy-paste paste of that category on a
clean scene, as the copy-paste step draws it in training. It is always scored on `--condition`'s scenes with the
evaluation's competitors: does what the policy could be trained on carry over to what it meets? Training
layouts are seeds 2 000 000 on, scored layouts the sweep's held-out ones (1 000 000 on). Reported per epoch:
held-out token accuracy (chance 50 %) and how often the cube's token outscores the competitor's (the choice a
policy makes).

    python docs/learning-curve/v3/backbone_capacity.py --sizes=96x128 --condition=object_color_1 \\
        --train_source=paste_same_color --output=docs/learning-curve/v3/backbone_capacity.csv

`--camera_codec=video` (the default) sends the frames through the dataset's video codec first, the look of the
frames the policy trains on. What this cannot show: a backbone supervised for the distinction is an upper
bound on what imitation from 200 demonstrations extracts, and the robot at home never hides the objects.
"""

import argparse
import time
from pathlib import Path

import pandas as pd
import torch
import torchvision
from separability import cell, one_paste_each, render
from torch import nn
from torchvision.models._utils import IntermediateLayerGetter
from tqdm import tqdm

from lerobot_condground.core.labels import FIRST_COMPETITOR, TARGET_OBJECT
from lerobot_condground.core.training import CPU_BATCH_SIZE, CPU_POLICY, native_bf16
from lerobot_condground.processors.copy_paste import CATEGORIES

TRAIN_SEED_OFFSET = 2_000_000


def scene_pairs(frames):
    """(rgb, the cube's mask, its object competitor's mask) of rendered scenes."""
    for rgb, seg, table in frames:
        others = [e["label"] for e in table if e["label"] >= FIRST_COMPETITOR and e["role"] == "object"]
        if others:
            yield rgb, seg == TARGET_OBJECT, seg == others[0]


def paste_pairs(frames, category: str, codec: str, wanted: int):
    """(rgb with one object-role paste of the category drawn on it as in training, the cube's mask, the
    paste's mask) of clean scenes."""
    for k, rgb, mask in one_paste_each([(f[0], f[1]) for f in frames], category, codec, wanted):
        yield rgb, frames[k][1] == TARGET_OBJECT, mask


def samples(pairs, grid) -> tuple[torch.Tensor, torch.Tensor]:
    """Images (N, 3, H, W) in [0, 1] and cells (N, 2, 2): the cube's then the look-alike's (row, column); a
    pair whose two objects share a cell, or one hidden, is dropped."""
    images, cells = [], []
    for rgb, target_mask, other_mask in pairs:
        target, other = cell(target_mask, grid), cell(other_mask, grid)
        if target is None or other is None or target == other:
            continue
        images.append(torch.from_numpy(rgb).permute(2, 0, 1).float() / 255)
        cells.append(torch.tensor([target, other]))
    return torch.stack(images), torch.stack(cells)


def training_pairs(args, size):
    if args.train_source.startswith("paste_"):
        clean = render(args.task, "clean", size, args.train_layouts, args.camera_codec, TRAIN_SEED_OFFSET)
        return paste_pairs(
            clean, args.train_source.removeprefix("paste_"), args.copy_paste_codec, args.train_layouts
        )
    pool = "augmentation" if args.train_source == "augmentation_pool" else "eval"
    return scene_pairs(
        render(
            args.task, args.condition, size, args.train_layouts, args.camera_codec, TRAIN_SEED_OFFSET, pool
        )
    )


def backbone(layer: str) -> tuple[nn.Module, int]:
    """The CPU configuration's backbone, as the policy builds it for `backbone_width` 64 (torchvision's ResNet-18)."""
    resnet = torchvision.models.resnet18(weights=CPU_POLICY["pretrained_backbone_weights"])
    channels = getattr(resnet, layer)[-1].conv2.out_channels
    return IntermediateLayerGetter(resnet, return_layers={layer: "feature_map"}), channels


class TokenClassifier(nn.Module):
    def __init__(self, layer: str, mean: torch.Tensor, std: torch.Tensor):
        super().__init__()
        self.backbone, channels = backbone(layer)
        self.head = nn.Conv2d(channels, 1, 1)
        self.register_buffer("mean", mean.view(1, 3, 1, 1))
        self.register_buffer("std", std.view(1, 3, 1, 1))

    def forward(self, images: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
        """Logits (N, 2) of the cube's token and the competitor's."""
        logits = self.head(self.backbone((images - self.mean) / self.std)["feature_map"])[:, 0]
        rows = torch.arange(len(images)).unsqueeze(1)
        return logits[rows, cells[..., 0], cells[..., 1]]


def scores(model: TokenClassifier, images, cells, amp: bool) -> dict[str, float]:
    model.eval()
    with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=amp):
        logits = torch.cat(
            [model(images[k : k + 64], cells[k : k + 64]).float() for k in range(0, len(images), 64)]
        )
    model.train()
    return {
        "token_accuracy": float(((logits[:, 0] > 0).float().mean() + (logits[:, 1] <= 0).float().mean()) / 2),
        "cube_outscores": float((logits[:, 0] > logits[:, 1]).float().mean()),
    }


def run(args, size: tuple[int, int]) -> list[dict]:
    torch.manual_seed(args.seed)
    # A throwaway backbone for the grid's shape, built first so the classifier draws the published runs' weights.
    grid_probe, _ = backbone(args.layer)
    grid = tuple(grid_probe(torch.zeros(1, 3, *size))["feature_map"].shape[2:])
    train = samples(training_pairs(args, size), grid)
    test = samples(
        scene_pairs(render(args.task, args.condition, size, args.test_layouts, args.camera_codec)), grid
    )
    mean, std = train[0].mean((0, 2, 3)), train[0].std((0, 2, 3))
    model = TokenClassifier(args.layer, mean, std)
    optimizer = torch.optim.AdamW(model.parameters(), lr=CPU_POLICY["optimizer_lr"], weight_decay=1e-4)
    amp = native_bf16()
    target = torch.tensor([1.0, 0.0]).expand(CPU_BATCH_SIZE, 2)
    rows, started = [], time.monotonic()
    label = f"{size[0]}x{size[1]}"
    for epoch in tqdm(range(1, args.epochs + 1), desc=label):
        order = torch.randperm(len(train[0]))
        for k in range(0, len(order) - CPU_BATCH_SIZE + 1, CPU_BATCH_SIZE):
            batch = order[k : k + CPU_BATCH_SIZE]
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=amp):
                logits = model(train[0][batch], train[1][batch]).float()
            loss = nn.functional.binary_cross_entropy_with_logits(logits, target)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        result = scores(model, *test, amp) | {f"train_{k}": v for k, v in scores(model, *train, amp).items()}
        rows.append(
            {
                "task": args.task,
                "condition": args.condition,
                "train_source": args.train_source,
                "frame": label,
                "layer": args.layer,
                "grid": f"{grid[0]}x{grid[1]}",
                "camera_codec": args.camera_codec,
                "copy_paste_codec": args.copy_paste_codec if args.train_source.startswith("paste_") else "",
                "seed": args.seed,
                "train_n": len(train[0]),
                "test_n": len(test[0]),
                "epoch": epoch,
                "minutes": (time.monotonic() - started) / 60,
                "bf16": amp,
            }
            | result
        )
        tqdm.write(
            f"{label} epoch {epoch}: held-out token accuracy {result['token_accuracy']:.3f}, cube outscores "
            f"{result['cube_outscores']:.3f} (train {result['train_token_accuracy']:.3f})"
        )
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="PickPlaceFixedBin-v0")
    parser.add_argument("--condition", default="object_color_1")
    parser.add_argument("--sizes", default="96x128,144x192")
    parser.add_argument(
        "--train_source",
        default="scene",
        choices=["scene", "augmentation_pool"] + [f"paste_{c}" for c in CATEGORIES],
        help="what the backbone is trained to tell the cube from (it is always scored on --condition's scenes)",
    )
    parser.add_argument("--layer", default="layer4", choices=["layer3", "layer4"])
    parser.add_argument("--train_layouts", type=int, default=400)
    parser.add_argument("--test_layouts", type=int, default=200)
    parser.add_argument("--epochs", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--camera_codec", default="video", choices=["none", "video"])
    parser.add_argument(
        "--copy_paste_codec",
        default="none",
        choices=["none", "video"],
        help="the pastes' codec, as `--policy.copy_paste_codec` (paste_* sources)",
    )
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = []
    for text in [t for t in args.sizes.split(",") if t]:
        rows += run(args, tuple(int(v) for v in text.split("x")))
    args.output.parent.mkdir(parents=True, exist_ok=True)
    new = pd.DataFrame(rows)
    if args.output.exists():  # runs append: one file for every size, condition and seed
        new = pd.concat([pd.read_csv(args.output), new], ignore_index=True)
    new.to_csv(args.output, index=False, float_format="%.4f")


if __name__ == "__main__":
    main()
