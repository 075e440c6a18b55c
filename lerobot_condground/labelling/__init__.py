"""Visual prompts and label maps for hardware recordings: segmenters, prompt tracking, dataset labelling."""
