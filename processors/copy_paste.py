"""Copy-paste distractor augmentation: synthetic look-alike competitors pasted into camera frames.

Each paste is a competitor of one role (a look-alike of the target object or of the target
receptacle) and one category:

- `same_color`: an augmentation-pool shape tinted so its median color is the target's median visible color;
- `same_shape`: the target's own pixels (cut out with its mask, so it also works on real frames with
  SAM 2 masks), recolored to an augmentation color through their luminance, rotated;
- `neither`: an augmentation-pool shape in an augmentation color.

Every pasted (shape, color) pair thus takes its shape or its color from the augmentation pool and is
never an evaluation competitor. When the target of the paste's role is not visible in a sample,
`same_color` and `same_shape` have nothing to copy and the paste falls back to `neither`.

With `codec=video` the pasted frames go through the dataset's video codec and back, and the decoded pixels
replace the paste and the two pixels around it: the frames a video dataset holds are decoded frames, whose small
objects are blurred and desaturated by 4:2:0 chroma, and a crisp paste beside them is told apart by its
sharpness alone, a cue the evaluation's raw renders turn around (the real target is then the crisp one).

Pasted pixels get `SYNTHETIC_DISTRACTOR` in the segmentation, which is how M_d (labels >= 3) learns
about them; alpha is hard (> 0.5), so the frame changes exactly where the label says so (with `codec=video`, also
within two pixels of it). Pastes never
cover more than `max_occlusion` of the target object's or the target receptacle's visible pixels,
all pastes of a sample together. As a training-only step it acts only when the transition carries an
action and gradients are enabled (LeRobot 0.6.1 has no train/eval flag for processors); `augment`
always acts, for offline use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import torch
import torch.nn.functional as F
from lerobot.configs.types import PipelineFeatureType, PolicyFeature
from lerobot.processor.pipeline import EnvTransition, ProcessorStep, ProcessorStepRegistry, TransitionKey

from lerobot_condground.core.codec import check_camera_codec, video_roundtrip
from lerobot_condground.core.labels import SYNTHETIC_DISTRACTOR, TARGET_OBJECT, TARGET_RECEPTACLE
from lerobot_condground.envs.assets import AUGMENTATION_COLORS, COLORS

CATEGORIES = ("same_color", "same_shape", "neither")
ROLES = ("object", "receptacle")
SAME_COLOR, SAME_SHAPE, NEITHER = range(3)
ROLE_LABELS = (TARGET_OBJECT, TARGET_RECEPTACLE)  # role 0 object, role 1 receptacle
SHAPES_PER_ROLE = 4  # sprites.SPRITE_SHAPES holds this many shapes per role, objects first
CANDIDATES = 4  # positions tried per paste; the one covering the targets least is kept
SCALE_JITTER = 0.1
MAX_COUNT = 16
MAX_SPRITE_SCALE = 4.0
CONFIG_FIELDS = (
    "camera_key",
    "segmentation_key",
    "prob",
    "min_count",
    "max_count",
    "max_occlusion",
    "categories",
    "roles",
    "seed",
    "sprite_scale",
    "placement_box",
    "codec",
    "warmup_steps",
)
# Pixels around a paste that take the codec's output too: 4:2:0 chroma spreads an edge over two of them.
CODEC_MARGIN = 2


def _luminance(rgb: torch.Tensor) -> torch.Tensor:
    return (0.299 * rgb[:, 0] + 0.587 * rgb[:, 1] + 0.114 * rgb[:, 2]).unsqueeze(1)


def _masked_median(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-sample, per-channel median of (B, C, H, W) values under a (B, H, W) mask; NaN where empty."""
    flat = values.flatten(2).masked_fill(~mask.flatten(1).unsqueeze(1), float("nan"))
    return flat.nanmedian(dim=-1).values


