"""The per-episode results table of the diagnosis commands: its columns, and safe reading and writing.

One row per episode. Identity columns say which policy ran where; outcome columns are what
`rollout.outcome` (pick-and-place) or `rollout.routing_outcome` (InstrumentRouting-v0) reads off the env,
or what an operator scored on hardware; a column an episode cannot know is null. Files are written to a
temporary name and renamed, so a killed process never leaves a half-written table under the real name.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

IDENTITY_COLUMNS = (
    "policy_label",
    "policy_type",
    "variant",
    "checkpoint",
    "checkpoint_hash",
    "training_seed",
    "task",
    "condition",
    "condition_spec",
    "counterbalanced",
    "eval_seed",
    "episode",
    "layout_seed",
    "prompt",
)
OUTCOME_COLUMNS = (
    "stage",
    "success",
    "pick",
    "lift",
    "place",
    "grasped_first",
    "grasped_first_match",
    "grasped_competitor",
    "grasped_competitor_match",
    "selected_competitor_object",
    "target_location",
    "competitor_location",
    "placed_in_competitor_receptacle",
    "target_x",
    "target_y",
    "target_z",
    "competitor_x",
    "competitor_y",
    "competitor_z",
    "receptacle_x",
    "receptacle_y",
    "steps",
    "truncated",
    "physics_unstable",
)
COLUMNS = IDENTITY_COLUMNS + OUTCOME_COLUMNS
# Columns added after the first tables were written: an older table lacks them and reads as if they were
# null. subgoal, destination, route_choice and placed_in are InstrumentRouting-v0's (see
# envs/routing_env.py); scored_by says who judged success: "env", or "operator" on hardware.
LATER_COLUMNS = ("subgoal", "destination", "route_choice", "placed_in", "scored_by")
TABLE_COLUMNS = COLUMNS + LATER_COLUMNS
# One episode: the same weights on the same layout under the same condition and prompt. Sweeps of one
# checkpoint with different seed offsets hold different layouts and may be combined.
EPISODE_KEY = ("checkpoint_hash", "task", "condition", "eval_seed", "episode", "layout_seed", "prompt")
METADATA_KEY = b"condground"


def scene_distribution(grid: dict) -> str:
    """What sets a sweep's scenes apart from the plain scenes of its conditions, as a suffix to their names
    ("" for the protocol's own): counterbalanced targets and augmentation competitors are other distributions,
    which every table keeps apart and the matched-pair analyses refuse."""
    suffix = " (counterbalanced)" if grid.get("counterbalanced") else ""
    if grid.get("competitor_pool", "eval") != "eval":
        suffix += " (augmentation competitors)"
    return suffix


def write_table(rows: list[dict] | pd.DataFrame, path: Path, metadata: dict | None = None) -> None:
    frame = rows if isinstance(rows, pd.DataFrame) else pd.DataFrame(rows, columns=list(TABLE_COLUMNS))
    frame = frame.assign(**{c: None for c in LATER_COLUMNS if c not in frame.columns})
    table = pa.Table.from_pandas(frame[list(TABLE_COLUMNS)], preserve_index=False)
    if metadata is not None:
        table = table.replace_schema_metadata(
            {**(table.schema.metadata or {}), METADATA_KEY: json.dumps(metadata).encode()}
        )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    pq.write_table(table, tmp)
    os.replace(tmp, path)


def read_table(path: Path) -> pd.DataFrame:
    """A results table; one clear error if the file is unreadable or lacks columns."""
    try:
        frame = pq.read_table(path).to_pandas()
    except Exception as err:  # pyarrow raises several types for damaged files
        raise ValueError(
            f"Results file {path} is corrupted or not a parquet table ({type(err).__name__}: {err})"
        ) from None
    missing = [c for c in COLUMNS if c not in frame.columns]
    if missing:
        raise ValueError(f"Results file {path} lacks columns {missing}; it was not written by condground")
    return frame.assign(**{c: None for c in LATER_COLUMNS if c not in frame.columns})


def read_metadata(path: Path) -> dict:
    metadata = pq.read_schema(path).metadata or {}
    return json.loads(metadata[METADATA_KEY]) if METADATA_KEY in metadata else {}


def refuse_contradictions(path: Path, frame: pd.DataFrame) -> None:
    """Pick-and-place rows whose outcome columns contradict each other (success without the placement, a
    placement without the lift, a stage that is not the count of stages reached) were edited, not measured:
    refused, naming the file and the first such episode."""
    from lerobot_condground.core.conditions import ROUTING_TASK

    rows = frame[frame["task"] != ROUTING_TASK]
    pick, lift, place = (rows[c].astype(bool) for c in ("pick", "lift", "place"))
    bad = (rows["success"].astype(bool) != place) | (place & ~lift) | (lift & ~pick)
    bad |= rows["stage"] != pick.astype(int) + lift.astype(int) + place.astype(int)
    if bad.any():
        row = rows[bad].iloc[0]
        raise ValueError(
            f"{path}: {int(bad.sum())} rows contradict themselves, e.g. episode {row['episode']} of "
            f"{row['policy_label']!r} under {row['condition']!r}: success={bool(row['success'])} with pick, lift, "
            f"place = {bool(row['pick'])}, {bool(row['lift'])}, {bool(row['place'])} and stage {row['stage']}; "
            "the table was edited after the sweep wrote it"
        )


def refuse_rows_outside(path: Path, frame, columns: list[str], belongs, manifest: str) -> None:
    """Raises naming the first row of `frame` (read from `path`) whose `columns` values `belongs` rejects:
    a row the run's manifest never asked for is an error, never counted, never dropped."""
    if not len(frame):
        return
    ok = [bool(belongs(*values)) for values in frame[columns].itertuples(index=False, name=None)]
    if not all(ok):
        i = ok.index(False)
        values = [frame[c].iloc[i] for c in columns]
        row = ", ".join(
            f"{c}={v.item() if hasattr(v, 'item') else v!r}" for c, v in zip(columns, values, strict=True)
        )
        raise ValueError(
            f"{path}: row {i} ({row}) is not part of the run {manifest} describes ({ok.count(False)} such rows); "
            "rows outside the manifest are never counted: rerun into a new --output_dir"
        )


def check_rows_against_runs(path: Path, rows: pd.DataFrame, runs: dict) -> None:
    """Every trial row belongs to a run of the manifest: its condition, one of its subgoals, a trial below
    its trial count, its checkpoint."""

    def belongs(condition, subgoal, episode, checkpoint_hash) -> bool:
        run = runs.get(condition)
        return (
            isinstance(run, dict)
            and subgoal in run.get("subgoals", [])
            and 0 <= episode < run.get("trials", 0)
            and checkpoint_hash == (run.get("checkpoint") or {}).get("hash")
        )

    columns = ["condition", "subgoal", "episode", "checkpoint_hash"]
    refuse_rows_outside(path, rows, columns, belongs, "subgoals.json")
