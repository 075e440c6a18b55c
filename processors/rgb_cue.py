"""`condground_rgb_cue`: draws the expected cue, a highlight of the correct destination, into the camera
frames (InstrumentRouting-v0; the paper's prompt-trained π0.5 variant).

The destination comes from each camera's segmentation (label 2 of `envs/routing_scene.py`): recorded
datasets carry it (`--dataset.labels=true`, the default), and the env sends it at evaluation with
`--env.cue=true`; `--env.cue=false` sends empty masks, so the same checkpoint is evaluated without its cue
and nothing is highlighted. A frame without masks is an error, never a frame silently left uncued.
Place the step before the policy's own image steps (resizing, normalization): it works on frames in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from lerobot.configs.types import PipelineFeatureType, PolicyFeature
from lerobot.processor.pipeline import ObservationProcessorStep, ProcessorStepRegistry

from lerobot_condground.core.labels import OBS_SEGMENTATION, OBS_SEGMENTATION_WRIST, decode_labels
from lerobot_condground.core.routing import DESTINATION


@ProcessorStepRegistry.register(name="condground_rgb_cue")
@dataclass
class RgbCueStep(ObservationProcessorStep):
    # Off: frames pass unchanged (a pipeline saved with the step, evaluated without it).
    enabled: bool = True
    # Camera key -> the segmentation key its destination mask comes from.
    cameras: dict[str, str] = field(
        default_factory=lambda: {
            "observation.images.top": OBS_SEGMENTATION,
            "observation.images.wrist": OBS_SEGMENTATION_WRIST,
        }
    )
    color: list[float] = field(default_factory=lambda: [1.0, 0.85, 0.0])
    alpha: float = 0.6

    def __post_init__(self):
        if not self.cameras:
            raise ValueError(
                "cameras={} is not allowed; allowed: camera key -> segmentation key, at least one"
            )
        if len(self.color) != 3 or not all(0.0 <= c <= 1.0 for c in self.color):
            raise ValueError(f"color={self.color!r} is not allowed; allowed: three values in 0..1 (RGB)")
        if not 0.0 < self.alpha <= 1.0:
            raise ValueError(f"alpha={self.alpha!r} is not allowed; allowed: 0 < alpha <= 1")

    def observation(self, observation: dict) -> dict:
        if not self.enabled:
            return observation
        present = {cam: seg for cam, seg in self.cameras.items() if cam in observation}
        missing = [seg for seg in present.values() if seg not in observation]
        if missing:
            raise ValueError(
                f"condground_rgb_cue needs the destination masks {missing}: record with --dataset.labels=true; "
                "at evaluation send them with --env.cue=true (cue shown) or --env.cue=false (cue hidden)"
            )
        out = decode_labels(observation, list(present.values()))
        for camera, seg_key in present.items():
            out[camera] = self._draw(out[camera], out[seg_key])
        return out

    def _draw(self, image: torch.Tensor, labels) -> torch.Tensor:
        labels = torch.as_tensor(labels)
        mask = (labels.round() == DESTINATION).to(image.dtype)
        if mask.ndim == image.ndim - 1:  # (..., H, W) -> (..., 1, H, W)
            mask = mask.unsqueeze(-3)
        if mask.shape[-2:] != image.shape[-2:]:
            flat = mask.reshape(-1, 1, *mask.shape[-2:])
            mask = F.interpolate(flat, size=image.shape[-2:], mode="nearest").reshape(
                *mask.shape[:-2], *image.shape[-2:]
            )
        mask = mask.to(image.device) * self.alpha
        color = torch.tensor(self.color, dtype=image.dtype, device=image.device).view(3, 1, 1)
        return image * (1 - mask) + color * mask

    def get_config(self) -> dict:
        return {
            "enabled": self.enabled,
            "cameras": dict(self.cameras),
            "color": list(self.color),
            "alpha": self.alpha,
        }

    def transform_features(
        self, features: dict[PipelineFeatureType, dict[str, PolicyFeature]]
    ) -> dict[PipelineFeatureType, dict[str, PolicyFeature]]:
        return features