def _theta(
    dest: torch.Tensor,
    angle: torch.Tensor,
    scale: torch.Tensor,
    src_center: torch.Tensor,
    height: int,
    width: int,
) -> torch.Tensor:
    """affine_grid matrices (..., 2, 3) pasting a source (same size as the frame) so that its point
    `src_center` lands on `dest` (pixels, x first), rotated by `angle` and scaled by `scale`."""
    half = dest.new_tensor([width / 2, height / 2])
    cos, sin = torch.cos(angle) / scale, torch.sin(angle) / scale
    # Output pixel p maps to source pixel src_center + M (p - dest), M the inverse rotation and scale;
    # conjugated with the pixel <-> normalized map p = half * (n + 1) (align_corners=False).
    lin = torch.stack(
        [torch.stack([cos, sin * height / width], -1), torch.stack([-sin * width / height, cos], -1)], -2
    )
    offset = dest - half
    moved = torch.stack(
        [cos * offset[..., 0] + sin * offset[..., 1], -sin * offset[..., 0] + cos * offset[..., 1]], -1
    )
    trans = (src_center - moved) / half - 1.0
    return torch.cat([lin, trans.unsqueeze(-1)], -1)


def _warp(source: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """grid_sample under affine_grid's convention; the grid is built by broadcasting because
    affine_grid's batched matmul with an inner size of 3 dominated the CPU time."""
    height, width = source.shape[-2:]
    xs = (torch.arange(width, device=source.device, dtype=source.dtype) * 2 + 1) / width - 1
    ys = (torch.arange(height, device=source.device, dtype=source.dtype) * 2 + 1) / height - 1
    t = theta.to(source.dtype).view(-1, 2, 3, 1, 1)
    grid = t[:, :, 0] * xs + (t[:, :, 1] * ys.view(-1, 1) + t[:, :, 2])  # (N, 2, H, W)
    return F.grid_sample(
        source, grid.permute(0, 2, 3, 1), mode="bilinear", padding_mode="zeros", align_corners=False
    )


@dataclass
class CopyPasteParams:
    """What the augmentation pastes, defined once: the step's fields, `condground augment --copy_paste.*`,
    and the defaults of act_modified's `copy_paste_*` fields."""

    camera_key: str = "observation.images.top"
    prob: float = 0.8  # probability that a sample is augmented
    min_count: int = 1
    max_count: int = 4
    max_occlusion: float = 0.1  # of the target object's and of the target receptacle's visible pixels
    categories: list[str] = field(default_factory=lambda: list(CATEGORIES))
    # Whose look-alikes are pasted: the target object's, the target receptacle's, or both (each paste draws one).
    roles: list[str] = field(default_factory=lambda: list(ROLES))
    seed: int = 0
    sprite_scale: float = 1.0
    # Where paste centers may fall, as fractions of the frame (top, left, bottom, right): by default the
    # table's part of the scene camera's view, so pastes rarely float over the background.
    placement_box: list[float] = field(default_factory=lambda: [0.25, 0.05, 0.95, 0.95])
    # none: pastes as drawn; video: pasted frames through the dataset's video codec (see the module docstring).
    codec: str = "none"
    # Training batches over which `prob` ramps up linearly from 0. A backbone trained from scratch has to find the
    # few pixels of the target from the action loss alone, and pastes from the first step drowned that signal on
    # Task 2 (docs/learning-curve/v3); the paper's backbone starts from ImageNet weights.
    warmup_steps: int = 0

    def __post_init__(self):
        _check_key("camera_key", self.camera_key)
        check_camera_codec(self.codec, "codec")
        for name, low, high in (("prob", 0.0, 1.0), ("max_occlusion", 0.0, 1.0)):
            _check_number(name, getattr(self, name), low, high)
        _check_integer("max_count", self.max_count, 1, MAX_COUNT)
        _check_integer("min_count", self.min_count, 0, self.max_count)
        _check_integer("seed", self.seed, 0, 2**63 - 1)
        _check_integer("warmup_steps", self.warmup_steps, 0, 10**9)
        if (
            isinstance(self.sprite_scale, bool)
            or not isinstance(self.sprite_scale, int | float)
            or not (0 < self.sprite_scale <= MAX_SPRITE_SCALE)
        ):
            raise ValueError(
                f"sprite_scale={self.sprite_scale!r} is not allowed; allowed: 0 < sprite_scale <= "
                f"{MAX_SPRITE_SCALE}"
            )
        self.categories = _check_choices("categories", self.categories, CATEGORIES)
        self.roles = _check_choices("roles", self.roles, ROLES)
        self.placement_box = list(self.placement_box)
        box = self.placement_box
        if (
            len(box) != 4
            or any(isinstance(v, bool) or not isinstance(v, int | float) for v in box)
            or not (0 <= box[0] <= box[2] <= 1 and 0 <= box[1] <= box[3] <= 1)
        ):
            raise ValueError(
                f"placement_box={box!r} is not allowed; allowed: [top, left, bottom, right] fractions "
                f"with 0 <= top <= bottom <= 1 and 0 <= left <= right <= 1"
            )


@ProcessorStepRegistry.register(name="condground_copy_paste")
@dataclass
class CopyPasteDistractorStep(CopyPasteParams, ProcessorStep):
    """Pastes synthetic look-alike competitors into one camera and marks them in the segmentation.

    Place it after the device step and before normalization: it expects float frames in [0, 1].
    """

    segmentation_key: str = "observation.segmentation"
    _bank: torch.Tensor | None = field(default=None, init=False, repr=False)
    _canvases: dict = field(default_factory=dict, init=False, repr=False)
    _shading: torch.Tensor | None = field(default=None, init=False, repr=False)
    _generator: torch.Generator = field(init=False, repr=False)
    _batches: int = field(default=0, init=False, repr=False)  # training batches seen, for warmup_steps

    def __post_init__(self):
        super().__post_init__()
        _check_key("segmentation_key", self.segmentation_key)
        self._generator = torch.Generator().manual_seed(self.seed)

    def current_prob(self) -> float:
        """The paste probability of the next training batch (`prob` once `warmup_steps` batches have passed)."""
        if self._batches >= self.warmup_steps:
            return self.prob
        return self.prob * self._batches / self.warmup_steps

    # ------------------------------------------------------------------ ProcessorStep interface
    def __call__(self, transition: EnvTransition) -> EnvTransition:
        # Training batches carry an action and run with gradients; eval-loss batches (no_grad) and
        # rollouts (no action) must see clean frames.
        if transition.get(TransitionKey.ACTION) is None or not torch.is_grad_enabled():
            return transition
        observation = transition.get(TransitionKey.OBSERVATION) or {}
        for key in (self.camera_key, self.segmentation_key):
            if key not in observation:
                raise KeyError(
                    f"condground_copy_paste needs observation key {key!r}; the batch has "
                    f"{sorted(observation)}"
                )
        images, segmentation = self.augment(
            observation[self.camera_key], observation[self.segmentation_key], prob=self.current_prob()
        )
        self._batches += 1
        new = dict(transition)
        new[TransitionKey.OBSERVATION] = {
            **observation,
            self.camera_key: images,
            self.segmentation_key: segmentation,
        }
        return new

    def get_config(self) -> dict[str, Any]:
        config = {name: getattr(self, name) for name in CONFIG_FIELDS}
        config["categories"] = list(self.categories)
        config["roles"] = list(self.roles)
        config["placement_box"] = list(self.placement_box)
        return config

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {
            "sprites": self._sprite_bank().clone(),
            "generator_state": self._generator.get_state(),
            "batches": torch.tensor(self._batches),
        }

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        if "batches" not in state and self.warmup_steps:
            raise ValueError(
                f"condground_copy_paste has warmup_steps={self.warmup_steps} but its saved state has no batch "
                "count (saved before warmup_steps existed); allowed: warmup_steps=0 for such a state"
            )
        self._batches = int(state.get("batches", 0))
        self._bank = state["sprites"].detach().to("cpu", torch.float32).contiguous()
        self._canvases.clear()
        self._shading = None
        self._generator.set_state(state["generator_state"].to("cpu", torch.uint8))

    def transform_features(
        self, features: dict[PipelineFeatureType, dict[str, PolicyFeature]]
    ) -> dict[PipelineFeatureType, dict[str, PolicyFeature]]:
        return features

    # ------------------------------------------------------------------ augmentation
    @torch.no_grad()
    def augment(
        self, images: torch.Tensor, segmentation: torch.Tensor, prob: float | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Pastes distractors into float frames (B, 3, H, W) in [0, 1] with label maps (B, H, W); an
        unbatched (3, H, W) / (H, W) pair is accepted too. Returns new tensors, inputs are untouched.
        `prob` (default: the step's `prob`) is the chance that a sample is augmented."""
        unbatched = images.dim() == 3
        if unbatched:
            images, segmentation = images.unsqueeze(0), segmentation.unsqueeze(0)
        if images.dim() != 4 or images.shape[1] != 3 or not images.is_floating_point():
            raise ValueError(
                f"{self.camera_key} must be float frames (B, 3, H, W) or (3, H, W) in [0, 1]; got "
                f"{images.dtype} {tuple(images.shape)}"
            )
        if segmentation.shape != (images.shape[0], *images.shape[2:]) or segmentation.is_floating_point():
            raise ValueError(
                f"{self.segmentation_key} must be an integer label map {images.shape[:1] + images.shape[2:]}"
                f" matching {self.camera_key}; got {segmentation.dtype} {tuple(segmentation.shape)}"
            )
        out_images, out_seg = self._augment_batch(images, segmentation, self.prob if prob is None else prob)
        if unbatched:
            return out_images[0], out_seg[0]
        return out_images, out_seg

    def _draw(self, batch: int, prob: float) -> dict[str, torch.Tensor]:
        """Every random choice of one call, from the CPU generator: the same seed gives the same pastes
        on any device, and the amount drawn depends on the batch size only."""
        g, slots = self._generator, self.max_count
        chosen = torch.rand(batch, generator=g) < prob
        count = torch.randint(self.min_count, self.max_count + 1, (batch,), generator=g)
        category_ids = torch.tensor([CATEGORIES.index(c) for c in self.categories])
        role_ids = torch.tensor([ROLES.index(r) for r in self.roles])
        return {
            "active": chosen & (torch.arange(slots).unsqueeze(1) < count),  # (slots, B)
            "role": role_ids[torch.randint(0, len(role_ids), (slots, batch), generator=g)],
            "category": category_ids[torch.randint(0, len(category_ids), (slots, batch), generator=g)],
            "shape": torch.randint(0, SHAPES_PER_ROLE, (slots, batch), generator=g),
            "color": torch.randint(0, len(AUGMENTATION_COLORS), (slots, batch), generator=g),
            "position": torch.rand(slots, batch, CANDIDATES, 2, generator=g),
            "angle": torch.rand(slots, batch, generator=g) * 2 * math.pi,
            "scale": 1.0 + SCALE_JITTER * (2 * torch.rand(slots, batch, generator=g) - 1),
        }

    def _augment_batch(self, images: torch.Tensor, segmentation: torch.Tensor, prob: float):
        batch, _, height, width = images.shape
        device = images.device
        draws = {k: v.to(device) for k, v in self._draw(batch, prob).items()}
        frames = images.float()
        out = frames.clone()
        seg = segmentation.clone()
        canvases = self._sprite_canvases(height, width, device)
        palette = torch.tensor([COLORS[c] for c in AUGMENTATION_COLORS], device=device)
        shading_median = self._shading_median(device)  # (sprites,)

        targets = torch.stack([segmentation == label for label in ROLE_LABELS], 1)  # (B, 2, H, W)
        target_pixels = targets.flatten(2).sum(-1)  # (B, 2)
        visible = target_pixels > 0
        luminance = _luminance(frames)
        median_color = torch.stack([_masked_median(frames, targets[:, r]) for r in range(2)], 1)  # (B, 2, 3)
        median_luminance = torch.stack([_masked_median(luminance, targets[:, r])[:, 0] for r in range(2)], 1)
        ys, xs = torch.meshgrid(
            torch.arange(height, device=device) + 0.5, torch.arange(width, device=device) + 0.5, indexing="ij"
        )
        centroid = torch.stack([(targets * xs).flatten(2).sum(-1), (targets * ys).flatten(2).sum(-1)], -1)
        centroid = centroid / target_pixels.clamp(min=1).unsqueeze(-1)  # (B, 2, 2)
        canvas_center = torch.tensor([width / 2, height / 2], device=device)
        covered = torch.zeros_like(targets)
        top, left, bottom, right = self.placement_box
        box_origin, box_size = (
            torch.tensor([left, top], device=device),
            torch.tensor([right - left, bottom - top], device=device),
        )
        frame_size = torch.tensor([width, height], device=device)
        rows = torch.arange(batch, device=device)

        for slot in range(self.max_count):
            active, role = draws["active"][slot], draws["role"][slot]
            if not active.any():
                continue
            category = torch.where(visible[rows, role], draws["category"][slot], NEITHER)
            is_copy = (category == SAME_SHAPE).view(batch, 1, 1, 1)
            color = palette[draws["color"][slot]]  # (B, 3)
            sprite = canvases[role * SHAPES_PER_ROLE + draws["shape"][slot]]  # (B, 2, H, W)
            tint = torch.where(
                (category == SAME_COLOR).unsqueeze(1),
                median_color[rows, role]
                / shading_median[role * SHAPES_PER_ROLE + draws["shape"][slot]].unsqueeze(1),
                color,
            )
            copy_alpha = targets[rows, role].unsqueeze(1).float()
            copy_rgb = (
                luminance
                / median_luminance[rows, role].clamp(min=1e-3).view(batch, 1, 1, 1)
                * color.view(batch, 3, 1, 1)
            )
            alpha = torch.where(is_copy, copy_alpha, sprite[:, 1:])
            # Premultiplied (sprites are stored so), so bilinear sampling does not bleed the surroundings
            # into the paste's edge.
            premultiplied = torch.where(
                is_copy, copy_rgb * copy_alpha, sprite[:, :1] * tint.view(batch, 3, 1, 1)
            )
            source = torch.cat([premultiplied, alpha], 1)
            src_center = torch.where(is_copy.view(batch, 1), centroid[rows, role], canvas_center)

            dest = (box_origin + draws["position"][slot] * box_size) * frame_size  # (B, K, 2) pixels
            angle, scale = draws["angle"][slot], draws["scale"][slot]
            theta = _theta(
                dest,
                angle.unsqueeze(1).expand(-1, CANDIDATES),
                scale.unsqueeze(1).expand(-1, CANDIDATES),
                src_center.unsqueeze(1),
                height,
                width,
            )  # (B, K, 2, 3)
            # Only the samples this slot pastes into are warped (most of the step's time is grid_sample).
            on = active.nonzero().squeeze(1)
            cand = _warp(alpha[on].repeat_interleave(CANDIDATES, 0), theta[on].flatten(0, 1)).view(
                len(on), CANDIDATES, height, width
            )
            cand = cand > 0.5
            # Covered target pixels if this candidate were pasted on top of what is already there.
            cover = (
                (covered[on].unsqueeze(1) | (cand.unsqueeze(2) & targets[on].unsqueeze(1))).flatten(3).sum(-1)
            )  # (n, K, 2)
            fraction = (cover / target_pixels[on].clamp(min=1).unsqueeze(1)).amax(-1)  # (n, K)
            best = fraction.argmin(1)
            picked = torch.arange(len(on), device=device)
            keep = fraction[picked, best] <= self.max_occlusion
            pasted = _warp(source[on], theta[on, best])
            mask = (pasted[:, 3] > 0.5) & keep.view(-1, 1, 1)
            rgb = (pasted[:, :3] / pasted[:, 3:].clamp(min=1e-6)).clamp(0.0, 1.0)
            out[on] = torch.where(mask.unsqueeze(1), rgb, out[on])
            seg[on] = seg[on].masked_fill(mask, SYNTHETIC_DISTRACTOR)
            covered[on] |= mask.unsqueeze(1) & targets[on]
        if self.codec == "video":
            out = self._codec_pastes(out, seg != segmentation)
        return out.to(images.dtype), seg

    @staticmethod
    def _codec_pastes(frames: torch.Tensor, pasted: torch.Tensor) -> torch.Tensor:
        """The pasted frames' codec round trip, kept where a paste lies and CODEC_MARGIN pixels around it."""
        rows = pasted.flatten(1).any(1).nonzero().squeeze(1)
        if not len(rows):
            return frames
        side = 2 * CODEC_MARGIN + 1
        region = F.max_pool2d(pasted[rows].unsqueeze(1).float(), side, stride=1, padding=CODEC_MARGIN) > 0
        raw = (frames[rows].clamp(0, 1) * 255).round().to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()
        decoded = torch.from_numpy(video_roundtrip(raw)).to(frames.device).permute(0, 3, 1, 2).float() / 255
        out = frames.clone()
        out[rows] = torch.where(region, decoded, frames[rows])
        return out

    # ------------------------------------------------------------------ sprites
    def _sprite_bank(self) -> torch.Tensor:
        # Lazy: a step restored from a checkpoint gets its bank from load_state_dict, without MuJoCo.
        if self._bank is None:
            from .sprites import render_sprite_bank

            self._bank = render_sprite_bank()
        return self._bank

    def _shading_median(self, device: torch.device) -> torch.Tensor:
        """Median shading of each sprite under its alpha: what a same-color paste is tinted against."""
        if self._shading is None:
            bank = self._sprite_bank()
            self._shading = _masked_median(bank[:, :1], bank[:, 1] > 0.5)[:, 0]
        return self._shading.to(device)

    def _sprite_canvases(self, height: int, width: int, device: torch.device) -> torch.Tensor:
        """(sprites, 2, H, W): the bank scaled to the frames' pixel size, each sprite centered on a
        frame-sized canvas, so sprites and copied targets are warped by one grid_sample."""
        key = (height, width, str(device))
        if key not in self._canvases:
            from .sprites import BANK_HEIGHT

            bank = self._sprite_bank()
            side = max(1, round(bank.shape[-1] * height / BANK_HEIGHT * self.sprite_scale))
            scaled = F.interpolate(
                bank, size=(side, side), mode="bilinear", antialias=True, align_corners=False
            )
            canvas = torch.zeros(bank.shape[0], 2, height, width)
            # A sprite larger than the frame is cropped around its center.
            ch, cw = min(side, height), min(side, width)
            sy, sx = (side - ch) // 2, (side - cw) // 2
            y0, x0 = (height - ch) // 2, (width - cw) // 2
            canvas[:, :, y0 : y0 + ch, x0 : x0 + cw] = scaled[:, :, sy : sy + ch, sx : sx + cw]
            self._canvases.clear()  # one resolution at a time in practice; do not hoard memory
            self._canvases[key] = canvas.to(device)
        return self._canvases[key]


def _check_choices(name: str, values, allowed: tuple[str, ...]) -> list[str]:
    values = list(values)
    if not values or any(v not in allowed for v in values) or len(set(values)) != len(values):
        raise ValueError(
            f"{name}={values!r} is not allowed; allowed: a non-empty list of distinct values from "
            f"{', '.join(allowed)}"
        )
    return values


def _check_key(name: str, value) -> None:
    if not isinstance(value, str) or not value:
        raise ValueError(f"{name}={value!r} is not allowed; allowed: a non-empty feature key string")


def _check_number(name: str, value, low: float, high: float) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float) or not (low <= value <= high):
        raise ValueError(f"{name}={value!r} is not allowed; allowed: a number in [{low}, {high}]")


def _check_integer(name: str, value, low: int, high: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or not (low <= value <= high):
        raise ValueError(f"{name}={value!r} is not allowed; allowed: an integer in [{low}, {high}]")
