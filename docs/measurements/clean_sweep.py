"""The examples' shared step: one checkpoint's `condground sweep` on clean scenes, reused once it finished."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pandas as pd

from lerobot_condground.evaluation.results import read_table


def clean_sweep(checkpoint: Path, task: str, out: Path, *flags: str) -> pd.DataFrame:
    """The rows of `out/results.parquet` by layout seed; `flags` are more `condground sweep` flags."""
    if not (out / "results.parquet").exists():
        subprocess.run(
            [
                str(Path(sys.executable).parent / "condground"),
                "sweep",
                f"--policy.paths={checkpoint}",
                f"--env.task={task}",
                "--sweep.conditions=clean",
                *flags,
                f"--output_dir={out}",
                "--progress=false",
            ],
            check=True,
        )
    return read_table(out / "results.parquet").sort_values("layout_seed", ignore_index=True)
