"""`condground_instruction`: rewrites InstrumentRouting-v0's task strings into the generic ("... into the
highlighted container") or the explicit form ("... into the left container").

Recordings hold the generic form and each frame's destination (`observation.destination`, 0 left,
1 right), so one dataset trains either variant. At evaluation the env gives the form itself
(`--env.instruction=explicit`): an explicit string needs no destination and passes as it is. Strings that
are no routing instruction (other subgoals, other tasks) pass unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from lerobot.configs.types import PipelineFeatureType, PolicyFeature
from lerobot.processor.pipeline import ComplementaryDataProcessorStep, ProcessorStepRegistry, TransitionKey

from lerobot_condground.core.labels import OBS_DESTINATION
from lerobot_condground.core.routing import INSTRUCTION_FORMS, ROUTING_SUBGOALS, SIDES, instruction

# Every routing instruction in any form -> (subgoal, side or None for the generic form).
_PARSED = {instruction(s): (s, None) for s in ROUTING_SUBGOALS} | {
    instruction(s, "explicit", side): (s, side) for s in ROUTING_SUBGOALS for side in SIDES
}


@ProcessorStepRegistry.register(name="condground_instruction")
@dataclass
class InstructionStep(ComplementaryDataProcessorStep):
    form: str = "generic"

    def __post_init__(self):
        if self.form not in INSTRUCTION_FORMS:
            raise ValueError(f"form={self.form!r} is not allowed; allowed: {', '.join(INSTRUCTION_FORMS)}")

    def complementary_data(self, complementary_data: dict) -> dict:
        task = complementary_data.get("task")
        if task is None:
            return complementary_data
        tasks = [task] if isinstance(task, str) else list(task)
        sides = None
        out = []
        for k, text in enumerate(tasks):
            subgoal, side = _PARSED.get(text, (None, None))
            if subgoal is None or (self.form == "generic") == (side is None):
                out.append(text)
                continue
            if self.form == "generic":
                out.append(instruction(subgoal))
                continue
            if sides is None:
                sides = self._sides(len(tasks))
            out.append(instruction(subgoal, "explicit", sides[k]))
        return {**complementary_data, "task": out[0] if isinstance(task, str) else out}

    def _sides(self, n: int) -> list[str]:
        observation = self._current_transition.get(TransitionKey.OBSERVATION) or {}
        value = observation.get(OBS_DESTINATION)
        if value is None:
            raise ValueError(
                f"condground_instruction (form=explicit) needs `{OBS_DESTINATION}` to name the side of a generic "
                "routing instruction: record with --dataset.labels=true; at evaluation give the explicit text "
                "with --env.instruction=explicit"
            )
        index = torch.as_tensor(value).reshape(-1).round().long().tolist()
        if len(index) != n or not all(i in (0, 1) for i in index):
            raise ValueError(
                f"`{OBS_DESTINATION}` holds {index}; allowed: one 0 (left) or 1 (right) per task string"
            )
        return [SIDES[i] for i in index]

    def get_config(self) -> dict:
        return {"form": self.form}

    def transform_features(
        self, features: dict[PipelineFeatureType, dict[str, PolicyFeature]]
    ) -> dict[PipelineFeatureType, dict[str, PolicyFeature]]:
        return features
