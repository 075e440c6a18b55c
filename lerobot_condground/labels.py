"""Names and encoding of the label features a recorded dataset carries beside cameras and state.

They are plain numeric `observation.*` features: LeRobot's batch conversion keeps them, and a stock
policy only reads `observation.state` and its cameras, so they are never fed to a policy that does
not ask for them.

`observation.segmentation` (H, W) uint8, lossless: 0 background and robot, 1 target object,
2 target receptacle, 3.. competitors (their classes are in the dataset's provenance file), 255
synthetic competitors pasted by the copy-paste augmentation.
`observation.phase` (1,) int64: 0 acquire the object, 1 transport and place.
`observation.prompt.object` / `observation.prompt.receptacle` (64, 64, 3) uint8: positionless crops.
"""

from __future__ import annotations

OBS_SEGMENTATION = "observation.segmentation"
OBS_PHASE = "observation.phase"
OBS_PROMPT_OBJECT = "observation.prompt.object"
OBS_PROMPT_RECEPTACLE = "observation.prompt.receptacle"
LABEL_KEYS = (OBS_SEGMENTATION, OBS_PHASE, OBS_PROMPT_OBJECT, OBS_PROMPT_RECEPTACLE)

BACKGROUND, TARGET_OBJECT, TARGET_RECEPTACLE, FIRST_COMPETITOR = 0, 1, 2, 3
SYNTHETIC_DISTRACTOR = 255


def phase_masks(segmentation, phase):
    """(M_phi, M_d): the phase-relevant entity (object while acquiring, receptacle while placing) and
    the competitors. Works on numpy arrays and torch tensors; `phase` broadcasts over (..., H, W)."""
    relevant_label = TARGET_OBJECT + phase
    if getattr(relevant_label, "ndim", 0):  # one phase per sample: broadcast over the image
        relevant_label = relevant_label.reshape(*relevant_label.shape, 1, 1)
    return segmentation == relevant_label, segmentation >= FIRST_COMPETITOR
