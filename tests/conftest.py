import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

BIN = Path(sys.executable).parent


def run_cli(*args: str, cwd: Path | None = None, timeout: float = 600, check: bool = True) -> subprocess.CompletedProcess:
    """Runs an installed console script (condground, lerobot-eval, ...) in a subprocess."""
    env = {**os.environ, "MUJOCO_GL": "egl", "HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled"}
    proc = subprocess.run(
        [str(BIN / args[0]), *args[1:]], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
    )
    if check and proc.returncode != 0:
        raise AssertionError(f"{' '.join(args)} failed ({proc.returncode}):\n{proc.stdout[-4000:]}\n{proc.stderr[-6000:]}")
    return proc


@pytest.fixture(scope="session")
def recorded_dataset(tmp_path_factory) -> Path:
    """Two expert episodes of Task 2 under full_mixed, written by `condground record`."""
    root = tmp_path_factory.mktemp("data") / "full_mixed"
    proc = run_cli(
        "condground", "record", "--env.task=PickPlaceRandomBin-v0", "--env.condition=full_mixed",
        "--dataset.repo_id=local/test_full_mixed", f"--dataset.root={root}", "--dataset.num_episodes=2",
        "--progress=false",
    )
    assert "expert success: 2/2" in proc.stdout, proc.stdout
    return root


@pytest.fixture(scope="session")
def plain_dataset(tmp_path_factory) -> Path:
    """One expert episode of Task 2 under full_mixed without label features, for stock policies."""
    root = tmp_path_factory.mktemp("data") / "plain"
    run_cli(
        "condground", "record", "--env.task=PickPlaceRandomBin-v0", "--env.condition=full_mixed",
        "--dataset.repo_id=local/test_plain", f"--dataset.root={root}", "--dataset.num_episodes=1",
        "--dataset.labels=false", "--progress=false",
    )
    return root


def read_json(path: Path) -> dict:
    return json.loads(Path(path).read_text())
