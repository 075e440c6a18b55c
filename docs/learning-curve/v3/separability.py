"""Can the target object be told from its look-alikes at a frame size? (issue 55, suspect 3)

For every frame size given, N held-out layouts of a task are rendered at their first frame (the robot at
home, unoccluded objects). From each, a square patch centred on the target cube is cut, and one on each kind
of look-alike: the evaluation's competitors (`object_color`: a same-colour other shape, the red cylinder
with the fixed assets; `object_shape`: a cube of another colour; `object_neither`) and the copy-paste
augmentation's object-role pastes of each category (`same_color`, `same_shape`, `neither`, one paste a
frame). A pixel-level classifier (logistic regression on the patch's standardized RGB, and an RBF support
vector machine) tells the target from each kind, 5-fold cross-validated; chance is 50 %. The patch covers
the same 11 cm of table at every size, so only the pixel count changes.

    python docs/learning-curve/v3/separability.py --task=PickPlaceFixedBin-v0 --layouts=150 --sizes=96x128,144x192,240x320 \
        --output=docs/learning-curve/v3/separability.csv

With `--camera_codec=video` every frame first goes through the dataset's video codec as one stream (the
training frames' look; the pastes are then drawn on decoded frames, as in training), and
`--copy_paste_codec=video` sends the pastes through it too. `--checkpoints` repeats the competitor test on
each policy's own backbone: the feature vector of the image token whose cell holds the object (what the
transformer reads), at the checkpoint's 96x128 frames (`--sizes=` skips the pixel test); `--paste_tokens`
adds the pastes' tokens (the look-alikes copy-paste trains on, drawn on the clean frames).

A kind the classifier cannot tell from the target at a frame size is a look-alike the policy cannot tell
either from that frame alone (a classifier on the raw patch is a rough bound on what is in the pixels, not
on what a from-scratch backbone learns to use).
"""

import argparse
import functools
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from sklearn.linear_model import LogisticRegression
from sklearn.model_selection import StratifiedKFold, cross_val_score
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import StandardScaler
from sklearn.svm import SVC
from tqdm import tqdm

from lerobot_condground.core.codec import video_roundtrip
from lerobot_condground.core.labels import FIRST_COMPETITOR, SYNTHETIC_DISTRACTOR, TARGET_OBJECT
from lerobot_condground.envs.pickplace_env import PickPlaceEnv
from lerobot_condground.processors.copy_paste import CATEGORIES, CopyPasteDistractorStep

SEED_OFFSET = 1_000_000  # the sweep's held-out layouts
PATCH_CM = 11.0  # table covered by a patch
CM_PER_PIXEL_AT_96 = 0.9  # the scene camera at 96 rows (the cube's 4.1 cm side is 4-5 px across)
MIN_PIXELS = 3  # an entity with fewer visible pixels at 96 rows is skipped (hidden under the arm)


def patch(rgb: np.ndarray, mask: np.ndarray, side: int) -> np.ndarray | None:
    ys, xs = np.nonzero(mask)
    if len(ys) * (96 / rgb.shape[0]) ** 2 < MIN_PIXELS:
        return None
    cy, cx = int(round(ys.mean())), int(round(xs.mean()))
    padded = np.pad(rgb, ((side, side), (side, side), (0, 0)), mode="edge")
    top, left = cy + side - side // 2, cx + side - side // 2
    return padded[top : top + side, left : left + side].astype(np.float32) / 255.0


def render(
    task: str,
    condition: str,
    size: tuple[int, int],
    layouts: int,
    codec: str = "none",
    start: int = SEED_OFFSET,
    competitor_pool: str = "eval",
):
    """(rgb, segmentation, entity table) of each layout's first frame (layout seeds from `start`, competitors
    from `competitor_pool`); with codec=video the frames go through the dataset's video codec as one stream, as
    a recording's frames do (inter-coded)."""
    env = PickPlaceEnv(
        task=task,
        condition=condition,
        observation_height=size[0],
        observation_width=size[1],
        segmentation=True,
        competitor_pool=competitor_pool,
    )
    frames = []
    for seed in range(start, start + layouts):
        obs, _ = env.reset(seed=seed)
        frames.append((obs["pixels"]["top"], obs["segmentation"], env.entity_table()))
    env.close()
    if codec == "video":
        decoded = video_roundtrip(np.stack([f[0] for f in frames]))
        frames = [(rgb, seg, table) for rgb, (_, seg, table) in zip(decoded, frames, strict=True)]
    return frames


