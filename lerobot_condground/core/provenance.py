"""How an output was made: package versions and the command of diagnosis outputs, and the files this package
writes into a dataset's meta/ folder to say how the dataset was made."""

from __future__ import annotations

import json
import platform
import sys
from importlib import metadata
from pathlib import Path

PACKAGES = ("lerobot", "torch", "mujoco", "lerobot_policy_condground")

# By `condground record`, `augment` and `prompts`; an augmented copy keeps its source's record file.
RECORD_FILE = "meta/condground_record.json"
AUGMENT_FILE = "meta/condground_augment.json"
PROMPTS_FILE = "meta/condground_prompts.json"


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


def console_script(name: str) -> str:
    """A console script installed beside this interpreter (condground, lerobot-train): found without PATH,
    which `make test` and a cron job need not have."""
    return str(Path(sys.executable).parent / name)
