"""Visual prompts and label maps for a real camera, in the simulation's form.

`PromptTracker` turns a `Segmenter` (SAM 2 or the color tracker) into what `act_modified` reads:

    tracker = PromptTracker(make_segmenter("sam2"))
    result = tracker.start(first_frame, object_prompt="120,80", receptacle_prompt="10,20,60,90")
    result = tracker.track(next_frame)   # per frame, live or over a recorded episode
    result.object_crop, result.receptacle_crop   # (64, 64, 3) uint8, as observation.prompt.*
    result.labels                                # (H, W) uint8, as observation.segmentation

The prompt crops are positionless: the simulation renders them once per episode, from a view of the
scene with the robot hidden, so they show the whole entity and nothing about where it goes. A real
camera cannot hide the robot, so the crops are cut once, from the annotated first frame (annotate it
while the gripper is away from both targets), and kept for the whole episode. Re-cutting them every
frame would leak the entity's current state into the prompt: the gripper closing over the object, the
object sitting in the receptacle, partial occlusion, and an empty crop whenever tracking loses it.
The masks, in contrast, are tracked on every frame: they are the per-frame segmentation labels.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from lerobot_condground.core.labels import (
    FIRST_COMPETITOR,
    PROMPT_SIZE,
    SYNTHETIC_DISTRACTOR,
    TARGET_OBJECT,
    TARGET_RECEPTACLE,
    crop_entity,
)
from lerobot_condground.labelling.segmenters import Prompt, Segmenter

logger = logging.getLogger(__name__)

MAX_COMPETITORS = SYNTHETIC_DISTRACTOR - FIRST_COMPETITOR  # labels 3..254; 255 is the augmentation's


@dataclass
class PromptResult:
    object_crop: np.ndarray  # (crop_size, crop_size, 3) uint8, fixed for the episode
    receptacle_crop: np.ndarray  # (crop_size, crop_size, 3) uint8, fixed for the episode
    labels: np.ndarray  # (H, W) uint8: 0 background, 1 object, 2 receptacle, 3.. competitors
    masks: dict[int, np.ndarray]  # the segmenter's (H, W) bool masks by object id


def labels_from_masks(masks: dict[int, np.ndarray], shape: tuple[int, int]) -> np.ndarray:
    """One label map from per-id masks. Where masks overlap, the target object wins (it lies in or on the
    receptacle and may be held over competitors), then the receptacle, then competitors by id."""
    labels = np.zeros(shape, np.uint8)
    order = sorted((i for i in masks if i >= FIRST_COMPETITOR), reverse=True)
    order += [i for i in (TARGET_RECEPTACLE, TARGET_OBJECT) if i in masks]
    for obj_id in order:
        labels[masks[obj_id]] = obj_id
    return labels


class PromptTracker:
    """Per-episode prompt crops and per-frame label maps from one annotation of the first frame."""

    def __init__(self, segmenter: Segmenter, crop_size: int = PROMPT_SIZE):
        self.segmenter = segmenter
        self.crop_size = crop_size
        self._crops: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def started(self) -> bool:
        return self._crops is not None

    def start(
        self, frame, object_prompt, receptacle_prompt, competitor_prompts: Iterable = ()
    ) -> PromptResult:
        """Annotates `frame` (the episode's first) and starts tracking. Prompts: `Prompt`, 'x,y',
        'x0,y0,x1,y1' or a tuple of 2 or 4 pixel coordinates."""
        prompts = {
            TARGET_OBJECT: Prompt.parse(object_prompt),
            TARGET_RECEPTACLE: Prompt.parse(receptacle_prompt),
        }
        competitors = [Prompt.parse(p) for p in competitor_prompts]
        if len(competitors) > MAX_COMPETITORS:
            raise ValueError(f"{len(competitors)} competitor prompts; allowed: at most {MAX_COMPETITORS}")
        prompts |= {FIRST_COMPETITOR + i: p for i, p in enumerate(competitors)}
        masks = self.segmenter.start(frame, prompts)
        frame = np.asarray(frame)
        for obj_id, name in ((TARGET_OBJECT, "object"), (TARGET_RECEPTACLE, "receptacle")):
            if not masks[obj_id].any():
                logger.warning(
                    "The %s prompt %s gave an empty mask on the annotated frame: its crop is black",
                    name,
                    prompts[obj_id],
                )
        self._crops = (
            crop_entity(frame, masks[TARGET_OBJECT], self.crop_size),
            crop_entity(frame, masks[TARGET_RECEPTACLE], self.crop_size),
        )
        return self._result(masks, frame.shape[:2])

    def track(self, frame) -> PromptResult:
        if self._crops is None:
            raise RuntimeError("track() before start(): annotate the episode's first frame with start()")
        masks = self.segmenter.track(frame)
        return self._result(masks, np.asarray(frame).shape[:2])

    def _result(self, masks: dict[int, np.ndarray], shape) -> PromptResult:
        return PromptResult(
            self._crops[0].copy(), self._crops[1].copy(), labels_from_masks(masks, shape), masks
        )


def annotate_interactively(frame, window: str = "condground prompts") -> tuple[Prompt, Prompt]:
    """Click the object, then the receptacle, then Enter (Backspace undoes, Esc cancels), in an OpenCV
    window: needs a display. Returns (object_prompt, receptacle_prompt) for `PromptTracker.start`."""
    import cv2

    image = cv2.cvtColor(np.asarray(frame), cv2.COLOR_RGB2BGR)
    clicks: list[tuple[int, int]] = []

    def on_mouse(event, x, y, *_):
        if event == cv2.EVENT_LBUTTONDOWN and len(clicks) < 2:
            clicks.append((x, y))

    cv2.namedWindow(window, cv2.WINDOW_NORMAL)
    cv2.setMouseCallback(window, on_mouse)
    try:
        while True:
            shown = image.copy()
            for (x, y), color in zip(clicks, [(0, 0, 255), (255, 0, 0)]):  # object red, receptacle blue
                cv2.circle(shown, (x, y), 4, color, -1)
            step = ("click the OBJECT", "click the RECEPTACLE", "Enter: accept")[len(clicks)]
            cv2.putText(shown, step, (5, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1)
            cv2.imshow(window, shown)
            key = cv2.waitKey(30) & 0xFF
            if key in (13, 10) and len(clicks) == 2:
                break
            if key == 27:
                raise ValueError("Annotation cancelled (Esc)")
            if key == 8 and clicks:
                clicks.pop()
    finally:
        cv2.destroyWindow(window)
    return Prompt(tuple(map(float, clicks[0]))), Prompt(tuple(map(float, clicks[1])))
