"""Promptable video segmenters: one manual annotation on the first frame, masks on every later frame.

The paper's hardware prompts come from "an initial manual annotation followed by SAM 2 segmentation".
A `Segmenter` is that step behind one small streaming interface:

    masks = segmenter.start(first_frame, {1: Prompt.parse("120,80"), 2: Prompt.parse("10,20,60,90")})
    masks = segmenter.track(next_frame)          # frame by frame, {obj_id: (H, W) bool mask}

Object ids follow the label maps of `lerobot_condground.core.labels`: 1 the target object, 2 the target
receptacle, 3.. competitors the user marked. Frames are (H, W, 3) uint8 RGB.

- `Sam2Segmenter`: SAM 2 (transformers' `Sam2VideoModel`) in streaming mode, for real cameras.
- `ColorSegmenter`: a deterministic color-threshold tracker, for scenes whose entities are uniformly
  colored and unique in color (the simulation's `clean` condition): the reference the tests check
  SAM 2's plumbing against, and a CPU-cheap fallback. It cannot tell same-colored look-alikes apart.
"""

from __future__ import annotations

import logging
import math
import os
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

logger = logging.getLogger(__name__)

DEFAULT_SAM2_MODEL = "facebook/sam2.1-hiera-tiny"
SEGMENTERS = ("sam2", "color")


@dataclass(frozen=True)
class Prompt:
    """A click (x, y) or a box (x0, y0, x1, y1), in pixel coordinates of the annotated frame
    (x to the right, y down; a box's corners are its top-left and bottom-right edges)."""

    coords: tuple[float, ...]

    def __post_init__(self):
        if len(self.coords) not in (2, 4) or not all(math.isfinite(c) for c in self.coords):
            raise ValueError(
                f"A prompt is a point x,y or a box x0,y0,x1,y1 of finite numbers; got {self.coords!r}"
            )
        if self.is_box and not (self.coords[0] < self.coords[2] and self.coords[1] < self.coords[3]):
            raise ValueError(f"Box prompt {self} must have x0 < x1 and y0 < y1")

    @classmethod
    def parse(cls, value) -> Prompt:
        """'120,80' / '10,20,60,90' / a tuple or list of 2 or 4 numbers / a Prompt."""
        if isinstance(value, Prompt):
            return value
        if isinstance(value, str):
            parts = [p.strip() for p in value.strip().strip("()[]").split(",")]
            try:
                coords = tuple(float(p) for p in parts)
            except ValueError:
                coords = ()
            if len(coords) not in (2, 4):
                raise ValueError(
                    f"Cannot read prompt {value!r}; allowed: a point 'x,y' or a box 'x0,y0,x1,y1' in pixels"
                )
            return cls(coords)
        if isinstance(value, list | tuple | np.ndarray):
            return cls(tuple(float(c) for c in value))
        raise ValueError(
            f"Cannot read prompt {value!r}; allowed: a point 'x,y' or a box 'x0,y0,x1,y1' in pixels"
        )

    @property
    def is_box(self) -> bool:
        return len(self.coords) == 4

    @property
    def center(self) -> tuple[float, float]:
        if self.is_box:
            x0, y0, x1, y1 = self.coords
            return (x0 + x1) / 2, (y0 + y1) / 2
        return self.coords[0], self.coords[1]

    def check_inside(self, height: int, width: int) -> None:
        """ValueError when the click or the box leaves a height x width image."""
        if self.is_box:
            x0, y0, x1, y1 = self.coords
            inside = x0 >= 0 and y0 >= 0 and x1 <= width and y1 <= height
        else:
            x, y = self.coords
            inside = 0 <= x < width and 0 <= y < height
        if not inside:
            kind = "box" if self.is_box else "click"
            raise ValueError(
                f"The {kind} {self} is outside the {width}x{height} image (width x height); allowed: "
                f"x in [0, {width}), y in [0, {height})"
            )

    def __str__(self) -> str:
        return ",".join(f"{c:g}" for c in self.coords)