def backbone_tokens(checkpoint: str, task: str, condition: str, layouts: int, paste_categories=()):
    """[(feature map (C, h, w) of the policy's backbone, segmentation, entity table)] of each layout's first
    frame, the frame going through the checkpoint's own preprocessing as in lerobot-eval. With paste
    categories (a clean condition), the second item {paste_<category>: [(feature map, paste mask)]} holds the
    same frames with one object-role paste of that category each, drawn on the render before preprocessing as in
    training."""
    from lerobot_condground.envs.configs import CondGroundEnvConfig
    from lerobot_condground.evaluation.checkpoints import load_policy
    from lerobot_condground.evaluation.rollout import policy_batch

    env_cfg = CondGroundEnvConfig(
        task=task, condition=condition, observation_height=96, observation_width=128
    )
    env = env_cfg.make_env()
    loaded = load_policy(checkpoint, env_cfg)
    loaded.policy.eval()

    def features(obs) -> np.ndarray:
        batch = policy_batch(loaded, [obs], [env])
        with torch.inference_mode():
            return (
                loaded.policy.model.backbone(batch["observation.images.top"])["feature_map"][0]
                .float()
                .numpy()
            )

    out, observations = [], []
    for seed in range(SEED_OFFSET, SEED_OFFSET + layouts):
        obs, _ = env.reset(seed=seed)
        observations.append(obs)
        out.append((features(obs), env.unwrapped.render_segmentation(), env.unwrapped.entity_table()))
    pasted = {}
    for category in paste_categories:
        frames = [(o["pixels"]["top"], seg) for o, (_, seg, _) in zip(observations, out, strict=True)]
        pasted[f"paste_{category}"] = [
            (features({**observations[k], "pixels": {**observations[k]["pixels"], "top": rgb}}), mask)
            for k, rgb, mask in one_paste_each(frames, category, "none", wanted=layouts)
        ]
    env.close()
    return out, pasted


def cell(mask: np.ndarray, grid: tuple[int, int]) -> tuple[int, int] | None:
    """The (row, column) of the grid cell holding the mask's centroid; None for an object too small to see."""
    ys, xs = np.nonzero(mask)
    if len(ys) * (96 / mask.shape[0]) ** 2 < MIN_PIXELS:
        return None
    return int(ys.mean() * grid[0] / mask.shape[0]), int(xs.mean() * grid[1] / mask.shape[1])


def token(features: np.ndarray, mask: np.ndarray) -> np.ndarray | None:
    """The feature vector of the token whose cell holds the mask's centroid."""
    where = cell(mask, features.shape[1:])
    return None if where is None else features[:, where[0], where[1]]


def score(target: list[np.ndarray], other: list[np.ndarray], seed: int) -> dict[str, float]:
    n = min(len(target), len(other))
    x = np.stack([p.reshape(-1) for p in target[:n] + other[:n]])
    y = np.r_[np.ones(n), np.zeros(n)]
    folds = StratifiedKFold(5, shuffle=True, random_state=seed)
    out = {"n": n}
    for name, model in (
        ("logistic", LogisticRegression(C=0.1, max_iter=2000)),
        ("svm_rbf", SVC(C=10.0, gamma="scale")),
    ):
        out[name] = float(cross_val_score(make_pipeline(StandardScaler(), model), x, y, cv=folds).mean())
    return out


def competitors(frames, cut) -> tuple[list[np.ndarray], dict[str, list[np.ndarray]]]:
    """The target's samples and each competitor kind's, cut from (image or features, segmentation, table)."""
    targets, kinds = [], {}
    for match, scenes in frames.items():
        for image, seg, table in scenes:
            p = cut(image, seg == TARGET_OBJECT)
            if p is not None and match == "color":  # the target's samples once, from the first scenes
                targets.append(p)
            for entity in table:
                if entity["label"] >= FIRST_COMPETITOR and entity["role"] == "object":
                    q = cut(image, seg == entity["label"])
                    if q is not None:
                        kinds.setdefault(f"competitor_{match}", []).append(q)
    return targets, kinds


