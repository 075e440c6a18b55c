"""Session fixtures: recorded datasets and small checkpoints, made once per test run."""

import os
from pathlib import Path

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")
# An xdist worker gets its share of the cores, and so do the subprocesses it starts (they inherit these):
# with two workers of two threads each on 2 cores, a CPU-bound test ran 3-4x slower than on one thread.
if workers := int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0")):
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, str(max(1, (os.cpu_count() or 1) // workers)))

import lerobot_policy_condground  # noqa: E402, F401  (registers the plugin, as LeRobot's discovery does)
from helpers import make_checkpoint, run_cli  # noqa: E402


@pytest.fixture(scope="session")
def recorded_dataset(tmp_path_factory) -> Path:
    """Two expert episodes of Task 2 under full_mixed, written by `condground record`."""
    root = tmp_path_factory.mktemp("data") / "full_mixed"
    proc = run_cli(
        "condground",
        "record",
        "--env.task=PickPlaceRandomBin-v0",
        "--env.condition=full_mixed",
        "--dataset.repo_id=local/test_full_mixed",
        f"--dataset.root={root}",
        "--dataset.num_episodes=2",
        "--progress=false",
    )
    assert "expert success: 2/2" in proc.stdout, proc.stdout
    return root


@pytest.fixture(scope="session")
def plain_dataset(tmp_path_factory) -> Path:
    """One expert episode of Task 2 under full_mixed without label features, for stock policies."""
    root = tmp_path_factory.mktemp("data") / "plain"
    run_cli(
        "condground",
        "record",
        "--env.task=PickPlaceRandomBin-v0",
        "--env.condition=full_mixed",
        "--dataset.repo_id=local/test_plain",
        f"--dataset.root={root}",
        "--dataset.num_episodes=1",
        "--dataset.labels=false",
        "--progress=false",
    )
    return root


@pytest.fixture(scope="session")
def act_checkpoint(tmp_path_factory) -> Path:
    """A small stock LeRobot ACT checkpoint (random weights, 96x128 camera)."""
    return make_checkpoint(tmp_path_factory.mktemp("act") / "act", policy_type="act")


@pytest.fixture(scope="session")
def tiny_checkpoints(tmp_path_factory) -> list[Path]:
    """Two act_modified/full checkpoints (training seeds 0 and 1), random weights, 96x128 camera, with the
    paper's phase predictor (the most a diagnosis has to read)."""
    root = tmp_path_factory.mktemp("checkpoints")
    return [make_checkpoint(root / f"seed{seed}", seed=seed, phase_predictor=True) for seed in (0, 1)]


@pytest.fixture(scope="session")
def routing_dataset(tmp_path_factory) -> Path:
    """Three expert episodes of InstrumentRouting-v0 at 96x128 (the whole procedure, or `place` from its
    start), with both cameras, both segmentations and the destination."""
    root = tmp_path_factory.mktemp("routing") / "data"
    out = run_cli(
        "condground", "record", "--env.task=InstrumentRouting-v0", "--env.subgoal=procedure,place",
        "--env.observation_height=96", "--env.observation_width=128", "--dataset.repo_id=local/routing",
        f"--dataset.root={root}", "--dataset.num_episodes=3", "--progress=false",
    )  # fmt: skip
    assert "expert success: 3/3" in out.stdout, out.stdout
    return root
