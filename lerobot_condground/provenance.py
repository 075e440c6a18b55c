"""What every diagnosis output records about how it was made: package versions and the command."""

from __future__ import annotations

import json
import platform
from importlib import metadata

PACKAGES = ("lerobot", "torch", "mujoco", "lerobot_policy_condground")


def versions() -> dict:
    out = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def command_line(subcommand: str, cfg) -> list[str]:
    """The `condground <subcommand> --group.key=value ...` line that reproduces cfg, defaults included."""
    import draccus

    def flatten(prefix: str, value) -> list[str]:
        if isinstance(value, dict):
            return [arg for key, sub in value.items() for arg in flatten(f"{prefix}{key}.", sub)]
        if value is None:
            return []
        text = json.dumps(value) if isinstance(value, bool) else str(value)
        return [f"--{prefix[:-1]}={text}"]

    return ["condground", subcommand, *flatten("", draccus.encode(cfg))]
