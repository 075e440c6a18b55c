"""Demonstration datasets: recording the scripted expert, merging recordings, copy-paste augmentation, dataset
provenance."""
