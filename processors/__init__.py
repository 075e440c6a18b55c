"""Processor steps of the plugin. Importing this package registers them with LeRobot's
`ProcessorStepRegistry`, which is how a saved pipeline finds them again."""

from .copy_paste import CopyPasteDistractorStep
from .decode_labels import DecodeLabelsStep

__all__ = ["CopyPasteDistractorStep", "DecodeLabelsStep"]
