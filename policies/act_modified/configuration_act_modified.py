"""Configuration of `act_modified`: LeRobot's ACT plus the paper's three interventions.

The paper's four variants are presets of this one type (`--policy.variant=...`); every switch and
weight stays overridable after the preset, e.g.
`--policy.type=act_modified --policy.variant=full --policy.attention_pos_weight=0.5`.

| variant                  | copy-paste | attention loss | prompts | phase predictor |
|--------------------------|:----------:|:--------------:|:-------:|:---------------:|
| `standard`               |            |                |         |                 |
| `augmentation`           |     x      |                |         |                 |
| `augmentation_attention` |     x      |       x        |         |                 |
| `full` (default)         |     x      |       x        |    x    |                 |

`full` feeds both prompts and has no phase predictor by default, and its attention weights are 0.1: the paper's
phase predictor picks the prompt (`--policy.use_phase_predictor=true`, which also sets
`prompt_selection=phase`) and gives no lambda. Both choices are measured in docs/learning-curve/v3 (the
thirty-fifth session) and explained in docs/policies.md ("What differs from the paper"), as is the third of ours:
the pastes ramp in over the first 3000 training batches (`copy_paste_warmup_steps`; the fortieth session).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from lerobot.configs.policies import PreTrainedConfig
from lerobot.configs.types import FeatureType
from lerobot.optim.schedulers import CosineAnnealingWithWarmupSchedulerConfig
from lerobot.policies.act.configuration_act import ACTConfig
from lerobot.utils.constants import OBS_ENV_STATE, OBS_IMAGES, OBS_STATE

from lerobot_condground.core.labels import (
    LABEL_KEYS,
    OBS_PHASE,
    OBS_PROMPT_OBJECT,
    OBS_PROMPT_RECEPTACLE,
    OBS_SEGMENTATION,
    PROMPT_CAMERA_KEYS,
)
from lerobot_condground.core.trust import HUB_ID
from lerobot_condground.processors.copy_paste import (
    CATEGORIES,
    ROLES,
    CopyPasteDistractorStep,
    CopyPasteParams,
)

# Learning-rate schedules of the training preset, over `--steps`: constant is ACT's (no scheduler);
# cosine warms up linearly, then anneals to zero at the last step.
SCHEDULERS = ("constant", "cosine")
# The ResNet stage whose output becomes the transformer's image tokens: layer4 (ACT's, stride 32) or layer3
# (stride 16: four times the tokens, at less compute than the final stride's dilation, which still runs layer4).
BACKBONE_LAYERS = ("layer4", "layer3")
COMPONENTS = ("use_copy_paste", "use_attention_loss", "use_prompts", "use_phase_predictor")
BACKBONE_NORMS = ("frozen_batchnorm", "batchnorm", "groupnorm")
# What the supervised head's A is normalized over: the camera's tokens (A sums to 1 on the grid, whatever share
# of the head's attention the camera gets) or the whole memory (A is the head's own attention on the grid, so
# 1 - <A, M_phi> is small only when the head looks at the image, and at the relevant entity there).
ATTENTION_NORMALIZATIONS = ("camera", "memory")
# Which prompts the memory holds: the one the phase picks (the paper: the phase predictor at inference, the label in
# training) or both, each with its kind, the policy reading the phase off the scene as stock ACT does. With "phase"
# a wrong prediction feeds the wrong crop: after a missed grasp the predictor, which reads the closed gripper, fed
# the receptacle's crop with the cube still on the table (docs/learning-curve/v3, thirty-fourth session).
PROMPT_SELECTIONS = ("phase", "both")
# Blocks per stage of the basic-block ResNets a narrower backbone can copy.
NARROW_RESNET_LAYERS = {"resnet18": (2, 2, 2, 2), "resnet34": (3, 4, 6, 3)}
VARIANTS: dict[str, dict[str, bool]] = {
    "standard": dict.fromkeys(COMPONENTS, False),
    "augmentation": {**dict.fromkeys(COMPONENTS, False), "use_copy_paste": True},
    "augmentation_attention": {
        **dict.fromkeys(COMPONENTS, False),
        "use_copy_paste": True,
        "use_attention_loss": True,
    },
    "full": {**dict.fromkeys(COMPONENTS, True), "use_phase_predictor": False},
}
# Label features each component reads from the dataset.
COMPONENT_NEEDS: dict[str, tuple[str, ...]] = {
    "use_copy_paste": (OBS_SEGMENTATION,),
    "use_attention_loss": (OBS_SEGMENTATION, OBS_PHASE),
    "use_prompts": (OBS_PROMPT_OBJECT, OBS_PROMPT_RECEPTACLE, OBS_PHASE),
    "use_phase_predictor": (OBS_PHASE,),
}


@PreTrainedConfig.register_subclass("act_modified")
@dataclass
class ACTModifiedConfig(ACTConfig):
    """ACT with copy-paste augmentation, phase-dependent attention regularization, positionless
    visual prompts and a phase predictor (paper eq. 1):

        L = L_ACT + phase_loss_weight * L_phi + attention_pos_weight * (1 - <A, M_phi>)
                  + attention_neg_weight * <A, M_d>
    """

    # One of standard | augmentation | augmentation_attention | full. Sets the four switches
    # below unless they are given explicitly.
    variant: str = "full"
    use_copy_paste: bool | None = None
    use_attention_loss: bool | None = None
    use_prompts: bool | None = None
    use_phase_predictor: bool | None = None

    # Attention regularization: this head of the last decoder layer's cross-attention is supervised,
    # over the token grid of `attention_camera`: the camera whose pixels `observation.segmentation`
    # labels (default: the first camera), which is also the camera the copy-paste step augments.
    attention_head: int = 0
    attention_camera: str | None = None
    # lambda_+, lambda_-: at 1.0 the two terms are about five times the L1 and `full` on the smaller model learned
    # nothing (0 of 300, docs/learning-curve/v2); 0.1 is the weight every later measurement used.
    attention_pos_weight: float = 0.1  # lambda_+
    attention_neg_weight: float = 0.1  # lambda_-
    attention_normalization: str = "camera"  # one of ATTENTION_NORMALIZATIONS

    # Phase predictor (L_phi, cross-entropy). In training the prompt is chosen by the phase label
    # with this probability and by the predictor otherwise (scheduled sampling when < 1).
    phase_loss_weight: float = 1.0  # lambda_phi
    phase_teacher_forcing: float = 1.0
    phase_head_dim: int = 256
    # The phase head reads the backbone's pooled features; with this set it reads them without training them
    # (stop-gradient), so L_phi shapes only the head. Joined with copy-paste, the trained-through head stalled
    # the first action chunk at 1000 steps (docs/learning-curve/v3).
    phase_head_detach: bool = False
    # One of PROMPT_SELECTIONS; "both" needs no phase predictor (it may still be trained, for L_phi alone).
    # Unset, it is "phase" where there is a phase predictor and "both" where there is none, which also keeps
    # checkpoints saved before this field existed (all with a predictor) as they were trained.
    prompt_selection: str | None = None

    # Copy-paste distractor augmentation (a train-only preprocessor step; saved with the checkpoint,
    # so changing these for a loaded checkpoint has no effect on its saved step).
    copy_paste_prob: float = CopyPasteParams.prob
    copy_paste_min_count: int = CopyPasteParams.min_count
    copy_paste_max_count: int = CopyPasteParams.max_count
    copy_paste_max_occlusion: float = CopyPasteParams.max_occlusion
    copy_paste_seed: int = CopyPasteParams.seed
    copy_paste_categories: list[str] = field(default_factory=lambda: list(CATEGORIES))
    copy_paste_roles: list[str] = field(default_factory=lambda: list(ROLES))
    copy_paste_codec: str = CopyPasteParams.codec
    # The paste probability ramps in over the first 3000 training batches: a backbone trained from scratch must
    # first find the target's few pixels from the action loss, and pastes from the first step kept it from ever
    # doing so on Task 2 (two seeds of `full`); on Task 1 it cost nothing in the one seed measured (docs/learning-curve/v3).
    copy_paste_warmup_steps: int = 3000

    # Normalization layers of the ResNet backbone: frozen_batchnorm (LeRobot's ACT, made for ImageNet
    # weights), batchnorm or groupnorm (32 groups). Trained from scratch (pretrained_backbone_weights=None),
    # frozen batch norm is an identity: the backbone then has no normalization at all.
    backbone_norm: str = "frozen_batchnorm"
    # Channels of the ResNet's first stage (each later stage doubles them). 64 is torchvision's ResNet
    # (`vision_backbone`, loadable with ImageNet weights); smaller widths build the same layout narrower
    # (timm's ResNet), trained from scratch: half the width is about a quarter of the backbone's compute.
    backbone_width: int = 64
    # The stage read as image tokens (one of BACKBONE_LAYERS): layer3 cuts the ResNet there, stride 16.
    backbone_layer: str = "layer4"
    # The backbone's frames and activations in channels-last memory order (a speed setting: oneDNN's
    # convolutions run faster so on the CPUs `condground bench` measured; the same function, summed in another
    # order). Weights and checkpoints are the same either way.
    channels_last: bool = False

    # Learning-rate schedule of the training preset (one of SCHEDULERS), as diffusion policy names it.
    # cosine needs `--steps` to be the run's real budget: the rate reaches zero there.
    scheduler_name: str = "constant"
    scheduler_warmup_steps: int = 500
    # Exponential moving average of the weights, updated after every optimizer step (decay warmed up as
    # diffusion policy does: min(ema_decay, (1 + t) / (10 + t))). The average is what acts and what the
    # diagnosis reads; the raw weights keep training. None trains without one.
    ema_decay: float | None = None

    # Warm start: a stock `act` (or `act_modified`) checkpoint, local directory or hub id, whose
    # weights initialize the shared ACT parameters; the new heads start fresh.
    init_from_act: str | None = None

    # Label features this policy was configured with (filled from the dataset on first use).
    label_keys: list[str] | None = None

    def __post_init__(self):
        super().__post_init__()
        if self.variant not in VARIANTS:
            raise ValueError(f"Unknown act_modified variant {self.variant!r}; allowed: {', '.join(VARIANTS)}")
        for name, value in VARIANTS[self.variant].items():
            if getattr(self, name) is None:
                setattr(self, name, value)
        if not 0 <= self.attention_head < self.n_heads:
            raise ValueError(f"attention_head={self.attention_head} must be in [0, n_heads={self.n_heads})")
        for name in ("attention_pos_weight", "attention_neg_weight", "phase_loss_weight"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name}={getattr(self, name)} must be >= 0")
        if self.attention_normalization not in ATTENTION_NORMALIZATIONS:
            raise ValueError(
                f"attention_normalization={self.attention_normalization!r} is not allowed; allowed: "
                f"{', '.join(ATTENTION_NORMALIZATIONS)}"
            )
        if not 0.0 <= self.phase_teacher_forcing <= 1.0:
            raise ValueError(f"phase_teacher_forcing={self.phase_teacher_forcing} must be in [0, 1]")
        if self.prompt_selection is None:
            self.prompt_selection = "phase" if self.use_phase_predictor else "both"
        if self.prompt_selection not in PROMPT_SELECTIONS:
            raise ValueError(
                f"prompt_selection={self.prompt_selection!r} is not allowed; allowed: {', '.join(PROMPT_SELECTIONS)}"
            )
        if self.use_prompts and self.prompt_selection == "phase" and not self.use_phase_predictor:
            raise ValueError(
                "use_prompts=true needs use_phase_predictor=true: the predicted phase picks the object or "
                "receptacle prompt at inference (or prompt_selection=both, which feeds both)"
            )
        if self.backbone_norm not in BACKBONE_NORMS:
            raise ValueError(
                f"backbone_norm={self.backbone_norm!r} is not allowed; allowed: {', '.join(BACKBONE_NORMS)}"
            )
        if self.backbone_norm == "groupnorm" and self.pretrained_backbone_weights:
            raise ValueError(
                f"backbone_norm=groupnorm cannot load pretrained_backbone_weights="
                f"{self.pretrained_backbone_weights!r} (batch-norm statistics); allowed with pretrained "
                "weights: frozen_batchnorm, batchnorm"
            )
        if self.backbone_layer not in BACKBONE_LAYERS:
            raise ValueError(
                f"backbone_layer={self.backbone_layer!r} is not allowed; allowed: {', '.join(BACKBONE_LAYERS)}"
            )
        if self.backbone_layer != "layer4" and self.replace_final_stride_with_dilation:
            raise ValueError(
                f"backbone_layer={self.backbone_layer!r} with replace_final_stride_with_dilation=true: the dilation "
                "is in layer4, which the cut drops; allowed: one of the two"
            )
        if self.init_from_act and Path(self.init_from_act).exists():
            # Saved into config.json: relative, it would name another folder from wherever the run is resumed.
            self.init_from_act = str(Path(self.init_from_act).resolve())
        elif self.init_from_act and not HUB_ID.fullmatch(self.init_from_act):
            raise ValueError(
                f"init_from_act={self.init_from_act!r} is neither an existing checkpoint directory nor a hub id "
                "(namespace/name)"
            )
        if self.scheduler_name not in SCHEDULERS:
            raise ValueError(
                f"scheduler_name={self.scheduler_name!r} is not allowed; allowed: {', '.join(SCHEDULERS)}"
            )
        if self.scheduler_warmup_steps < 0:
            raise ValueError(f"scheduler_warmup_steps={self.scheduler_warmup_steps} must be >= 0")
        if self.ema_decay is not None and not 0.0 < self.ema_decay < 1.0:
            raise ValueError(f"ema_decay={self.ema_decay} must be in (0, 1), or null for no moving average")
        if self.backbone_width != 64:
            self._check_narrow_backbone()
        if self.use_copy_paste:
            self.make_copy_paste_step()  # validates the copy_paste_* values now, at parse time

    def _check_narrow_backbone(self) -> None:
        if self.backbone_width < 8 or self.backbone_width % 8:
            raise ValueError(
                f"backbone_width={self.backbone_width} must be a positive multiple of 8 (64: torchvision's)"
            )
        if self.vision_backbone not in NARROW_RESNET_LAYERS:
            raise ValueError(
                f"backbone_width={self.backbone_width} needs a basic-block ResNet; vision_backbone="
                f"{self.vision_backbone!r} is not one of: {', '.join(NARROW_RESNET_LAYERS)}"
            )
        if self.pretrained_backbone_weights:
            raise ValueError(
                f"backbone_width={self.backbone_width} is trained from scratch; pretrained_backbone_weights="
                f"{self.pretrained_backbone_weights!r} only fits backbone_width=64 (set it to null)"
            )
        if self.backbone_norm == "frozen_batchnorm":
            raise ValueError(
                f"backbone_width={self.backbone_width} is trained from scratch, where frozen batch norm normalizes "
                "nothing; allowed: backbone_norm=batchnorm or groupnorm"
            )
        if self.backbone_norm == "groupnorm" and self.backbone_width % 32:
            raise ValueError(
                f"backbone_norm=groupnorm uses 32 groups, so backbone_width={self.backbone_width} must be a "
                "multiple of 32 (or use backbone_norm=batchnorm)"
            )

    def make_copy_paste_step(self):
        return CopyPasteDistractorStep(
            camera_key=self.attention_camera or f"{OBS_IMAGES}.top",
            prob=self.copy_paste_prob,
            min_count=self.copy_paste_min_count,
            max_count=self.copy_paste_max_count,
            max_occlusion=self.copy_paste_max_occlusion,
            seed=self.copy_paste_seed,
            categories=self.copy_paste_categories,
            roles=self.copy_paste_roles,
            codec=self.copy_paste_codec,
            warmup_steps=self.copy_paste_warmup_steps,
        )

    def get_scheduler_preset(self) -> CosineAnnealingWithWarmupSchedulerConfig | None:
        if self.scheduler_name == "cosine":
            return CosineAnnealingWithWarmupSchedulerConfig(num_warmup_steps=self.scheduler_warmup_steps)
        return None

    def needed_label_keys(self) -> list[str]:
        needed = [key for name, keys in COMPONENT_NEEDS.items() if getattr(self, name) for key in keys]
        return sorted(set(needed))

    def validate_features(self) -> None:
        if self.label_keys is None:
            self._take_label_features()
        missing = [key for key in self.needed_label_keys() if key not in self.label_keys]
        if missing:
            fallback = next(
                name
                for name in reversed(VARIANTS)
                if all(
                    key in self.label_keys
                    for c, on in VARIANTS[name].items()
                    if on
                    for key in COMPONENT_NEEDS[c]
                )
            )
            switches = ", ".join(f"{c}={getattr(self, c)}" for c in COMPONENTS)
            raise ValueError(
                f"act_modified variant {self.variant!r} ({switches}) needs the dataset features {missing}, which "
                f"the dataset lacks. `condground record` writes them; --policy.variant={fallback} builds without them."
            )
        super().validate_features()
        if self.attention_camera is None and self.image_features:
            self.attention_camera = next(iter(self.image_features))
        if (
            self.use_attention_loss or self.use_copy_paste
        ) and self.attention_camera not in self.image_features:
            raise ValueError(
                f"attention_camera={self.attention_camera!r} is not a camera of the policy; allowed: "
                f"{', '.join(self.image_features)}"
            )

    def _take_label_features(self) -> None:
        """Moves label features out of the inputs: they are targets and masks, not observations, and
        the normalizer must never see them. Only state and cameras stay inputs."""
        self.label_keys = [key for key in LABEL_KEYS if key in self.input_features]
        for key in list(self.input_features):
            feature = self.input_features[key]
            is_camera = (
                feature.type is FeatureType.VISUAL
                and key.startswith(f"{OBS_IMAGES}.")
                and key not in PROMPT_CAMERA_KEYS
            )
            if key not in (OBS_STATE, OBS_ENV_STATE) and not is_camera:
                del self.input_features[key]
