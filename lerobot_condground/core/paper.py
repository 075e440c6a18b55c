"""The paper's reference numbers (`shared/paper/what-matters-when.tex`, Results), in one place.

Every table, report and command that prints "paper" beside a measurement reads it from here.
"""

from __future__ import annotations

# The act_modified variant that reproduces each of the paper's methods; stock `act` counts as `standard`.
METHODS = {"standard": "Standard ACT", "augmentation": "Augmentation only", "full": "ACT-Modified"}

# Table I, simulation, 600 rollouts per cell, full mixed distractors: success in %.
TABLE1 = {
    "standard": {"PickPlaceFixedBin-v0": 39.5, "PickPlaceRandomBin-v0": 14.0},
    "augmentation": {"PickPlaceFixedBin-v0": 100.0, "PickPlaceRandomBin-v0": 64.0},
    "full": {"PickPlaceFixedBin-v0": 94.5, "PickPlaceRandomBin-v0": 88.5},
}

# Stage metrics of standard ACT quoted in the text, in %.
STAGES = {
    ("PickPlaceFixedBin-v0", "clean"): "success 98.5",
    ("PickPlaceRandomBin-v0", "clean"): "success 99.7",
    ("PickPlaceRandomBin-v0", "object_color_3"): "P(pick) 39.2, P(lift|pick) 93.8, P(place|pick,lift) 95.5",
    ("PickPlaceRandomBin-v0", "receptacle_shape_2"): "P(pick) 97.5, P(place|pick,lift) 33.9",
}

# Table II, Task 2 decoder state: Standard ACT, augmentation-only ACT, ACT-Modified.
# phase_retained and conditional_placement in %, as printed in the paper (and as `diagnose` writes them).
TABLE2 = {
    "Standard": {
        "place_shift": 0.1993,
        "phase_retained": 13.1,
        "container_silhouette": 0.0095,
        "conditional_placement": 33.3,
    },
    "DataAug": {
        "place_shift": 0.0011,
        "phase_retained": 94.8,
        "container_silhouette": 0.0889,
        "conditional_placement": 66.3,
    },
    "Modified": {
        "place_shift": 0.0125,
        "phase_retained": 108.5,
        "container_silhouette": 0.2037,
        "conditional_placement": 100.0,
    },
}
TABLE2_UNITS = {
    "place_shift": "1 - cos",
    "phase_retained": "%",
    "container_silhouette": "silhouette",
    "conditional_placement": "%",
}
# Which Table II column a checkpoint corresponds to, by policy label.
TABLE2_COLUMN = {
    "act": "Standard",
    "act_modified/standard": "Standard",
    "act_modified/augmentation": "DataAug",
    "act_modified/full": "Modified",
}

# The cup-selection probe: competitor selection in %, with the target's prompt and with it swapped.
PROBE = {"target": (0, 1), "swapped": (35, 91)}


def probe_range(arm: str, dash: str = "-") -> str:
    low, high = PROBE[arm]
    return f"{low}{dash}{high} %"


# The VLA case study (π0.5 fine-tuned for instrument routing): successes / trials over the five subgoals
# (5 trials each) and over the two routing subgoals (route, place), per `condground subgoals` condition.
# The paper gives no split per subgoal; it says the remaining subgoals were unaffected, so each of them
# went 5/5 in every condition (overall minus routing: 15/15).
SUBGOAL_STUDY = {
    "cue": {"method": "prompt-trained, with its RGB cue", "overall": (25, 25), "routing": (10, 10)},
    "no_cue": {"method": "prompt-trained, cue hidden", "overall": (20, 25), "routing": (5, 10)},
    "explicit": {"method": "regularized, explicit text", "overall": (25, 25), "routing": (10, 10)},
}
SUBGOAL_TRIALS = 5
