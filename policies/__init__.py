"""Policies of the plugin: `act_modified` (LeRobot's ACT with the paper's interventions) and `pi05_grounded`
(LeRobot's π0.5 with the VLA study's cue, instruction and attention regularizer)."""

from . import (
    act_modified,  # noqa: F401  registers the policy type
    pi05_grounded,  # noqa: F401
)
