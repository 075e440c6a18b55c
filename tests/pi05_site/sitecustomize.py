"""Loaded at start-up by Python when this folder is on PYTHONPATH: makes a subprocess (stock `lerobot-train`,
`lerobot-eval`) build the tiny π0.5 of `pi05_tiny` when CONDGROUND_TINY_PI05=1."""

import os

if os.environ.get("CONDGROUND_TINY_PI05") == "1":
    import pi05_tiny

    pi05_tiny.activate()
