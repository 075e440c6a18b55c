"""Pre/post-processors of `act_modified`: LeRobot's four stock steps, plus the decoding of the PNG label
features the variant reads right after renaming, and the copy-paste augmentation between device placement and
normalization (it pastes into [0, 1] frames on the training device)."""

from __future__ import annotations

from typing import Any

import torch
from lerobot.processor import PolicyAction, PolicyProcessorPipeline
from lerobot.processor.factory import make_default_policy_processor_steps, make_policy_processor_pipelines

from lerobot_condground.core.labels import PNG_LABEL_KEYS
from lerobot_condground.processors.decode_labels import DecodeLabelsStep

from .configuration_act_modified import ACTModifiedConfig


def make_act_modified_pre_post_processors(
    config: ACTModifiedConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    steps = make_default_policy_processor_steps(config, dataset_stats, normalizer_device=config.device)
    labels = [key for key in PNG_LABEL_KEYS if key in config.needed_label_keys()]
    decoding = [DecodeLabelsStep(keys=labels)] if labels else []
    augmentation = [config.make_copy_paste_step()] if config.use_copy_paste else []
    return make_policy_processor_pipelines(
        input_steps=[
            steps.rename_observations,
            *decoding,
            steps.add_batch_dim,
            steps.to_device,
            *augmentation,
            steps.normalize,
        ],
        output_steps=[steps.unnormalize, steps.to_cpu],
    )
