"""Pre/post-processors of `pi05_grounded`: LeRobot's pi05 pipeline with the config's tokenizer instead of the
hard-coded PaliGemma one, and the plugin's steps at its head, on raw [0, 1] frames and raw task strings:
label decoding, the RGB cue (variant `cue`), the instruction form. The steps are saved with every checkpoint,
so `lerobot-train --policy.path` and `lerobot-eval` rebuild them by name."""

from __future__ import annotations

from typing import Any

import torch
from lerobot.policies.pi05.processor_pi05 import Pi05PrepareStateTokenizerProcessorStep
from lerobot.processor import (
    AbsoluteActionsProcessorStep,
    PolicyAction,
    PolicyProcessorPipeline,
    RelativeActionsProcessorStep,
    TokenizerProcessorStep,
    make_default_policy_processor_steps,
    make_policy_processor_pipelines,
)

from lerobot_condground.processors.decode_labels import DecodeLabelsStep
from lerobot_condground.processors.instruction import InstructionStep
from lerobot_condground.processors.rgb_cue import RgbCueStep

from .configuration_pi05_grounded import PI05GroundedConfig


def make_pi05_grounded_pre_post_processors(
    config: PI05GroundedConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    relative = RelativeActionsProcessorStep(
        enabled=config.use_relative_actions,
        exclude_joints=config.relative_exclude_joints,
        action_names=config.action_feature_names,
    )
    steps = make_default_policy_processor_steps(config, dataset_stats)
    cameras = {cam: seg for cam, seg in config.grounding_cameras.items() if cam in config.image_features}
    plugin_steps = [
        DecodeLabelsStep(keys=sorted(set(cameras.values()))) if config.use_grounding_loss else None,
        RgbCueStep(cameras=cameras) if config.cue else None,
        InstructionStep(form=config.instruction),
    ]
    return make_policy_processor_pipelines(
        input_steps=[
            steps.rename_observations,
            *[step for step in plugin_steps if step is not None],
            steps.add_batch_dim,
            relative,
            # The state tokenizer step discretizes the normalized state, so it comes after normalization.
            steps.normalize,
            Pi05PrepareStateTokenizerProcessorStep(max_state_dim=config.max_state_dim),
            tokenizer_step(config),
            steps.to_device,
        ],
        output_steps=[
            steps.unnormalize,
            AbsoluteActionsProcessorStep(enabled=config.use_relative_actions, relative_step=relative),
            steps.to_cpu,
        ],
    )


def tokenizer_step(config: PI05GroundedConfig) -> TokenizerProcessorStep:
    try:
        return TokenizerProcessorStep(
            tokenizer_name=config.tokenizer_name,
            max_length=config.tokenizer_max_length,
            padding_side="right",
            padding="max_length",
        )
    except (OSError, ValueError) as e:
        raise ValueError(
            f"--policy.tokenizer_name={config.tokenizer_name!r} cannot be loaded here ({type(e).__name__}). "
            "Without network access keep the hub id and copy the hub cache from where the hub is reachable "
            "(`hf download NAME`, then HF_HUB_CACHE): a checkpoint naming a tokenizer directory outside its "
            "folder is refused by condground's commands. A local directory holding the tokenizer's files "
            "(`AutoTokenizer.from_pretrained(name).save_pretrained(DIR)`) works with the stock scripts"
        ) from e
