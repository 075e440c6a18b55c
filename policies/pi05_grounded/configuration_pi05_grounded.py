"""Configuration of `pi05_grounded`: LeRobot's π0.5 with the paper's VLA-study variants (InstrumentRouting-v0).

| variant                 | RGB cue (`condground_rgb_cue`) | instruction | eq. (1) on the action expert |
|-------------------------|:------------------------------:|:-----------:|:----------------------------:|
| `plain`                 |                                | generic     |                              |
| `cue` (prompt-trained)  |               x                | generic     |                              |
| `regularized` (default) |                                | explicit    |              x               |

Every switch stays overridable after the preset (`--policy.variant=cue --policy.instruction=explicit`).
The regularizer adds no parameter: `pi05_base` (or any `pi05` checkpoint) loads strictly into this type.

    L = L_flow + grounding_pos_weight * (1 - <A, M_phi>) + grounding_neg_weight * <A, M_d>

A is the attention of the action queries over one camera's image patches (chosen expert layers and heads,
averaged over them and the action queries, renormalized over the camera's patches). M_phi is the
step-relevant entity, M_d the other container (`core.routing.step_masks`), both from the recorded
segmentation of that camera.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs.policies import PreTrainedConfig
from lerobot.configs.types import FeatureType
from lerobot.policies.pi05.configuration_pi05 import PI05Config
from lerobot.utils.constants import OBS_IMAGES, OBS_STATE

from lerobot_condground.core.labels import (
    OBS_DESTINATION,
    OBS_PHASE,
    OBS_SEGMENTATION,
    OBS_SEGMENTATION_WRIST,
)
from lerobot_condground.core.routing import INSTRUCTION_FORMS

# The stock pi05 tokenizer (hard-coded in LeRobot's pi05 processor); here a field, so a local copy works offline.
PALIGEMMA_TOKENIZER = "google/paligemma-3b-pt-224"
SWITCHES = ("use_grounding_loss", "cue", "instruction")
VARIANTS: dict[str, dict] = {
    "plain": {"use_grounding_loss": False, "cue": False, "instruction": "generic"},
    "cue": {"use_grounding_loss": False, "cue": True, "instruction": "generic"},
    "regularized": {"use_grounding_loss": True, "cue": False, "instruction": "explicit"},
}
# Dataset features that are labels (masks, step, side), never inputs the normalizer may see.
LABEL_KEYS = (OBS_SEGMENTATION, OBS_SEGMENTATION_WRIST, OBS_PHASE, OBS_DESTINATION)
# π0.5's query heads per layer (its layer code reshapes with 8 heads).
N_HEADS = 8


@PreTrainedConfig.register_subclass("pi05_grounded")
@dataclass
class PI05GroundedConfig(PI05Config):
    variant: str = "regularized"
    use_grounding_loss: bool | None = None
    cue: bool | None = None
    instruction: str | None = None  # generic | explicit

    # A hub id or a local directory holding the tokenizer files (AutoTokenizer.from_pretrained).
    tokenizer_name: str = PALIGEMMA_TOKENIZER

    grounding_pos_weight: float = 1.0  # lambda_+
    grounding_neg_weight: float = 1.0  # lambda_-
    # Layers of the action expert (negative: from the last), and query heads (empty: all of them).
    grounding_layers: list[int] = field(default_factory=lambda: [-1])
    grounding_heads: list[int] = field(default_factory=list)
    # Camera -> the segmentation labelling its pixels. The regularizer and the cue use the pairs whose
    # camera the policy has.
    grounding_cameras: dict[str, str] = field(
        default_factory=lambda: {
            f"{OBS_IMAGES}.top": OBS_SEGMENTATION,
            f"{OBS_IMAGES}.wrist": OBS_SEGMENTATION_WRIST,
        }
    )

    # Label features this policy was configured with (filled from the dataset on first use).
    label_keys: list[str] | None = None

    def __post_init__(self):
        super().__post_init__()
        if self.variant not in VARIANTS:
            raise ValueError(
                f"Unknown pi05_grounded variant {self.variant!r}; allowed: {', '.join(VARIANTS)}"
            )
        for name, value in VARIANTS[self.variant].items():
            if getattr(self, name) is None:
                setattr(self, name, value)
        if self.instruction not in INSTRUCTION_FORMS:
            raise ValueError(
                f"instruction={self.instruction!r} is not allowed; allowed: {', '.join(INSTRUCTION_FORMS)}"
            )
        for name in ("grounding_pos_weight", "grounding_neg_weight"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name}={getattr(self, name)} is not allowed; allowed: >= 0")
        bad_heads = [h for h in self.grounding_heads if not 0 <= h < N_HEADS]
        if bad_heads:
            raise ValueError(f"grounding_heads={bad_heads} are not allowed; allowed: 0..{N_HEADS - 1}")
        if self.use_grounding_loss and not self.grounding_layers:
            raise ValueError(
                "grounding_layers=[] is not allowed with use_grounding_loss=true; allowed: layer indices"
            )
        if not self.tokenizer_name:
            raise ValueError("tokenizer_name is empty; allowed: a hub id or a local tokenizer directory")

    def needed_label_keys(self) -> list[str]:
        """The label features training needs, given the switches and the policy's cameras."""
        segmentations = [seg for cam, seg in self.grounding_cameras.items() if cam in self.image_features]
        needed = []
        if self.use_grounding_loss:
            needed += [OBS_PHASE, *segmentations]
        if self.cue:
            needed += segmentations
        if self.instruction == "explicit":
            needed.append(OBS_DESTINATION)
        return sorted(set(needed))

    def validate_features(self) -> None:
        if self.label_keys is None:
            self.label_keys = [key for key in LABEL_KEYS if key in self.input_features]
            for key, feature in list(self.input_features.items()):
                if key != OBS_STATE and feature.type is not FeatureType.VISUAL:
                    del self.input_features[key]
        if (self.use_grounding_loss or self.cue) and not any(
            c in self.image_features for c in self.grounding_cameras
        ):
            raise ValueError(
                f"grounding_cameras={list(self.grounding_cameras)} names none of the policy's cameras "
                f'{list(self.image_features)}; give --policy.grounding_cameras=\'{{"<camera>": "<segmentation>"}}\''
            )
        missing = [key for key in self.needed_label_keys() if key not in self.label_keys]
        if missing:
            switches = ", ".join(f"{name}={getattr(self, name)}" for name in SWITCHES)
            raise ValueError(
                f"pi05_grounded variant {self.variant!r} ({switches}) needs the dataset features {missing}, which "
                "the dataset lacks: record it with `condground record --env.task=InstrumentRouting-v0` "
                "(--dataset.labels=true), or use --policy.variant=plain"
            )
        super().validate_features()
