"""Reading and checking the output directories of `condground sweep`, `subgoals`, `diagnose`, `probe`,
`attention` and `compare` (its comparison folder).

Each directory is recognised by the JSON its command wrote; any inconsistency is one ValueError naming the
directory, raised before anything is written.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from lerobot_condground.core.conditions import ROUTING_TASK
from lerobot_condground.core.files import read_json_object
from lerobot_condground.evaluation.results import (
    EPISODE_KEY,
    check_rows_against_runs,
    read_metadata,
    read_table,
    refuse_contradictions,
    refuse_rows_outside,
    scene_distribution,
)

KIND_FILES = {
    "sweep.json": "sweep",
    "subgoals.json": "subgoals",
    "diagnostics.json": "diagnose",
    "probe.json": "probe",
    "attention.json": "attention",
    "compare.json": "compare",
}
# The numbers of a comparison's summary row the report shows: anything else in the JSON is not read.
COMPARISON_NUMBERS = ("seeds", "n", "baseline", "treated", "diff", "diff_low", "diff_high", "p", "cluster_low",
                      "cluster_high", "cluster_p")  # fmt: skip
# One trial of `condground subgoals`: the same weights on the same layout under the same condition and scorer.
TRIAL_KEY = ("checkpoint_hash", "condition", "subgoal", "layout_seed", "scored_by")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@dataclass
class Inputs:
    results: pd.DataFrame  # every sweep's episodes, with `source` = the input directory
    subgoals: pd.DataFrame  # every subgoals directory's trials, with `source`
    sources: list[tuple[Path, dict]]  # (directory, its JSON) in the order given, for provenance
    diagnostics: list[tuple[Path, dict]]
    probes: list[tuple[Path, dict]]
    attention: list[tuple[Path, dict]]
    comparisons: list[tuple[Path, dict]]


def _load_sweep(folder: Path, manifest: dict) -> pd.DataFrame:
    path = folder / "results.parquet"
    if not path.is_file():
        raise ValueError(
            f"{folder}: sweep.json without results.parquet; the sweep did not finish or the file was moved"
        )
    try:
        frame = read_table(path)
    except ValueError as err:
        raise ValueError(f"{folder}: {err}") from None
    grid = manifest.get("grid")
    if not isinstance(grid, dict) or "task" not in grid or "conditions" not in grid:
        raise ValueError(f"{folder}: sweep.json has no grid with task and conditions")
    written = read_metadata(path).get("grid")
    if written != grid:
        keys = sorted(k for k in set(grid) | set(written or {}) if (written or {}).get(k) != grid.get(k))
        raise ValueError(
            f"{folder}: results.parquet was written for another grid than sweep.json (differs in {keys})"
        )
    problems = []
    if set(frame["task"]) - {grid["task"]}:
        problems.append(f"tasks {sorted(set(frame['task']))} but the grid's task is {grid['task']!r}")
    if set(frame["condition"]) != set(grid["conditions"]):
        problems.append(
            f"conditions {sorted(set(frame['condition']))} but the grid lists {sorted(grid['conditions'])}"
        )
    hashes = {c.get("hash") for c in manifest.get("checkpoints", [])}
    if set(frame["checkpoint_hash"]) != hashes:
        problems.append(
            f"checkpoint hashes {sorted(set(frame['checkpoint_hash']))} but sweep.json lists {sorted(hashes)}"
        )
    if problems:
        raise ValueError(f"{folder}: results.parquet does not match sweep.json: {'; '.join(problems)}")
    listed = {(c.get("label"), c.get("hash")) for c in manifest.get("checkpoints", [])}
    refuse_rows_outside(
        path, frame, ["policy_label", "checkpoint_hash"], lambda label, h: (label, h) in listed, "sweep.json"
    )
    _refuse_repeats(folder, frame, EPISODE_KEY, "episode")
    refuse_contradictions(path, frame)
    if suffix := scene_distribution(grid):
        frame = frame.assign(condition=frame["condition"] + suffix)
    return frame.assign(source=str(folder))


def _load_subgoals(folder: Path, manifest: dict) -> pd.DataFrame:
    path = folder / "results.parquet"
    if not path.is_file():
        raise ValueError(f"{folder}: subgoals.json without results.parquet; no trial has finished there")
    try:
        frame = read_table(path)
    except ValueError as err:
        raise ValueError(f"{folder}: {err}") from None
    runs = manifest.get("runs")
    if not isinstance(runs, dict):
        raise ValueError(f"{folder}: subgoals.json has no runs")
    problems = []
    if set(frame["task"]) - {ROUTING_TASK}:
        problems.append(f"tasks {sorted(set(frame['task']))}, not {ROUTING_TASK}")
    if frame["subgoal"].isna().any():
        problems.append("rows without a subgoal")
    if set(frame["condition"]) - set(runs):
        problems.append(f"conditions {sorted(set(frame['condition']))} but subgoals.json runs {sorted(runs)}")
    if problems:
        raise ValueError(f"{folder}: results.parquet does not match subgoals.json: {'; '.join(problems)}")
    check_rows_against_runs(path, frame, runs)
    _refuse_repeats(folder, frame, TRIAL_KEY, "trial")
    return frame.assign(source=str(folder))


def _refuse_repeats(folder: Path, frame: pd.DataFrame, key, what: str) -> None:
    dup = frame.duplicated(list(key), keep=False)
    if dup.any():
        example = frame.loc[dup, list(key)].iloc[0].to_dict()
        raise ValueError(
            f"{folder}: results.parquet holds {int(dup.sum())} rows with a repeated {what}, e.g. {example}"
        )


def _check_files(folder: Path, rels, what: str) -> None:
    for rel in rels:
        path = folder / str(rel)
        # The JSON is input like any other: a path out of its folder would put any PNG on disk in the report.
        if not path.resolve().is_relative_to(folder.resolve()):
            raise ValueError(f"{folder}: {what} {rel!r} listed in its JSON is outside {folder}")
        if not path.is_file():
            raise ValueError(f"{folder}: {what} {rel!r} listed in its JSON does not exist")
        with path.open("rb") as fh:
            if fh.read(8) != PNG_MAGIC:
                raise ValueError(f"{folder}: {what} {rel!r} is not a PNG image")


def _check_comparison(folder: Path, data: dict) -> None:
    """A comparison's summary rows must be what `condground compare` writes: numbers where numbers belong."""
    rows = data.get("summary")
    if not isinstance(rows, list) or not rows or not all(isinstance(r, dict) for r in rows):
        raise ValueError(f"{folder}: compare.json has no summary rows; the comparison did not finish")
    for row in rows:
        for key in COMPARISON_NUMBERS:
            value = row.get(key)
            if value is not None and (isinstance(value, bool) or not isinstance(value, int | float)):
                raise ValueError(f"{folder}: compare.json's summary has {key}={value!r}; allowed: a number")
    _check_files(folder, [data.get("figure") or "compare.png"], "figure")