def one_paste_each(frames, category: str, codec: str, wanted: int):
    """(layout index, rgb with one object-role paste of the category, the paste's mask) from (rgb, segmentation)
    first frames, until `wanted` (a receptacle-role paste is several times the cube's area and is dropped)."""
    images = torch.from_numpy(np.stack([f[0] for f in frames])).permute(0, 3, 1, 2).float() / 255
    seg = torch.from_numpy(np.stack([f[1] for f in frames]))
    cube_area = (seg == TARGET_OBJECT).flatten(1).sum(1).float().median().item()
    found = 0
    for seed in range(20):
        step = CopyPasteDistractorStep(
            prob=1.0, min_count=1, max_count=1, categories=[category], seed=seed, codec=codec
        )
        pasted, labels = step.augment(images, seg)
        for k in range(len(frames)):
            mask = (labels[k] == SYNTHETIC_DISTRACTOR).numpy()
            # visible enough to cut (`patch`, `token`) and no larger than an object
            if mask.sum() * (96 / mask.shape[0]) ** 2 >= MIN_PIXELS and mask.sum() < 2.5 * cube_area:
                found += 1
                yield k, (pasted[k].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8), mask
                if found >= wanted:
                    return


def pastes(args, size, side: int, wanted: int) -> dict[str, list[np.ndarray]]:
    """Patches around object-role pastes of each category on the clean first frames, one a frame."""
    clean = [(rgb, seg) for rgb, seg, _ in render(args.task, "clean", size, args.layouts, args.camera_codec)]
    kinds = {}
    for category in CATEGORIES:
        kinds[f"paste_{category}"] = [
            patch(rgb, mask, side)
            for _, rgb, mask in one_paste_each(clean, category, args.copy_paste_codec, wanted)
        ]
    return kinds


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="PickPlaceFixedBin-v0")
    parser.add_argument("--layouts", type=int, default=150)
    parser.add_argument("--sizes", default="96x128,144x192,240x320")
    parser.add_argument(
        "--camera_codec", default="none", help="none | video: frames as a video dataset holds them"
    )
    parser.add_argument(
        "--copy_paste_codec", default="none", help="none | video: the copy-paste step's codec"
    )
    parser.add_argument(
        "--checkpoints", nargs="*", default=[], help="also probe these policies' backbone tokens"
    )
    parser.add_argument(
        "--paste_tokens", action="store_true", help="with --checkpoints: also the pastes' tokens"
    )
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = []
    base = {"task": args.task, "camera_codec": args.camera_codec, "copy_paste_codec": args.copy_paste_codec}

    def add(frame: str, source: str, cut: str, targets, kinds) -> None:
        for kind, samples in kinds.items():
            result = score(targets, samples, seed=0)
            rows.append(base | {"frame": frame, "source": source, "sample": cut, "kind": kind} | result)
            tqdm.write(
                f"{frame} {source} {kind:>26}: n {result['n']:3d}, logistic {result['logistic']:.3f}, "
                f"svm {result['svm_rbf']:.3f}"
            )

    matches = ("color", "shape", "neither")
    for text in tqdm([t for t in args.sizes.split(",") if t], desc="frame sizes"):
        size = tuple(int(v) for v in text.split("x"))
        side = max(3, round(PATCH_CM / CM_PER_PIXEL_AT_96 * size[0] / 96))
        frames = {
            m: render(args.task, f"object_{m}_1", size, args.layouts, args.camera_codec) for m in matches
        }
        targets, kinds = competitors(frames, functools.partial(patch, side=side))
        add(text, "pixels", f"patch_{side}px", targets, kinds | pastes(args, size, side, len(targets)))
    for checkpoint in args.checkpoints:
        frames = {
            m: backbone_tokens(checkpoint, args.task, f"object_{m}_1", args.layouts)[0] for m in matches
        }
        targets, kinds = competitors(frames, token)
        if args.paste_tokens:
            _, pasted = backbone_tokens(checkpoint, args.task, "clean", args.layouts, CATEGORIES)
            for kind, samples in pasted.items():
                kinds[kind] = [token(f, mask) for f, mask in samples]
        add("96x128", checkpoint, "backbone_token", targets, kinds)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    pd.DataFrame(rows).to_csv(args.output, index=False, float_format="%.4f")


if __name__ == "__main__":
    main()
