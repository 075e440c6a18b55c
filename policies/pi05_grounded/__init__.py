"""The `pi05_grounded` policy type (configuration / modeling / processor, as LeRobot's own policies)."""

from .configuration_pi05_grounded import VARIANTS, PI05GroundedConfig  # noqa: F401
