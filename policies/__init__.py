"""Policies of the plugin: `act_modified` (LeRobot's ACT with the paper's interventions)."""

from . import act_modified  # noqa: F401  registers the policy type
