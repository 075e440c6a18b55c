"""Demonstration datasets: recording the scripted expert, copy-paste augmentation, dataset provenance."""
