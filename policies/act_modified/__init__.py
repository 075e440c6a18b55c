"""The `act_modified` policy type (configuration / modeling / processor, as LeRobot's own policies)."""

from .configuration_act_modified import VARIANTS, ACTModifiedConfig  # noqa: F401
