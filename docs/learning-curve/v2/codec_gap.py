"""How far a video dataset's frames are from the renders they were made of (issue 55, suspect 1): the same
demonstrations recorded as video and losslessly (`condground record --dataset.video=false`, same --seed), read
frame by frame, the mean absolute difference per segmentation label and the target cube's median colour.

    python docs/learning-curve/v2/codec_gap.py outputs/levers/data/PickPlaceFixedBin-v0_dart06_200 \\
        outputs/levers/data/PickPlaceFixedBin-v0_png_200 --frames=150
"""

import argparse

import numpy as np
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_condground.core.labels import TARGET_OBJECT, TARGET_RECEPTACLE, decode_labels

parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
parser.add_argument("video_root")
parser.add_argument("lossless_root")
parser.add_argument("--frames", type=int, default=150)
parser.add_argument("--camera", default="observation.images.top")
args = parser.parse_args()
video, lossless = (
    LeRobotDataset("local/codec_gap", root=root) for root in (args.video_root, args.lossless_root)
)
if video.num_frames != lossless.num_frames:
    raise SystemExit(f"the recordings differ in length ({video.num_frames} and {lossless.num_frames} frames)")
picked = np.random.default_rng(0).choice(video.num_frames, min(args.frames, video.num_frames), replace=False)
labels = {"background and robot": 0, "target cube": TARGET_OBJECT, "target receptacle": TARGET_RECEPTACLE}
errors = {name: [] for name in labels}
cube_colour = {"video": [], "lossless": []}
for index in picked:
    a, b = video[int(index)], lossless[int(index)]
    if not torch.allclose(a["observation.state"], b["observation.state"]):
        raise SystemExit(f"frame {index} differs in state: not the same demonstrations")
    seg = decode_labels(b)["observation.segmentation"].numpy()
    coded, raw = (x[args.camera].permute(1, 2, 0).numpy() * 255 for x in (a, b))
    for name, label in labels.items():
        errors[name].append(np.abs(coded - raw)[seg == label])
    if (seg == TARGET_OBJECT).sum() > 5:
        cube_colour["video"].append(np.median(coded[seg == TARGET_OBJECT], 0))
        cube_colour["lossless"].append(np.median(raw[seg == TARGET_OBJECT], 0))
print(f"{len(picked)} frames, mean |video - lossless| (RGB of 255):")
for name, parts in errors.items():
    diff = np.concatenate(parts)
    print(f"  {name}: {len(diff) / len(picked):.1f} px a frame, {np.round(diff.mean(0), 1)}")
for kind, values in cube_colour.items():
    print(f"target cube median colour, {kind}: {np.round(np.median(values, 0), 1)}")