def parse_prompt(value, image_size: tuple[int, int] | None = None) -> Prompt:
    """`Prompt.parse`, checked to lie inside an image of image_size = (height, width) when given."""
    prompt = Prompt.parse(value)
    if image_size is not None:
        prompt.check_inside(*image_size)
    return prompt


def check_frame(frame) -> np.ndarray:
    frame = np.asarray(frame)
    if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
        raise ValueError(f"Frames must be (H, W, 3) uint8 RGB arrays; got {frame.dtype} {frame.shape}")
    return frame


def check_prompts(prompts: Mapping[int, Prompt], height: int, width: int) -> dict[int, Prompt]:
    """Parses and validates every prompt before any model runs."""
    if not prompts:
        raise ValueError(
            "At least one prompt is needed (1 = target object, 2 = target receptacle, 3.. competitors)"
        )
    out = {}
    for obj_id, prompt in prompts.items():
        if isinstance(obj_id, bool) or not isinstance(obj_id, int | np.integer) or not 1 <= obj_id <= 254:
            raise ValueError(
                f"Object id {obj_id!r} is not allowed; allowed: integers 1..254 (1 object, 2 receptacle, "
                f"3.. competitors)"
            )
        prompt = Prompt.parse(prompt)
        prompt.check_inside(height, width)
        out[int(obj_id)] = prompt
    return out


class Segmenter(ABC):
    """Streaming promptable segmentation: `start` on the annotated frame, then `track` on each next one."""

    def __init__(self):
        self._shape: tuple[int, int] | None = None
        self.obj_ids: list[int] = []

    @property
    def started(self) -> bool:
        return self._shape is not None

    def start(self, frame, prompts: Mapping[int, Prompt]) -> dict[int, np.ndarray]:
        """Starts a new video (forgetting any previous one) from prompts on its first frame; returns
        {obj_id: (H, W) bool mask} of that frame."""
        frame = check_frame(frame)
        prompts = check_prompts(prompts, *frame.shape[:2])
        self._shape = frame.shape[:2]
        self.obj_ids = sorted(prompts)
        return self._start(frame, prompts)

    def track(self, frame) -> dict[int, np.ndarray]:
        """The masks of the next frame of the video `start` began."""
        if self._shape is None:
            raise RuntimeError("track() before start(): annotate the first frame with start(frame, prompts)")
        frame = check_frame(frame)
        if frame.shape[:2] != self._shape:
            raise ValueError(
                f"Frame size {frame.shape[1]}x{frame.shape[0]} differs from the annotated frame's "
                f"{self._shape[1]}x{self._shape[0]}; start() again for a new camera"
            )
        return self._track(frame)

    @abstractmethod
    def _start(self, frame: np.ndarray, prompts: dict[int, Prompt]) -> dict[int, np.ndarray]: ...

    @abstractmethod
    def _track(self, frame: np.ndarray) -> dict[int, np.ndarray]: ...


# --------------------------------------------------------------------------------------------- SAM 2
def _torch_dtype(dtype):
    import torch

    if isinstance(dtype, torch.dtype):
        return dtype
    allowed = {"float32": torch.float32, "float16": torch.float16, "bfloat16": torch.bfloat16}
    if dtype not in allowed:
        raise ValueError(f"Unknown dtype {dtype!r}; allowed: {', '.join(allowed)}")
    return allowed[dtype]


def _looks_like_path(model_id: str) -> bool:
    # Hub ids are "owner/name": anything else with a slash, or starting like a path, is a directory.
    return (
        model_id.startswith((".", "/", "~"))
        or model_id.count("/") > 1
        or Path(model_id).expanduser().exists()
    )


@dataclass
class Sam2Config:
    # Hub id (from the local Hugging Face cache when offline) or a directory written by save_pretrained.
    model_id: str = DEFAULT_SAM2_MODEL
    device: str = "cpu"
    # float32, bfloat16 or float16 (the last two for GPUs).
    dtype: str = "float32"
    # Mask logit threshold.
    mask_threshold: float = 0.0


