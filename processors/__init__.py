"""Processor steps of the plugin. The copy-paste distractor augmentation lands here (issue 3)."""
