"""Distractor conditions: how many look-alike competitors of each class a scene holds.

A competitor matches its target (the target object, or the target receptacle) in color (same color,
other shape), in shape (same shape, other color) or in neither. Every command takes a condition by
name (`clean`, `object_color_2`, `full_mixed`, ...) or as fields (`object_color=2,receptacle_shape=1`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, fields

ROLES = ("object", "receptacle")
MATCHES = ("color", "shape", "neither")
MAX_PER_CLASS = 3
TASKS = ("PickPlaceFixedBin-v0", "PickPlaceRandomBin-v0")
# The state-conditioned routing task of the VLA case study: no competitor conditions, subgoals instead.
ROUTING_TASK = "InstrumentRouting-v0"
ENV_TASKS = (*TASKS, ROUTING_TASK)


@dataclass(frozen=True)
class ConditionSpec:
    object_color: int = 0
    object_shape: int = 0
    object_neither: int = 0
    receptacle_color: int = 0
    receptacle_shape: int = 0
    receptacle_neither: int = 0

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_PER_CLASS:
                raise ValueError(
                    f"Competitor count {f.name}={value!r} is out of range; allowed: integers 0..{MAX_PER_CLASS}"
                )

    def count(self, role: str, match: str) -> int:
        return getattr(self, f"{role}_{match}")

    def competitor_classes(self) -> list[tuple[str, str]]:
        """(role, match) once per competitor, in a fixed order."""
        return [(r, m) for r in ROLES for m in MATCHES for _ in range(self.count(r, m))]

    @property
    def num_competitors(self) -> int:
        return sum(getattr(self, f.name) for f in fields(self))

    @property
    def name(self) -> str:
        for name, spec in NAMED_CONDITIONS.items():
            if spec == self:
                return name
        return ",".join(f"{f.name}={getattr(self, f.name)}" for f in fields(self) if getattr(self, f.name))

    @classmethod
    def parse(cls, text: str | ConditionSpec) -> ConditionSpec:
        """A condition by name, or by fields `role_match=count` joined with commas."""
        if isinstance(text, ConditionSpec):
            return text
        text = str(text).strip()
        if text in NAMED_CONDITIONS:
            return NAMED_CONDITIONS[text]
        if "=" not in text:
            raise ValueError(
                f"Unknown condition {text!r}; allowed: {', '.join(NAMED_CONDITIONS)}, "
                f"or fields like 'object_color=2,receptacle_shape=1' (fields: {', '.join(FIELD_NAMES)})"
            )
        values: dict[str, int] = {}
        for part in text.split(","):
            key, _, raw = part.partition("=")
            key = key.strip()
            if key not in FIELD_NAMES:
                raise ValueError(
                    f"Unknown condition field {key!r} in {text!r}; allowed: {', '.join(FIELD_NAMES)}"
                )
            if key in values:
                raise ValueError(
                    f"Condition field {key!r} is given twice in {text!r}; allowed: each field once"
                )
            # int() would also read '١' or '2_0': only the ASCII digits condition names are written with.
            if not re.fullmatch(r"-?[0-9]+", raw.strip()):
                raise ValueError(
                    f"Competitor count {key}={raw.strip()!r} is not an integer; allowed: 0..{MAX_PER_CLASS}"
                )
            values[key] = int(raw)
        return cls(**values)


FIELD_NAMES = tuple(f"{r}_{m}" for r in ROLES for m in MATCHES)

NAMED_CONDITIONS: dict[str, ConditionSpec] = {"clean": ConditionSpec()}
for _field in FIELD_NAMES:
    for _n in range(1, MAX_PER_CLASS + 1):
        NAMED_CONDITIONS[f"{_field}_{_n}"] = ConditionSpec(**{_field: _n})
NAMED_CONDITIONS["full_mixed"] = ConditionSpec(**dict.fromkeys(FIELD_NAMES, 1))

# The paper's evaluation grid: clean, each class at 1..3 competitors, and full mixed.
PAPER_GRID = tuple(NAMED_CONDITIONS)


def check_task(task: str) -> str:
    """A pick-and-place task: the ones with competitor conditions."""
    if task == ROUTING_TASK:
        raise ValueError(
            f"{task} has no competitor conditions; allowed here: {', '.join(TASKS)}. Evaluate it per subgoal: "
            f"lerobot-eval --env.type=condground --env.task={task} --env.subgoal=route"
        )
    if task not in TASKS:
        raise ValueError(f"Unknown task {task!r}; allowed: {', '.join(TASKS)}")
    return task


def check_env_task(task: str) -> str:
    """A task the `condground` env type runs (the pick-and-place tasks and the routing task)."""
    if task not in ENV_TASKS:
        raise ValueError(f"Unknown task {task!r}; allowed: {', '.join(ENV_TASKS)}")
    return task


def check_condition(condition: str, flag: str) -> str:
    """A condition's name as a command's flag gives it (a name or a spec), or one error naming the flag."""
    try:
        return ConditionSpec.parse(condition).name
    except ValueError as err:
        raise ValueError(f"{flag}={condition!r}: {err}") from None