class Sam2Segmenter(Segmenter):
    """SAM 2 video segmentation (transformers' `Sam2VideoModel` + `Sam2VideoProcessor`), streamed one
    frame at a time: the prompts condition the first frame, SAM 2's memory bank carries the objects on.

    `model_id`: a Hugging Face hub id (weights from the local cache when offline) or a local directory
    written by `save_pretrained` (config.json, model.safetensors, processor files)."""

    def __init__(self, config: Sam2Config | None = None, **overrides):
        super().__init__()
        import torch

        config = replace(config or Sam2Config(), **overrides)
        self.model_id = str(config.model_id)
        self.device = torch.device(config.device)
        self.dtype = _torch_dtype(config.dtype)
        self.mask_threshold = config.mask_threshold
        self.model, self.processor = self._load()
        self._session = None
        self._frame_idx = -1
        # SAM 2 reads back at most this many past frames (its memory bank and its object pointers):
        # older per-frame state is dropped so that a long episode does not grow memory without bound.
        self._history = (
            max(self.model.config.num_maskmem, self.model.config.max_object_pointers_in_encoder) + 1
        )

    def _load(self):
        from transformers import Sam2VideoModel, Sam2VideoProcessor

        model_id = self.model_id
        path = Path(model_id).expanduser()
        if _looks_like_path(model_id) and not path.is_dir():
            raise FileNotFoundError(
                f"--sam2.model_id={model_id!r}: no such directory; allowed: a directory written "
                f"by save_pretrained (config.json, model.safetensors, processor files) or a "
                f"hub id such as {DEFAULT_SAM2_MODEL}"
            )
        source = str(path) if path.is_dir() else model_id
        try:
            model = Sam2VideoModel.from_pretrained(source, dtype=self.dtype)
            processor = Sam2VideoProcessor.from_pretrained(source)
        except OSError as err:  # not cached and no network, unknown repo, or an incomplete directory
            offline = os.environ.get("HF_HUB_OFFLINE", "0").lower() in ("1", "true", "yes")
            if path.is_dir():
                raise FileNotFoundError(
                    f"{path} does not hold a SAM 2 video model and its processor ({err}); "
                    f"allowed: a directory written by Sam2VideoModel.save_pretrained and "
                    f"Sam2VideoProcessor.save_pretrained"
                ) from None
            from huggingface_hub.constants import HF_HUB_CACHE

            raise FileNotFoundError(
                f"The SAM 2 weights {model_id!r} are not available locally (not in the Hugging Face cache "
                f"{HF_HUB_CACHE}{', and HF_HUB_OFFLINE=1 forbids downloading' if offline else ''}). Provide them: "
                f"on a machine with internet run `hf download {model_id}` (then copy its cache here, or unset "
                f"HF_HUB_OFFLINE), or pass --sam2.model_id=/path/to/a/directory holding the model and processor "
                f"saved with save_pretrained"
            ) from None
        model.to(self.device).eval()
        return model, processor

    def _start(self, frame, prompts):
        self._session = self.processor.init_video_session(inference_device=self.device, dtype=self.dtype)
        self._frame_idx = -1
        return self._step(frame, prompts)

    def _track(self, frame):
        return self._step(frame, None)

    def _step(self, frame: np.ndarray, prompts: dict[int, Prompt] | None) -> dict[int, np.ndarray]:
        import torch

        self._frame_idx += 1
        t, session = self._frame_idx, self._session
        inputs = self.processor(images=frame, device=self.device, return_tensors="pt")
        if prompts is not None:
            size = inputs.original_sizes[0]
            for obj_id, prompt in prompts.items():
                if prompt.is_box:
                    kwargs = {"input_boxes": [[list(prompt.coords)]]}
                else:
                    kwargs = {"input_points": [[[list(prompt.coords)]]], "input_labels": [[[1]]]}
                self.processor.add_inputs_to_inference_session(
                    session, frame_idx=t, obj_ids=obj_id, original_size=size, **kwargs
                )
            # Each add_inputs call replaces the session's list of objects with new inputs by its own
            # ids; points and boxes need separate calls, so the full list is restored here.
            session.obj_with_new_inputs = list(prompts)
        with torch.inference_mode():
            out = self.model(
                inference_session=session, frame=inputs.pixel_values[0].to(self.dtype), frame_idx=t
            )
        masks = self.processor.post_process_masks(
            [out.pred_masks.float()], inputs.original_sizes, mask_threshold=self.mask_threshold, binarize=True
        )[0]
        result = {
            int(obj_id): masks[i, 0].cpu().numpy().astype(bool) for i, obj_id in enumerate(out.object_ids)
        }
        self._forget_old_frames(t)
        return result

    def _forget_old_frames(self, t: int) -> None:
        session = self._session
        session.processed_frames.pop(t - 1, None)  # the preprocessed frame is only read while it is current
        old = t - self._history
        if old < 0:
            return
        for outputs in session.output_dict_per_obj.values():
            outputs["non_cond_frame_outputs"].pop(old, None)  # the annotated frame's outputs are kept
        for tracked in session.frames_tracked_per_obj.values():
            tracked.pop(old, None)


