"""`condground_decode_labels`: turns the PNG label features of a recorded dataset (segmentation,
prompt crops) back into uint8 tensors at the head of a policy's preprocessor.

They are stored as PNG strings because LeRobot reads whole parquet rows for every frame of an action
chunk (see `lerobot_condground.core.labels`); decoding only the current frame here keeps data loading as
fast as for a dataset without labels. Values that already are tensors (prompts sent by the env or a
robot at inference) pass through.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs.types import PipelineFeatureType, PolicyFeature
from lerobot.processor.pipeline import ObservationProcessorStep, ProcessorStepRegistry

from lerobot_condground.core.labels import PNG_LABEL_KEYS, decode_labels


@ProcessorStepRegistry.register(name="condground_decode_labels")
@dataclass
class DecodeLabelsStep(ObservationProcessorStep):
    # Only the labels the policy reads: decoding runs on every training batch.
    keys: list[str] = field(default_factory=lambda: list(PNG_LABEL_KEYS))

    def __post_init__(self):
        unknown = [key for key in self.keys if key not in PNG_LABEL_KEYS]
        if unknown:
            raise ValueError(
                f"keys={unknown} are not PNG label features; allowed: {', '.join(PNG_LABEL_KEYS)}"
            )

    def observation(self, observation: dict) -> dict:
        return decode_labels(observation, self.keys)

    def get_config(self) -> dict:
        return {"keys": list(self.keys)}

    def transform_features(
        self, features: dict[PipelineFeatureType, dict[str, PolicyFeature]]
    ) -> dict[PipelineFeatureType, dict[str, PolicyFeature]]:
        return features
