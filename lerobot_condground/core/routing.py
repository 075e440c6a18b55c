"""InstrumentRouting-v0's vocabulary, shared by the env, the recording, the processors and the evaluation:
procedure steps, subgoals, instructions, sides, segmentation labels. Nothing here needs MuJoCo.

The rule: a contaminated (marked) instrument goes to the left container, a clean one to the right, left
and right as the robot sees them (its base facing the table along +x: left is +y).
"""

from __future__ import annotations

from lerobot_condground.core.configs import comma_items

STEPS = ("approach", "pick", "inspect", "route", "place", "retreat", "home")
SUBGOALS = ("pick", "inspect", "route", "place", "home")
# The subgoals whose correct destination depends on the instrument's state.
ROUTING_SUBGOALS = ("route", "place")
EPISODES = ("procedure", *SUBGOALS)
INSTRUCTION_FORMS = ("generic", "explicit")
SIDES = ("left", "right")
DESTINATION_OF = {True: "left", False: "right"}  # contaminated -> side
# Segmentation labels: 0 background and robot, then these.
INSTRUMENT, DESTINATION, OTHER_CONTAINER, STATE_REGION = 1, 2, 3, 4

_INSTRUCTIONS = {
    "pick": "pick up the instrument",
    "inspect": "show the instrument to the inspection camera",
    "route": "move the instrument over the {} container",
    "place": "put the instrument into the {} container",
    "home": "return the arm to its home pose",
}


def instruction(subgoal: str, form: str = "generic", destination: str | None = None) -> str:
    """The subgoal's instruction: generic ("... the highlighted container") or explicit ("... the left
    container"; needs the destination)."""
    if subgoal not in _INSTRUCTIONS:
        raise ValueError(f"Unknown subgoal {subgoal!r}; allowed: {', '.join(SUBGOALS)}")
    if form not in INSTRUCTION_FORMS:
        raise ValueError(f"Unknown instruction form {form!r}; allowed: {', '.join(INSTRUCTION_FORMS)}")
    if form == "explicit" and subgoal in ROUTING_SUBGOALS and destination not in SIDES:
        raise ValueError(f"The explicit {subgoal} instruction needs the destination; got {destination!r}")
    return _INSTRUCTIONS[subgoal].format("highlighted" if form == "generic" else destination)


def parse_episodes(text: str) -> tuple[str, ...]:
    """`procedure`, a subgoal, or several of them separated by commas."""
    items = tuple(comma_items(text, "subgoal"))
    bad = [t for t in items if t not in EPISODES]
    if not items or bad or len(set(items)) != len(items):
        raise ValueError(
            f"subgoal={text!r} is not allowed; allowed: {', '.join(EPISODES)}, or several of them "
            "separated by commas, each once"
        )
    return items


# What must be looked at in each procedure step (eq. (1) of `pi05_grounded`): the instrument while it is
# acquired, its state region while it is inspected, the destination while it is routed and placed, with the
# other container as the distractor. Retreating and going home have no referent and are not supervised.
RELEVANT_LABEL = {
    "approach": INSTRUMENT,
    "pick": INSTRUMENT,
    "inspect": STATE_REGION,
    "route": DESTINATION,
    "place": DESTINATION,
}
DISTRACTOR_LABEL = {"route": OTHER_CONTAINER, "place": OTHER_CONTAINER}


def step_masks(segmentation, phase):
    """(M_phi, M_d) for label maps (B, H, W) and procedure steps (B,) (`observation.phase`), as torch bools.
    Steps without a referent get an empty M_phi."""
    import torch

    def table(labels: dict) -> torch.Tensor:
        return torch.tensor([labels.get(step, -1) for step in STEPS], device=segmentation.device)

    phase = phase.reshape(-1).long().to(segmentation.device)
    if phase.numel() and not bool(((phase >= 0) & (phase < len(STEPS))).all()):
        raise ValueError(
            f"observation.phase holds {sorted(set(phase.tolist()))}; allowed: 0..{len(STEPS) - 1} ({', '.join(STEPS)})"
        )
    per_sample = (-1,) + (1,) * (segmentation.ndim - 1)
    relevant = table(RELEVANT_LABEL)[phase].view(per_sample)
    distractor = table(DISTRACTOR_LABEL)[phase].view(per_sample)
    segmentation = segmentation.long()
    return (segmentation == relevant) & (relevant >= 0), (segmentation == distractor) & (distractor >= 0)