# --------------------------------------------------------------------------------------------- color
@dataclass
class _ColorTrack:
    reference: np.ndarray  # HSV (hue mode) or RGB (rgb mode) of the prompt
    use_hue: bool
    centroid: tuple[float, float]  # (x, y) of the last mask
    min_area: int


@dataclass
class ColorConfig:
    """`ColorSegmenter`'s thresholds (its docstring says what each does)."""

    hue_tol: float = 3.0
    sat_ratio: float = 0.35
    value_ratio: float = 0.25
    min_saturation: float = 60.0
    rgb_tol: float = 40.0
    snap_px: int = 5
    max_jump: float = 0.25
    min_area_ratio: float = 0.05
    fill_holes: bool = True


class ColorSegmenter(Segmenter):
    """Color-threshold segmentation and tracking.

    The prompt pixel's color (a box's: its centre's), as the median of its 3x3 neighbourhood, defines a
    band: for saturated colors a hue band (`hue_tol`, OpenCV hue units 0..180) with enough saturation
    (`sat_ratio` of the reference's) and brightness (`value_ratio` of the reference's, shadows
    included); for grays an RGB distance (`rgb_tol`). The mask is the in-band connected component under
    the click (or the nearest one within `snap_px`); for a box, the largest in-band component inside
    the box. Holes inside the component are filled (a receptacle's shaded floor, or the object lying in
    it: the label map paints the object over the receptacle anyway). Tracking takes, per frame, the
    in-band component nearest the previous centroid, at most `max_jump` of the image diagonal away and
    at least `min_area_ratio` of the annotated mask's area; when none qualifies (occluded) the mask is
    empty and the last centroid kept.

    The default hue tolerance is tight because in the simulation the UR3e's blue joints are only
    4 hue units from the blue receptacle; real cameras (lighting, white balance) need 8-12.
    """

    def __init__(self, config: ColorConfig | None = None, **overrides):
        super().__init__()
        self.config = replace(config or ColorConfig(), **overrides)
        self._tracks: dict[int, _ColorTrack] = {}

    # -- colors
    @staticmethod
    def _hsv(frame: np.ndarray) -> np.ndarray:
        import cv2

        return cv2.cvtColor(frame, cv2.COLOR_RGB2HSV)

    def _reference(self, frame, hsv, x: int, y: int) -> tuple[np.ndarray, bool]:
        y0, y1, x0, x1 = max(y - 1, 0), y + 2, max(x - 1, 0), x + 2
        ref_hsv = np.median(hsv[y0:y1, x0:x1].reshape(-1, 3), axis=0)
        # Hue is meaningless for grays and near-blacks: those are matched by RGB distance.
        use_hue = ref_hsv[1] >= self.config.min_saturation and ref_hsv[2] >= self.config.min_saturation
        if use_hue:
            # The median of a hue window that straddles red's wrap-around (0/180) is wrong: take the
            # clicked pixel's own hue then.
            ref_hsv[0] = hsv[y, x, 0]
            return ref_hsv, True
        return np.median(frame[y0:y1, x0:x1].reshape(-1, 3), axis=0), False

    def _band(self, frame, hsv, track_ref: np.ndarray, use_hue: bool) -> np.ndarray:
        if use_hue:
            h = hsv[..., 0].astype(np.int16)
            dh = np.abs(h - int(round(track_ref[0])))
            dh = np.minimum(dh, 180 - dh)
            return (
                (dh <= self.config.hue_tol)
                & (hsv[..., 1] >= self.config.sat_ratio * track_ref[1])
                & (hsv[..., 2] >= self.config.value_ratio * track_ref[2])
            )
        diff = frame.astype(np.float32) - track_ref.astype(np.float32)
        return np.sqrt((diff * diff).sum(-1)) <= self.config.rgb_tol

    # -- components
    def _component_mask(self, labels: np.ndarray, index: int) -> np.ndarray:
        import cv2

        mask = labels == index
        if self.config.fill_holes:
            contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
            filled = np.zeros(mask.shape, np.uint8)
            cv2.drawContours(filled, contours, -1, 1, thickness=cv2.FILLED)
            mask = filled.astype(bool)
        return mask

    def _start(self, frame, prompts):
        import cv2

        hsv = self._hsv(frame)
        self._tracks = {}
        masks = {}
        for obj_id, prompt in prompts.items():
            cx, cy = prompt.center
            x, y = min(int(cx), frame.shape[1] - 1), min(int(cy), frame.shape[0] - 1)
            ref, use_hue = self._reference(frame, hsv, x, y)
            band = self._band(frame, hsv, ref, use_hue)
            n, labels, stats, centroids = cv2.connectedComponentsWithStats(
                band.astype(np.uint8), connectivity=4
            )
            index = 0
            if prompt.is_box:
                x0, y0, x1, y1 = (
                    int(math.floor(prompt.coords[0])),
                    int(math.floor(prompt.coords[1])),
                    int(math.ceil(prompt.coords[2])),
                    int(math.ceil(prompt.coords[3])),
                )
                inside = np.bincount(labels[y0:y1, x0:x1].ravel(), minlength=n)
                inside[0] = 0
                index = int(inside.argmax()) if inside.max() > 0 else 0
            elif labels[y, x]:
                index = int(labels[y, x])
            else:
                ys, xs = np.nonzero(labels)
                if len(ys):
                    d2 = (xs - x) ** 2 + (ys - y) ** 2
                    nearest = int(d2.argmin())
                    if d2[nearest] <= self.config.snap_px**2:
                        index = int(labels[ys[nearest], xs[nearest]])
            if index == 0:
                logger.warning(
                    "Prompt %s of object %d matches no region of its color; its mask starts empty",
                    prompt,
                    obj_id,
                )
                mask = np.zeros(frame.shape[:2], bool)
                centroid, area = (cx, cy), 1
            else:
                mask = self._component_mask(labels, index)
                centroid, area = tuple(centroids[index]), int(stats[index, cv2.CC_STAT_AREA])
            self._tracks[obj_id] = _ColorTrack(
                ref, use_hue, centroid, max(1, int(self.config.min_area_ratio * area))
            )
            masks[obj_id] = mask
        return masks

    def _track(self, frame):
        import cv2

        hsv = self._hsv(frame)
        max_jump = self.config.max_jump * math.hypot(*frame.shape[:2])
        masks = {}
        for obj_id, track in self._tracks.items():
            band = self._band(frame, hsv, track.reference, track.use_hue)
            n, labels, stats, centroids = cv2.connectedComponentsWithStats(
                band.astype(np.uint8), connectivity=4
            )
            best, best_d = 0, max_jump
            for i in range(1, n):
                if stats[i, cv2.CC_STAT_AREA] < track.min_area:
                    continue
                d = math.hypot(centroids[i][0] - track.centroid[0], centroids[i][1] - track.centroid[1])
                if d <= best_d:
                    best, best_d = i, d
            if best:
                masks[obj_id] = self._component_mask(labels, best)
                track.centroid = tuple(centroids[best])
            else:
                masks[obj_id] = np.zeros(frame.shape[:2], bool)
        return masks


