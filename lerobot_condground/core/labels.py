"""Names and encoding of the label features a recorded dataset carries beside cameras and state.

`observation.segmentation`: one label map of the top camera, (H, W) uint8, lossless: 0 background
and robot, 1 target object, 2 target receptacle, 3.. competitors (their classes are in the dataset's
provenance file), 255 synthetic competitors pasted by the copy-paste augmentation.
`observation.phase` (1,) int64: 0 acquire the object, 1 transport and place.
`observation.prompt.object` / `observation.prompt.receptacle`: positionless (64, 64, 3) RGB crops.

The segmentation and the prompts are stored as one PNG per frame (base64 `string` features). As
numeric columns they made every training sample slow: LeRobot fetches whole parquet rows for each
frame of the action chunk, and converting 100 rows of 240x320 label maps took about 3 s per sample
(5 ms as strings). `decode_labels` turns them back into uint8 tensors; the `condground_decode_labels`
processor step does it for act_modified. A stock policy never reads them: they are `observation.*`
strings, which LeRobot's batch conversion keeps and its statistics and normalizer skip.
"""

from __future__ import annotations

import base64

import numpy as np

OBS_SEGMENTATION = "observation.segmentation"
OBS_PHASE = "observation.phase"
OBS_PROMPT_OBJECT = "observation.prompt.object"
OBS_PROMPT_RECEPTACLE = "observation.prompt.receptacle"
LABEL_KEYS = (OBS_SEGMENTATION, OBS_PHASE, OBS_PROMPT_OBJECT, OBS_PROMPT_RECEPTACLE)
# A robot's prompt virtual cameras (`prompt_object` / `prompt_receptacle`, see the ur3e robot) reach a
# policy as these camera keys: they are the prompt crops, never cameras of the policy.
PROMPT_CAMERA_KEYS = {
    "observation.images.prompt_object": OBS_PROMPT_OBJECT,
    "observation.images.prompt_receptacle": OBS_PROMPT_RECEPTACLE,
}
# InstrumentRouting-v0 (labels of `envs/routing_scene.py` in both segmentations): the wrist camera's label
# map, and the side the instrument must go to (0 left, 1 right; what the explicit instruction names).
OBS_SEGMENTATION_WRIST = "observation.segmentation_wrist"
OBS_DESTINATION = "observation.destination"
PNG_LABEL_KEYS = (OBS_SEGMENTATION, OBS_PROMPT_OBJECT, OBS_PROMPT_RECEPTACLE, OBS_SEGMENTATION_WRIST)
PNG_FEATURE = {"dtype": "string", "shape": (1,), "names": None}

BACKGROUND, TARGET_OBJECT, TARGET_RECEPTACLE, FIRST_COMPETITOR = 0, 1, 2, 3
SYNTHETIC_DISTRACTOR = 255
# Side of the square prompt crops, in simulation and on hardware.
PROMPT_SIZE = 64


def encode_png(image: np.ndarray) -> str:
    """uint8 (H, W) label map or (H, W, 3) RGB image -> base64 PNG text (lossless)."""
    import cv2

    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
        raise ValueError(
            f"encode_png takes uint8 (H, W) or (H, W, 3) arrays; got {image.dtype} {image.shape}"
        )
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    ok, png = cv2.imencode(".png", image)
    if not ok:
        raise ValueError(f"PNG encoding failed for an array of shape {image.shape}")
    return base64.b64encode(png.tobytes()).decode("ascii")


def decode_png(text: str) -> np.ndarray:
    """Inverse of `encode_png`."""
    import cv2

    image = cv2.imdecode(np.frombuffer(base64.b64decode(text), np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"not a base64 PNG label image: {text[:40]!r}...")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB) if image.ndim == 3 else image


def decode_labels(data: dict, keys=PNG_LABEL_KEYS) -> dict:
    """A copy of a frame or batch dict with its PNG label features `keys` as uint8 tensors ((H, W) per
    frame, (B, H, W) for a batch's list of strings). Values that are already arrays pass through."""
    import torch

    out = dict(data)
    for camera_key, key in PROMPT_CAMERA_KEYS.items():
        if camera_key in out and key not in out:
            out[key] = out.pop(camera_key)
    for key in keys:
        value = out.get(key)
        if isinstance(value, str):
            out[key] = torch.from_numpy(decode_png(value))
        elif isinstance(value, list | tuple) and value and isinstance(value[0], str):
            out[key] = torch.from_numpy(np.stack([decode_png(v) for v in value]))
    return out


def phase_masks(segmentation, phase):
    """(M_phi, M_d): the phase-relevant entity (object while acquiring, receptacle while placing) and
    the competitors. Works on numpy arrays and torch tensors; `phase` broadcasts over (..., H, W)."""
    relevant_label = TARGET_OBJECT + phase
    if getattr(relevant_label, "ndim", 0):  # one phase per sample: broadcast over the image
        relevant_label = relevant_label.reshape(*relevant_label.shape, 1, 1)
    return segmentation == relevant_label, segmentation >= FIRST_COMPETITOR


def crop_entity(rgb: np.ndarray, mask: np.ndarray, size: int = PROMPT_SIZE, pad: float = 0.15) -> np.ndarray:
    """A square crop around a mask's bounding box, resized to size x size; black if the mask is empty."""
    import cv2

    ys, xs = np.nonzero(mask)
    if len(ys) == 0:
        return np.zeros((size, size, 3), dtype=np.uint8)
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    side = int(max(y1 - y0, x1 - x0) * (1 + 2 * pad)) + 1
    cy, cx = (y0 + y1) // 2, (x0 + x1) // 2
    top, left = cy - side // 2, cx - side // 2
    padded = cv2.copyMakeBorder(rgb, side, side, side, side, cv2.BORDER_REPLICATE)
    crop = padded[top + side : top + 2 * side, left + side : left + 2 * side]
    return cv2.resize(crop, (size, size), interpolation=cv2.INTER_AREA)