def load_inputs(dirs: list[str]) -> Inputs:
    """Reads and checks every input directory; any inconsistency is one ValueError naming the directory."""
    if not dirs:
        raise ValueError(
            "No input directories: give --input_dir=DIR (repeatable) with sweep, subgoals, diagnose, probe, "
            "attention or compare outputs"
        )
    frames, subgoals, sources, diagnostics, probes, attention, comparisons = [], [], [], [], [], [], []
    seen: set[Path] = set()
    for raw in dirs:
        folder = Path(raw)
        if not folder.is_dir():
            raise ValueError(f"{folder}: not a directory")
        if folder.resolve() in seen:
            raise ValueError(f"{folder}: given twice as --input_dir; its episodes would count double")
        seen.add(folder.resolve())
        found = [(name, kind) for name, kind in KIND_FILES.items() if (folder / name).is_file()]
        if not found:
            raise ValueError(
                f"{folder}: none of {', '.join(KIND_FILES)} found; give the --output_dir of condground "
                "sweep, subgoals, diagnose, probe or attention, or a comparison folder of condground compare"
            )
        for name, kind in found:
            data = read_json_object(folder / name, "Input")
            if data.get("kind") != kind:
                raise ValueError(f"{folder}: {name} says kind {data.get('kind')!r}, expected {kind!r}")
            sources.append((folder, data))
            if kind == "sweep":
                frames.append(_load_sweep(folder, data))
            elif kind == "subgoals":
                subgoals.append(_load_subgoals(folder, data))
            elif kind == "diagnose":
                _check_files(folder, (data.get("figures") or {}).values(), "figure")
                diagnostics.append((folder, data))
            elif kind == "probe":
                probes.append((folder, data))
            elif kind == "compare":
                _check_comparison(folder, data)
                comparisons.append((folder, data))
            else:
                _check_files(folder, data.get("stills") or [], "still")
                attention.append((folder, data))
    results = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    if len(frames) > 1:
        _refuse_overlap(results, EPISODE_KEY, "sweep")
    trials = pd.concat(subgoals, ignore_index=True) if subgoals else pd.DataFrame()
    if len(subgoals) > 1:
        _refuse_overlap(trials, TRIAL_KEY, "subgoals")
    return Inputs(results, trials, sources, diagnostics, probes, attention, comparisons)


def _refuse_overlap(results: pd.DataFrame, keys: tuple[str, ...], kind: str) -> None:
    """The same episode of the same weights in two directories would be counted twice."""
    what = "episodes" if kind == "sweep" else "trials"
    per_key = results.groupby(list(keys), sort=False)["source"].nunique()
    clash = per_key[per_key > 1]
    if len(clash):
        key = dict(zip(keys, clash.index[0], strict=True))
        mask = np.logical_and.reduce([results[k] == v for k, v in key.items()])
        folders = sorted(set(results.loc[mask, "source"]))
        raise ValueError(
            f"{len(clash)} {what} appear in more than one {kind} directory ({' and '.join(folders)}), e.g. "
            f"{key}; give each {kind} directory once, or separate runs of the same checkpoints by condition or "
            "seed"
        )