def save_random_sam2(path, size: str = "small", seed: int = 0) -> Path:
    """A SAM 2 video model with RANDOM weights and its processor, saved with `save_pretrained` like a
    downloaded checkpoint, so `Sam2Segmenter(model_id=path)` loads it the real way. It segments nothing
    meaningful: it exercises the code path and times it.

    size "tiny": transformers' default `Sam2VideoConfig`, which is sam2.1-hiera-tiny's architecture
    (Hiera 96-dim, blocks 1-2-7-2, 1024x1024 input, 38.96 M parameters), built without a download.
    size "small": a 2.3 M-parameter model at 256x256 input, for fast tests."""
    import torch
    from transformers import (
        Sam2ImageProcessor,
        Sam2VideoConfig,
        Sam2VideoMaskDecoderConfig,
        Sam2VideoModel,
        Sam2VideoProcessor,
    )
    from transformers.models.sam2_video.video_processing_sam2_video import Sam2VideoVideoProcessor

    if size == "tiny":
        config, side = Sam2VideoConfig(), 1024
    elif size == "small":
        side, f = 256, 64  # input side and the first backbone level's feature side (stride 4)
        config = Sam2VideoConfig(
            vision_config={
                "backbone_config": {
                    "image_size": [side, side],
                    "hidden_size": 32,
                    "embed_dim_per_stage": [32, 64, 128, 256],
                    "num_attention_heads_per_stage": [1, 1, 2, 2],
                    "blocks_per_stage": [1, 1, 2, 1],
                    # A global-attention block must not open a stage (Hiera pools there): block 3 is
                    # the second of stage 3.
                    "global_attention_blocks": [3],
                    "window_size_per_stage": [8, 4, 8, 4],
                },
                "backbone_channel_list": [256, 128, 64, 32],
                "backbone_feature_sizes": [[f, f], [f // 2, f // 2], [f // 4, f // 4]],
                "fpn_hidden_size": 128,
            },
            prompt_encoder_config={"image_size": side, "hidden_size": 128},
            # transformers 5.5.4 builds a mask decoder config given as a dict with the prompt encoder's
            # class, which then lacks the decoder's fields: pass the instance.
            mask_decoder_config=Sam2VideoMaskDecoderConfig(
                hidden_size=128, mlp_dim=256, iou_head_hidden_dim=64
            ),
            image_size=side,
            memory_attention_hidden_size=128,
            memory_attention_num_layers=1,
            memory_attention_feed_forward_hidden_size=256,
            memory_attention_rope_feat_sizes=[side // 16, side // 16],
            # The memory is 64 channels wide: the memory attention's key projection hard-codes it.
            memory_encoder_hidden_size=128,
            memory_encoder_output_channels=64,
            mask_downsampler_embed_dim=128,
            memory_fuser_embed_dim=128,
            memory_fuser_intermediate_dim=256,
            memory_fuser_num_layers=1,
        )
    else:
        raise ValueError(f"Unknown random SAM 2 size {size!r}; allowed: small, tiny")
    torch.manual_seed(seed)
    model = Sam2VideoModel(config).eval()
    processor = Sam2VideoProcessor(
        image_processor=Sam2ImageProcessor(
            size={"height": side, "width": side}, mask_size={"height": side // 4, "width": side // 4}
        ),
        video_processor=Sam2VideoVideoProcessor(size={"height": side, "width": side}),
        target_size=side,
    )
    path = Path(path)
    model.save_pretrained(path)
    processor.save_pretrained(path)
    return path


def make_segmenter(name: str, **kwargs) -> Segmenter:
    """`name`: "sam2" (fields of `Sam2Config`) or "color" (fields of `ColorConfig`)."""
    if name == "sam2":
        return Sam2Segmenter(**kwargs)
    if name == "color":
        return ColorSegmenter(**kwargs)
    raise ValueError(f"Unknown segmenter {name!r}; allowed: {', '.join(SEGMENTERS)}")
