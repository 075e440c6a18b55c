"""`condground report`: sweep and diagnosis outputs -> one self-contained HTML report and a Markdown twin.

Each input directory is recognised by the JSON its command wrote (`sweep.json`, `diagnostics.json`,
`probe.json`, `attention.json`). The report is built once as a list of blocks (headings, paragraphs,
tables, figures) and rendered twice: HTML with every PNG inlined as a data URI, so the file can be
mailed or archived alone, and Markdown with the PNGs written to `FILE_files/` beside it.
"""

from __future__ import annotations

import base64
import html
import io
import json
import math
import platform
import re
import shlex
from dataclasses import dataclass, field
from importlib.metadata import version
from pathlib import Path

import draccus
import numpy as np
import pandas as pd

from lerobot_condground.conditions import PAPER_GRID, TASKS
from lerobot_condground.results import read_metadata, read_table
from lerobot_condground.statistics import (
    CELL,
    METRIC_TITLES,
    METRICS,
    cell_metrics,
    condition_differences,
    variant_differences,
)

KIND_FILES = {
    "sweep.json": "sweep", "diagnostics.json": "diagnose", "probe.json": "probe", "attention.json": "attention",
}
# One episode: the same weights on the same layout under the same condition and prompt. Sweeps of one
# checkpoint with different seed offsets hold different layouts and may be combined.
EPISODE_KEY = ("checkpoint_hash", "task", "condition", "eval_seed", "episode", "layout_seed", "prompt")
TASK_SHORT = {"PickPlaceFixedBin-v0": "T1", "PickPlaceRandomBin-v0": "T2"}
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"

# The paper's numbers (Results section), keyed by the act_modified variant that reproduces each row;
# stock `act` counts as `standard`.
PAPER_METHODS = {"standard": "Standard ACT", "augmentation": "Augmentation only", "full": "ACT-Modified"}
PAPER_TABLE1 = {  # Table I, simulation, 600 rollouts per cell, full mixed distractors, success %
    "standard": {"PickPlaceFixedBin-v0": 39.5, "PickPlaceRandomBin-v0": 14.0},
    "augmentation": {"PickPlaceFixedBin-v0": 100.0, "PickPlaceRandomBin-v0": 64.0},
    "full": {"PickPlaceFixedBin-v0": 94.5, "PickPlaceRandomBin-v0": 88.5},
}
PAPER_STAGES = {  # stage metrics of standard ACT quoted in the text, %
    ("PickPlaceFixedBin-v0", "clean"): "success 98.5",
    ("PickPlaceRandomBin-v0", "clean"): "success 99.7",
    ("PickPlaceRandomBin-v0", "object_color_3"): "P(pick) 39.2, P(lift|pick) 93.8, P(place|pick,lift) 95.5",
    ("PickPlaceRandomBin-v0", "receptacle_shape_2"): "P(pick) 97.5, P(place|pick,lift) 33.9",
}
TABLE2_ROWS = {  # key in diagnostics.json "table2" -> row title
    "place_shift": "Place shift ↓",
    "phase_retained": "Phase retained ↑",
    "container_silhouette": "Container silhouette ↑",
    "conditional_placement": "Conditional placement ↑",
}
# `condground diagnose` writes these two in percent and says so in `table2_units`.
TABLE2_PERCENT = {"phase_retained", "conditional_placement"}
PAPER_TABLE2 = {  # Table II, Task 2 decoder state, in the units diagnose writes
    "Standard": dict(place_shift=0.1993, phase_retained=13.1, container_silhouette=0.0095, conditional_placement=33.3),
    "DataAug": dict(place_shift=0.0011, phase_retained=94.8, container_silhouette=0.0889, conditional_placement=66.3),
    "Modified": dict(place_shift=0.0125, phase_retained=108.5, container_silhouette=0.2037, conditional_placement=100.0),
}
PAPER_PROBE = {"target": "0–1 %", "swapped": "35–91 %"}
VARIANT_ORDER = ("standard", "augmentation", "augmentation_attention", "full")


@dataclass
class ReportConfig:
    # Output directories of `condground sweep`, `diagnose`, `probe` and `attention`, in any mix.
    # Repeat the flag or separate directories with commas.
    input_dir: list[str] = field(default_factory=list)
    # The HTML file; the Markdown version and its figure folder (FILE_files/) go beside it.
    output: str = "outputs/report/report.html"
    title: str = "Conditional visual grounding: diagnosis report"


def parse_report_args(argv: list[str]) -> ReportConfig:
    """draccus reads a list flag only as one YAML list (`--input_dir=[A,B]`); this also accepts the
    flag repeated (`--input_dir=A --input_dir=B`, `--input_dir A`) and comma-separated values."""
    dirs: list[str] = []
    rest: list[str] = []
    i = 0
    while i < len(argv):
        arg = argv[i]
        if arg.startswith("--input_dir="):
            value = arg.partition("=")[2]
        elif arg == "--input_dir" and i + 1 < len(argv):
            i += 1
            value = argv[i]
        else:
            rest.append(arg)
            i += 1
            continue
        i += 1
        value = value.strip()
        if value.startswith("[") and value.endswith("]"):
            value = value[1:-1]
        dirs += [v.strip().strip("'\"") for v in value.split(",") if v.strip()]
    cfg = draccus.parse(ReportConfig, args=rest, prog="condground report")
    cfg.input_dir = [*cfg.input_dir, *dirs]
    return cfg


# ---------------------------------------------------------------------------------------------- inputs


@dataclass
class Inputs:
    results: pd.DataFrame  # every sweep's episodes, with `source` = the input directory
    sources: list[tuple[Path, dict]]  # (directory, its JSON) in the order given, for provenance
    diagnostics: list[tuple[Path, dict]]
    probes: list[tuple[Path, dict]]
    attention: list[tuple[Path, dict]]


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"{path.parent}: {path.name} is not readable JSON ({err})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path.parent}: {path.name} holds {type(data).__name__}, not a JSON object")
    return data


def _load_sweep(folder: Path, manifest: dict) -> pd.DataFrame:
    path = folder / "results.parquet"
    if not path.is_file():
        raise ValueError(f"{folder}: sweep.json without results.parquet; the sweep did not finish or the file was moved")
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
        raise ValueError(f"{folder}: results.parquet was written for another grid than sweep.json (differs in {keys})")
    problems = []
    if set(frame["task"]) - {grid["task"]}:
        problems.append(f"tasks {sorted(set(frame['task']))} but the grid's task is {grid['task']!r}")
    if set(frame["condition"]) != set(grid["conditions"]):
        problems.append(f"conditions {sorted(set(frame['condition']))} but the grid lists {sorted(grid['conditions'])}")
    hashes = {c.get("hash") for c in manifest.get("checkpoints", [])}
    if set(frame["checkpoint_hash"]) != hashes:
        problems.append(f"checkpoint hashes {sorted(set(frame['checkpoint_hash']))} but sweep.json lists {sorted(hashes)}")
    if problems:
        raise ValueError(f"{folder}: results.parquet does not match sweep.json: {'; '.join(problems)}")
    dup = frame.duplicated(list(EPISODE_KEY), keep=False)
    if dup.any():
        example = frame.loc[dup, list(EPISODE_KEY)].iloc[0].to_dict()
        raise ValueError(f"{folder}: results.parquet holds {int(dup.sum())} rows with a repeated episode, e.g. {example}")
    return frame.assign(source=str(folder))


def _check_files(folder: Path, rels, what: str) -> None:
    for rel in rels:
        path = folder / rel
        if not path.is_file():
            raise ValueError(f"{folder}: {what} {rel!r} listed in its JSON does not exist")
        with path.open("rb") as fh:
            if fh.read(8) != PNG_MAGIC:
                raise ValueError(f"{folder}: {what} {rel!r} is not a PNG image")


def load_inputs(dirs: list[str]) -> Inputs:
    """Reads and checks every input directory; any inconsistency is one ValueError naming the directory."""
    if not dirs:
        raise ValueError(
            "No input directories: give --input_dir=DIR (repeatable) with sweep, diagnose, probe or attention outputs"
        )
    frames, sources, diagnostics, probes, attention = [], [], [], [], []
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
                f"{folder}: none of {', '.join(KIND_FILES)} found; give the --output_dir of condground sweep, "
                "diagnose, probe or attention"
            )
        for name, kind in found:
            data = _read_json(folder / name)
            if data.get("kind") != kind:
                raise ValueError(f"{folder}: {name} says kind {data.get('kind')!r}, expected {kind!r}")
            sources.append((folder, data))
            if kind == "sweep":
                frames.append(_load_sweep(folder, data))
            elif kind == "diagnose":
                _check_files(folder, (data.get("figures") or {}).values(), "figure")
                diagnostics.append((folder, data))
            elif kind == "probe":
                probes.append((folder, data))
            else:
                _check_files(folder, data.get("stills") or [], "still")
                attention.append((folder, data))
    results = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    if len(frames) > 1:
        _refuse_overlap(results)
    return Inputs(results, sources, diagnostics, probes, attention)


def _refuse_overlap(results: pd.DataFrame) -> None:
    """The same episode of the same weights in two sweep directories would be counted twice."""
    per_key = results.groupby(list(EPISODE_KEY), sort=False)["source"].nunique()
    clash = per_key[per_key > 1]
    if len(clash):
        key = dict(zip(EPISODE_KEY, clash.index[0]))
        mask = np.logical_and.reduce([results[k] == v for k, v in key.items()])
        folders = sorted(set(results.loc[mask, "source"]))
        raise ValueError(
            f"{len(clash)} episodes appear in more than one sweep directory ({' and '.join(folders)}), e.g. {key}; "
            "give each sweep once, or separate sweeps of the same checkpoints by condition or eval seed"
        )


# ---------------------------------------------------------------------------------------------- blocks


@dataclass
class Heading:
    text: str
    level: int = 2


@dataclass
class Para:
    text: str
    note: bool = False  # an omitted section's one-line explanation


@dataclass
class Table:
    id: str
    caption: str
    columns: list[str]
    rows: list[list[str]]
    groups: list[tuple[str, int]] | None = None  # header groups spanning consecutive columns


@dataclass
class Figure:
    name: str  # unique, file-name safe
    png: bytes
    caption: str


# ---------------------------------------------------------------------------------------------- formatting


def _pct(x: float, digits: int = 1) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100 * x:.{digits}f}"


def fmt_rate(k: int, n: int, low: float, high: float) -> str:
    if not n:
        return "n/a (0/0)"
    return f"{_pct(k / n)}% [{_pct(low)}, {_pct(high)}] ({int(k)}/{int(n)})"


def fmt_diff(d) -> str:
    if d is None or not d.get("n") or d.get("diff") is None or math.isnan(d["diff"]):
        return "n/a"
    p = d.get("p_value")
    p_text = "" if p is None else f", McNemar p={p:.3g}"
    return f"{100 * d['diff']:+.1f} pp [{100 * d['low']:+.1f}, {100 * d['high']:+.1f}] (n={d['n']}{p_text})"


def _fmt_number(value, percent: bool = False) -> str:
    """A diagnostic value: 4 decimals, or one decimal and % for values diagnose writes in percent."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "—"
    if not isinstance(value, (int, float)):
        return str(value)
    return f"{value:.1f}%" if percent else f"{value:.4f}"


def _seed_spread(row) -> str:
    seeds = int(row["training_seeds"])
    if seeds <= 1:
        return f"{_pct(row['success_seed_mean'])}% (1 seed)"
    return (f"{_pct(row['success_seed_mean'])}% ± {_pct(row['success_seed_std'])} "
            f"[{_pct(row['success_seed_min'])}, {_pct(row['success_seed_max'])}] ({seeds} seeds)")


def _metric_cell(row, metric: str) -> str:
    return fmt_rate(row[f"{metric}_k"], row[f"{metric}_n"], row[f"{metric}_low"], row[f"{metric}_high"])


def _task_title(task: str) -> str:
    return f"{TASK_SHORT[task]} {task}" if task in TASK_SHORT else task


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "-", text).strip("-").lower() or "figure"


# ---------------------------------------------------------------------------------------------- ordering


def _method(policy_type: str, variant: str, label: str) -> str | None:
    """Which of the paper's methods a policy is, from its type and act_modified variant."""
    if policy_type == "act" or label == "act":
        return "standard"
    if policy_type == "act_modified" and variant:
        return variant
    if label.startswith("act_modified/"):
        return label.partition("/")[2]
    return None


def _label_methods(results: pd.DataFrame) -> dict[str, str | None]:
    first = results.drop_duplicates("policy_label")
    return {r.policy_label: _method(r.policy_type, r.variant, r.policy_label) for r in first.itertuples()}


def _label_order(labels, methods: dict[str, str | None]) -> list[str]:
    def key(label):
        method = methods.get(label)
        rank = VARIANT_ORDER.index(method) if method in VARIANT_ORDER else len(VARIANT_ORDER) + (label == "expert")
        return rank, label

    return sorted(set(labels), key=key)


def _condition_order(conditions) -> list[str]:
    grid = list(PAPER_GRID)
    return sorted(set(conditions), key=lambda c: (grid.index(c) if c in grid else len(grid), c))


def _task_order(tasks) -> list[str]:
    return sorted(set(tasks), key=lambda t: (TASKS.index(t) if t in TASKS else len(TASKS), t))


def pick_baseline(labels) -> str:
    """`act`, else `act_modified/standard`, else the first label given."""
    labels = list(dict.fromkeys(labels))
    for candidate in ("act", "act_modified/standard"):
        if candidate in labels:
            return candidate
    return labels[0]


# ---------------------------------------------------------------------------------------------- figures


def _png(fig) -> bytes:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)  # Agg directly: no pyplot, so no global backend state and no display needed
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    return buf.getvalue()


def _new_figure(width: float, height: float, rows: int = 1, cols: int = 1):
    from matplotlib.figure import Figure as MplFigure

    fig = MplFigure(figsize=(width, height), layout="constrained")
    return fig, fig.subplots(rows, cols, squeeze=False).ravel()


def _panel_width(conditions: int, labels: int) -> float:
    """Inches for one condition axis: room for every series' error bar side by side."""
    return max(3.6, 0.8 + 0.32 * conditions * max(1.0, labels / 2))


def _nonnegative(err: np.ndarray) -> np.ndarray:
    """Wilson bounds of a rate of 0 or 1 can sit a rounding error inside the rate; matplotlib refuses that."""
    return np.where(np.isnan(err), np.nan, np.maximum(err, 0.0))


def _series_offsets(count: int) -> np.ndarray:
    width = min(0.8, 0.18 * count)
    return np.linspace(-width / 2, width / 2, count) if count > 1 else np.zeros(1)


def stage_figure(task: str, metrics: pd.DataFrame, labels: list[str], conditions: list[str]) -> bytes:
    panels = list(METRICS)
    # a few conditions fit three panels abreast; the paper's 20-condition grid needs the full width
    cols = 3 if len(conditions) <= 5 else 2 if len(conditions) <= 10 else 1
    rows = math.ceil(len(panels) / cols)
    width = min(18.0, cols * _panel_width(len(conditions), len(labels)))
    fig, axes = _new_figure(width, 0.6 + 2.4 * rows, rows, cols)
    x = np.arange(len(conditions))
    for ax, metric in zip(axes, panels):
        for offset, label in zip(_series_offsets(len(labels)), labels):
            cell = metrics[metrics["policy_label"] == label].set_index("condition").reindex(conditions)
            y = cell[metric].to_numpy(float)
            err = np.vstack([y - cell[f"{metric}_low"].to_numpy(float), cell[f"{metric}_high"].to_numpy(float) - y])
            ax.errorbar(x + offset, 100 * y, yerr=100 * _nonnegative(err), fmt="o", ms=3.5, capsize=2, lw=1, label=label)
        ax.set_title(f"{METRIC_TITLES[metric]} (%)", fontsize=9)
        ax.set_ylim(-5, 105)
        ax.set_xticks(x, conditions, rotation=60, ha="right", fontsize=7)
        ax.tick_params(axis="y", labelsize=7)
        ax.grid(axis="y", alpha=0.3)
    for ax in axes[len(panels):]:
        ax.set_visible(False)
    handles, names = axes[0].get_legend_handles_labels()
    fig.legend(handles, names, loc="outside lower center", ncol=min(4, max(1, len(labels))), fontsize=8)
    fig.suptitle(f"{_task_title(task)}: stage metrics per condition (95 % Wilson intervals)", fontsize=10)
    return _png(fig)


def difference_figure(title: str, diffs: pd.DataFrame, series: str, conditions: list[str]) -> bytes:
    labels = list(dict.fromkeys(diffs[series]))
    fig, (ax,) = _new_figure(min(18.0, max(6.0, _panel_width(len(conditions), len(labels)))), 3.6)
    x = np.arange(len(conditions))
    for offset, label in zip(_series_offsets(len(labels)), labels):
        cell = diffs[diffs[series] == label].set_index("condition").reindex(conditions)
        y = cell["diff"].to_numpy(float)
        err = np.vstack([y - cell["low"].to_numpy(float), cell["high"].to_numpy(float) - y])
        ax.errorbar(x + offset, 100 * y, yerr=100 * _nonnegative(err), fmt="o", ms=3.5, capsize=2, lw=1, label=label)
    ax.axhline(0, color="0.4", lw=0.8)
    ax.set_ylim(-105, 105)
    ax.set_ylabel("difference in success (pp)", fontsize=8)
    ax.set_xticks(x, conditions, rotation=60, ha="right", fontsize=7)
    ax.grid(axis="y", alpha=0.3)
    fig.legend(loc="outside lower center", ncol=min(4, max(1, len(labels))), fontsize=8)
    ax.set_title(title, fontsize=9)
    return _png(fig)


def probe_figure(probes: list[tuple[str, dict]]) -> bytes:
    fig, (ax,) = _new_figure(max(4.0, 1.6 * len(probes) + 1.5), 3.0)
    x = np.arange(len(probes))
    for offset, arm in ((-0.17, "target"), (0.17, "swapped")):
        stats = [p.get(arm) or {} for _, p in probes]
        y = np.array([s.get("rate", np.nan) for s in stats], float)
        err = np.vstack([y - np.array([s.get("low", np.nan) for s in stats], float),
                         np.array([s.get("high", np.nan) for s in stats], float) - y])
        ax.bar(x + offset, 100 * y, width=0.32, label=f"{arm} prompt")
        # errorbar, not bar(yerr=): bar's own error bars trip a NumPy deprecation on (2, n) arrays
        ax.errorbar(x + offset, 100 * y, yerr=100 * _nonnegative(err), fmt="none", capsize=3, ecolor="0.2")
    ax.set_xticks(x, [name for name, _ in probes], fontsize=7)
    ax.set_ylim(0, 105)
    ax.set_ylabel("competitor selected (%)", fontsize=8)
    ax.legend(fontsize=7)
    ax.set_title("Prompt-swap probe (95 % Wilson intervals)", fontsize=9)
    return _png(fig)


# ---------------------------------------------------------------------------------------------- sections


class _Doc:
    def __init__(self):
        self.blocks: list = []
        self._names: set[str] = set()

    def add(self, *blocks):
        self.blocks.extend(blocks)

    def figure(self, name: str, png: bytes, caption: str):
        name, base, i = _slug(name), _slug(name), 1
        while name in self._names:
            i += 1
            name = f"{base}-{i}"
        self._names.add(name)
        self.blocks.append(Figure(name, png, caption))


def _section_table1(doc: _Doc, results: pd.DataFrame, methods, labels) -> None:
    doc.add(Heading("Table I: end-to-end success under full mixed distractors"))
    full = results[results["condition"] == "full_mixed"] if len(results) else results
    if full.empty:
        doc.add(Para("No full_mixed episodes among the inputs: a `condground sweep` that includes the full_mixed "
                     "condition produces this table.", note=True))
        return
    tasks = _task_order(full["task"])
    m = cell_metrics(full, by=("policy_label", "task")).set_index(["policy_label", "task"])
    paper_tasks = [t for t in TASKS if t in PAPER_TABLE1["standard"]]
    rows = []
    for label in [lb for lb in labels if lb in set(full["policy_label"])]:
        method = methods.get(label)
        ours = [_metric_cell(m.loc[(label, t)], "success") if (label, t) in m.index else "not run" for t in tasks]
        paper = PAPER_TABLE1.get(method, {})
        rows.append([label, *ours, PAPER_METHODS.get(method, "—"),
                     *[f"{paper[t]:.1f}%" if t in paper else "—" for t in paper_tasks]])
    doc.add(
        Para("Success % [95 % Wilson interval] (successes/episodes), pooled over training seeds and eval seeds. "
             "The paper's simulation column group (600 rollouts per cell) is printed beside ours; a policy maps to a "
             "paper row by its type and act_modified variant."),
        Table("table-1", "Table I: full mixed distractors, success",
              ["policy", *[_task_title(t) for t in tasks], "paper method", *[TASK_SHORT[t] for t in paper_tasks]],
              rows, groups=[("", 1), ("this report", len(tasks)), ("paper (simulation)", 1 + len(paper_tasks))]),
    )


def _paper_stage(method: str | None, task: str, condition: str) -> str:
    """What the paper reports for this cell, if anything: Table I's full-mixed success of the three
    methods, and the stage metrics of standard ACT quoted in the Results text."""
    if condition == "full_mixed" and task in PAPER_TABLE1.get(method, {}):
        return f"success {PAPER_TABLE1[method][task]:.1f}"
    if method == "standard":
        return PAPER_STAGES.get((task, condition), "—")
    return "—"


def _section_stages(doc: _Doc, results: pd.DataFrame, methods, labels) -> None:
    doc.add(Heading("Stage metrics per policy, task and condition"))
    if results.empty:
        doc.add(Para("No sweep among the inputs: `condground sweep` writes the per-episode results these tables and "
                     "plots come from.", note=True))
        return
    m = cell_metrics(results, by=CELL)
    conditions = _condition_order(results["condition"])
    rows = []
    for label in labels:
        for task in _task_order(results["task"]):
            for condition in conditions:
                hit = m[(m.policy_label == label) & (m.task == task) & (m.condition == condition)]
                if hit.empty:
                    continue
                r = hit.iloc[0]
                rows.append([label, task, condition, str(int(r["episodes"])),
                             *[_metric_cell(r, metric) for metric in METRICS], _seed_spread(r),
                             _paper_stage(methods.get(label), task, condition)])
    doc.add(
        Para("Each cell: rate [95 % Wilson interval] (k/n). Conditional probabilities use their own denominators: "
             "P(lift|pick) over the episodes that picked, P(place|pick,lift) over those that also lifted. "
             "'competitor grasped' and 'placed in competitor receptacle' are over all episodes. The seed column is "
             "the mean ± sd [min, max] of per-checkpoint success across training seeds."),
        Table("stage-table", "Stage metrics", ["policy", "task", "condition", "episodes",
                                                *[METRIC_TITLES[x] for x in METRICS], "success across training seeds",
                                                "paper (%)"], rows),
    )
    for task in _task_order(results["task"]):
        tm = m[m.task == task]
        task_labels = [lb for lb in labels if lb in set(tm.policy_label)]
        doc.figure(f"stages-{task}", stage_figure(task, tm, task_labels, _condition_order(tm.condition)),
                   f"{_task_title(task)}: stage metrics across the condition grid, one series per policy, "
                   "95 % Wilson intervals.")


def _differences_by_group(results: pd.DataFrame, keys: list[str], compute) -> tuple[pd.DataFrame, list[str]]:
    """Runs a pairing per group so that one unpairable group is reported, not fatal to the rest."""
    frames, failures = [], []
    for _, group in results.groupby(keys, sort=False):
        try:
            frames.append(compute(group))
        except ValueError as err:
            failures.append(str(err))
    frames = [f for f in frames if not f.empty]
    return (pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()), failures


def _section_condition_differences(doc: _Doc, results: pd.DataFrame, labels) -> None:
    doc.add(Heading("Paired differences: condition − clean"))
    if results.empty or "clean" not in set(results["condition"]) or set(results["condition"]) == {"clean"}:
        doc.add(Para("Needs a sweep with the clean condition and at least one other condition for the same checkpoints.",
                     note=True))
        return
    diffs, failures = _differences_by_group(results, ["policy_label", "task"], condition_differences)
    for failure in failures:
        doc.add(Para(f"Not paired: {failure}", note=True))
    if diffs.empty:
        doc.add(Para("No condition could be paired with clean episodes of the same checkpoints and layouts.", note=True))
        return
    conditions = _condition_order(diffs["condition"])
    diffs = diffs.assign(_l=diffs.policy_label.map(labels.index), _c=diffs.condition.map(conditions.index))
    diffs = diffs.sort_values(["_l", "task", "_c"], kind="stable")
    doc.add(
        Para("Success under each condition minus clean success, episode by episode on the same checkpoint and "
             "layout seed. Interval: Newcombe's hybrid score interval for paired proportions (1998, method 10); "
             "p: exact McNemar test on the discordant pairs."),
        Table("condition-differences", "Condition − clean (success)",
              ["policy", "task", "condition", "clean", "condition rate", "difference [95 % CI]", "only clean / only condition"],
              [[r.policy_label, r.task, r.condition, f"{_pct(r.rate_reference)}%", f"{_pct(r.rate_condition)}%",
                fmt_diff(r._asdict()), f"{r.reference_only} / {r.condition_only}"] for r in diffs.itertuples()]),
    )
    for task in _task_order(diffs["task"]):
        td = diffs[diffs.task == task]
        doc.figure(f"condition-differences-{task}",
                   difference_figure(f"{_task_title(task)}: success under condition − clean (Newcombe 95 % CI)",
                                     td, "policy_label", _condition_order(td.condition)),
                   f"{_task_title(task)}: paired difference of success, condition − clean, per policy.")


def _section_variant_differences(doc: _Doc, results: pd.DataFrame, labels) -> None:
    doc.add(Heading("Paired differences: variant − baseline"))
    # The scripted expert is the oracle every table shows, not a variant to compare against.
    results = results[results.policy_type != "expert"] if len(results) else results
    labels = [lb for lb in labels if len(results) and lb in set(results["policy_label"])]
    if not len(results) or not (results.groupby("task")["policy_label"].nunique() >= 2).any():
        doc.add(Para("Needs sweeps of at least two policies (the expert aside) on the same task.", note=True))
        return
    baseline = pick_baseline(labels)
    frames, failures = [], []
    for task in _task_order(results["task"]):
        tr = results[results.task == task]
        if baseline not in set(tr.policy_label):
            if tr.policy_label.nunique() >= 2:
                failures.append(f"{task}: the baseline {baseline!r} was not run on this task")
            continue
        for label in [lb for lb in labels if lb != baseline and lb in set(tr.policy_label)]:
            try:
                frames.append(variant_differences(tr[tr.policy_label.isin([baseline, label])], baseline))
            except ValueError as err:
                failures.append(str(err))
    for failure in failures:
        doc.add(Para(f"Not paired: {failure}", note=True))
    frames = [f for f in frames if not f.empty]
    if not frames:
        doc.add(Para("No variant shares conditions, eval seeds and training seed indices with the baseline.", note=True))
        return
    diffs = pd.concat(frames, ignore_index=True)
    conditions = _condition_order(diffs["condition"])
    diffs = diffs.assign(_c=diffs.condition.map(conditions.index)).sort_values(["task", "_c"], kind="stable")
    doc.add(
        Para(f"Success of each policy minus the baseline {baseline!r}, paired on task, condition, training seed "
             "index, eval seed and episode (same layout). Newcombe interval and exact McNemar p as above."),
        Table("variant-differences", f"Variant − {baseline} (success)",
              ["policy", "task", "condition", baseline, "policy rate", "difference [95 % CI]", f"only {baseline} / only policy"],
              [[r.policy_label, r.task, r.condition, f"{_pct(r.rate_baseline)}%", f"{_pct(r.rate_policy)}%",
                fmt_diff(r._asdict()), f"{r.baseline_only} / {r.policy_only}"] for r in diffs.itertuples()]),
    )
    for task in _task_order(diffs["task"]):
        td = diffs[diffs.task == task]
        doc.figure(f"variant-differences-{task}",
                   difference_figure(f"{_task_title(task)}: success of variant − {baseline} (Newcombe 95 % CI)",
                                     td, "policy_label", _condition_order(td.condition)),
                   f"{_task_title(task)}: paired difference of success, variant − {baseline}.")


def _unique_names(entries: list[tuple[Path, dict]]) -> list[str]:
    """Column names for diagnose outputs: the label, qualified by task and then folder where needed."""
    names = [d.get("policy_label") or folder.name for folder, d in entries]
    if len(set(names)) < len(names):
        names = [f"{n} ({d.get('task', '?')})" for n, (_, d) in zip(names, entries)]
    if len(set(names)) < len(names):
        names = [f"{n} [{folder.name}]" for n, (folder, _) in zip(names, entries)]
    return names


def _section_table2(doc: _Doc, diagnostics: list[tuple[Path, dict]]) -> None:
    doc.add(Heading("Table II: decoder-state diagnostics"))
    if not diagnostics:
        doc.add(Para("No diagnose output among the inputs: `condground diagnose` writes diagnostics.json with these "
                     "metrics and the t-SNE figures.", note=True))
        return
    names = _unique_names(diagnostics)
    # the paper column each policy corresponds to, as diagnose recorded it
    columns = [f"{n} (paper: {d['paper']['column']})" if (d.get("paper") or {}).get("column") else n
               for n, (_, d) in zip(names, diagnostics)]
    rows = []
    for key, title in TABLE2_ROWS.items():
        ours = []
        for _, d in diagnostics:
            units = d.get("table2_units") or {}
            text = _fmt_number((d.get("table2") or {}).get(key), units.get(key, "%" if key in TABLE2_PERCENT else "") == "%")
            counted = d.get(key) if isinstance(d.get(key), dict) else {}
            if counted.get("n"):
                text += f" ({counted['k']}/{counted['n']})"
            ours.append(text)
        rows.append([title, *ours, *[_fmt_number(PAPER_TABLE2[p][key], key in TABLE2_PERCENT) for p in PAPER_TABLE2]])
    tasks = sorted({str(d.get("task", "?")) for _, d in diagnostics})
    doc.add(
        Para(f"Computed on {', '.join(tasks)} (the paper's Table II is Task 2). Shift: place-phase clean-to-full cosine "
             "distance; phase retained: full-to-clean pick/place centroid separation; silhouette: container-position "
             "silhouette under full distractors; conditional placement: P(place|pick,lift) under full distractors, "
             "from the sweep given to diagnose."),
        Table("table-2", "Table II: decoder-state diagnostics", ["metric", *columns, *PAPER_TABLE2],
              rows, groups=[("", 1), ("this report", len(names)), ("paper (Task 2)", len(PAPER_TABLE2))]),
    )
    for name, (_, d) in zip(names, diagnostics):
        for note in d.get("notes") or []:
            doc.add(Para(f"{name}: {note}", note=True))
    layer_rows = []
    for name, (_, d) in zip(names, diagnostics):
        for layer, values in (d.get("layers") or {}).items():
            shift = values.get("shift") or {}
            layer_rows.append([name, layer, _fmt_number(shift.get("pick")), _fmt_number(shift.get("place")),
                               _fmt_number(values.get("phase_retained"), True),
                               _fmt_number(values.get("container_silhouette"))])
    if layer_rows:
        doc.add(Table("layer-diagnostics", "Diagnostics per layer",
                      ["policy", "layer", "shift (pick)", "shift (place)", "phase retained", "container silhouette"],
                      layer_rows))


def _section_tsne(doc: _Doc, diagnostics: list[tuple[Path, dict]]) -> None:
    doc.add(Heading("t-SNE projections"))
    figures = [(folder, d, name, rel) for folder, d in diagnostics for name, rel in (d.get("figures") or {}).items()]
    if not figures:
        doc.add(Para("No t-SNE figures: `condground diagnose` writes them under its figures/ folder.", note=True))
        return
    doc.add(Para("Illustrative only: the quantitative comparisons above are computed in the original feature space."))
    for folder, d, name, rel in figures:
        label = d.get("policy_label", folder.name)
        doc.figure(f"tsne-{label}-{name}", (folder / rel).read_bytes(), f"{label} · {d.get('task', '')}: {name}")


def _still_caption(d: dict, rel: str) -> str:
    """Policy, scene and head of an attention still; its step and the phase predicted there when the
    file name carries the step (`step_0042.png`, as `condground attention` writes)."""
    caption = (f"{d.get('policy_label', '')} · {d.get('task', '')} · {d.get('condition', '')} · seed {d.get('seed', '?')} · "
               f"head {d.get('head', '?')}: {Path(rel).stem}")
    match = re.search(r"(\d+)$", Path(rel).stem)
    phases = d.get("phase_predicted") or []
    if match and int(match.group(1)) < len(phases) and phases[int(match.group(1))] is not None:
        caption += f", predicted phase {phases[int(match.group(1))]}"
    return caption


def _section_attention(doc: _Doc, attention: list[tuple[Path, dict]]) -> None:
    doc.add(Heading("Attention stills"))
    stills = [(folder, d, rel) for folder, d in attention for rel in (d.get("stills") or [])]
    if not stills:
        doc.add(Para("No attention stills: `condground attention` writes them with its video.", note=True))
        return
    rows = []
    for name, (folder, d) in zip(_unique_names(attention), attention):
        mass = d.get("attention_mass_mean") or {}
        rows.append([name, str(d.get("task", "")), str(d.get("condition", "")), str(d.get("seed", "")),
                     str(d.get("head", "")), str(d.get("frames", "")),
                     "\n".join(f"{k}: {_fmt_number(v)}" for k, v in mass.items()) or "—",
                     str(folder / d["video"]) if d.get("video") else "—"])
    doc.add(Para("The supervised decoder head's attention over the episode; the video is not embedded."),
            Table("attention", "Attention episodes", ["policy", "task", "condition", "seed", "head", "steps",
                                                      "mean attention mass", "video"], rows))
    for folder, d, rel in stills:
        doc.figure(f"attention-{d.get('policy_label', folder.name)}-{Path(rel).stem}", (folder / rel).read_bytes(),
                   _still_caption(d, rel))


def _section_probe(doc: _Doc, probes: list[tuple[Path, dict]]) -> None:
    doc.add(Heading("Prompt-swap probe"))
    if not probes:
        doc.add(Para("No probe output among the inputs: `condground probe` runs each layout with the target's prompt "
                     "and with a competitor's prompt swapped in.", note=True))
        return

    def arm(s):
        s = s or {}
        return fmt_rate(s.get("k", 0), s.get("n", 0), s.get("low", math.nan), s.get("high", math.nan))

    names = _unique_names(probes)
    rows = [[name, str(d.get("condition", "")), str(d.get("selection", d.get("role", ""))), str(d.get("episodes", "")),
             arm(d.get("target")), arm(d.get("swapped")), fmt_diff(d.get("difference")),
             PAPER_PROBE["target"], PAPER_PROBE["swapped"]] for name, (_, d) in zip(names, probes)]
    doc.add(
        Para("Competitor selection with the target's prompt and with a competitor's crop swapped in, on the same "
             "layouts. The paper reports 0–1 % competitor selection with the target prompt and 35–91 % swapped. "
             "Difference: swapped − target, Newcombe paired interval, exact McNemar p."),
        Table("probe", "Prompt-swap probe: competitor selected",
              ["policy", "condition", "selection measured", "layouts", "target prompt", "swapped prompt", "swapped − target",
               "target", "swapped"], rows, groups=[("this report", 7), ("paper", 2)]),
    )
    doc.figure("probe", probe_figure(list(zip(names, (d for _, d in probes)))),
               "Competitor selection with the target prompt and the swapped prompt, per probe.")


def _versions_text(versions) -> str:
    return "; ".join(f"{k} {v}" for k, v in (versions or {}).items()) or "—"


def _command_text(command) -> str:
    if isinstance(command, list):
        return shlex.join(str(c) for c in command)
    return str(command) if command else "—"


def _checkpoints_text(data: dict) -> str:
    if data.get("kind") == "sweep":
        return "\n".join(f"{c.get('label')}: {c.get('path')} (hash {c.get('hash')}, training seed {c.get('training_seed')})"
                         for c in data.get("checkpoints", [])) or "—"
    path, digest = data.get("checkpoint"), data.get("checkpoint_hash")
    if not path:
        return "—"
    return f"{data.get('policy_label', '')}: {path}" + (f" (hash {digest})" if digest else "")


def report_versions() -> dict:
    out = {"python": platform.python_version()}
    for package in ("lerobot_policy_condground", "pandas", "numpy", "scipy", "statsmodels", "matplotlib"):
        try:
            out[package] = version(package)
        except Exception:
            out[package] = "not installed"
    return out


def _section_provenance(doc: _Doc, inputs: Inputs, cfg: ReportConfig) -> None:
    doc.add(Heading("Provenance"))
    rows = [[str(folder), str(d.get("kind")), _command_text(d.get("command")), _versions_text(d.get("versions")),
             _checkpoints_text(d)] for folder, d in inputs.sources]
    command = ["condground", "report", *[f"--input_dir={x}" for x in cfg.input_dir], f"--output={cfg.output}"]
    rows.append(["(this report)", "report", shlex.join(command), _versions_text(report_versions()), "—"])
    doc.add(Table("provenance", "Inputs: commands, versions, checkpoints",
                  ["input", "kind", "command", "versions", "checkpoints (path, hash)"], rows))


def build_document(inputs: Inputs, cfg: ReportConfig) -> list:
    doc = _Doc()
    results = inputs.results
    methods = _label_methods(results) if len(results) else {}
    labels = _label_order(results["policy_label"], methods) if len(results) else []
    if len(results):
        doc.add(Para(f"{len(results)} episodes from {results['source'].nunique()} sweep director"
                     f"{'y' if results['source'].nunique() == 1 else 'ies'}: policies {', '.join(labels)}; tasks "
                     f"{', '.join(_task_order(results['task']))}; {results['condition'].nunique()} conditions; "
                     f"{results['checkpoint_hash'].nunique()} checkpoints. Intervals are 95 %."))
    _section_table1(doc, results, methods, labels)
    _section_stages(doc, results, methods, labels)
    _section_condition_differences(doc, results, labels)
    _section_variant_differences(doc, results, labels)
    _section_table2(doc, inputs.diagnostics)
    _section_tsne(doc, inputs.diagnostics)
    _section_attention(doc, inputs.attention)
    _section_probe(doc, inputs.probes)
    _section_provenance(doc, inputs, cfg)
    return doc.blocks


# ---------------------------------------------------------------------------------------------- rendering

CSS = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1400px; padding: 0 1em; color: #222; }
table { border-collapse: collapse; margin: 0.6em 0 1.6em; font-size: 0.82em; }
caption { text-align: left; font-weight: bold; padding: 0.3em 0; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.5em; vertical-align: top; }
th { background: #f2f2f2; }
th.group { background: #e4e9f2; }
figure { margin: 1em 0 2em; }
figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.85em; color: #555; }
p.note { color: #8a5a00; font-style: italic; }
"""


def render_html(title: str, blocks: list) -> str:
    e = html.escape
    out = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">', f"<title>{e(title)}</title>",
           f"<style>{CSS}</style></head><body>", f"<h1>{e(title)}</h1>"]
    for b in blocks:
        if isinstance(b, Heading):
            out.append(f"<h{b.level}>{e(b.text)}</h{b.level}>")
        elif isinstance(b, Para):
            text = re.sub(r"`([^`]+)`", r"<code>\1</code>", e(b.text))  # Markdown's code spans, in HTML
            out.append(f'<p class="note">{text}</p>' if b.note else f"<p>{text}</p>")
        elif isinstance(b, Table):
            out.append(f'<table id="{e(b.id)}"><caption>{e(b.caption)}</caption><thead>')
            if b.groups:
                cells = "".join(f'<th class="group" colspan="{span}">{e(text)}</th>' for text, span in b.groups)
                out.append(f"<tr>{cells}</tr>")
            out.append("<tr>" + "".join(f"<th>{e(c)}</th>" for c in b.columns) + "</tr></thead><tbody>")
            for row in b.rows:
                cells = "".join(f"<td>{'<br>'.join(e(line) for line in str(c).splitlines())}</td>" for c in row)
                out.append(f"<tr>{cells}</tr>")
            out.append("</tbody></table>")
        elif isinstance(b, Figure):
            data = base64.b64encode(b.png).decode("ascii")
            out.append(f'<figure id="fig-{e(b.name)}"><img alt="{e(b.caption)}" src="data:image/png;base64,{data}">'
                       f"<figcaption>{e(b.caption)}</figcaption></figure>")
    out.append("</body></html>")
    return "\n".join(out)


def _md_cell(text) -> str:
    return "<br>".join(str(text).replace("|", "\\|").splitlines())


def render_markdown(title: str, blocks: list, files_dir: str) -> tuple[str, dict[str, bytes]]:
    """Markdown text and the PNG files it links, by file name under `files_dir`."""
    out, files = [f"# {title}", ""], {}
    for b in blocks:
        if isinstance(b, Heading):
            out += ["#" * b.level + " " + b.text, ""]
        elif isinstance(b, Para):
            out += [f"*{b.text}*" if b.note else b.text, ""]
        elif isinstance(b, Table):
            columns = list(b.columns)
            if b.groups:  # Markdown has no spanning headers: the group goes into each column's name
                i = 0
                for text, span in b.groups:
                    for j in range(i, i + span):
                        columns[j] = f"{text}: {columns[j]}" if text else columns[j]
                    i += span
            out += [f"**{b.caption}**", "", "| " + " | ".join(_md_cell(c) for c in columns) + " |",
                    "|" + "---|" * len(columns)]
            out += ["| " + " | ".join(_md_cell(c) for c in row) + " |" for row in b.rows]
            out.append("")
        elif isinstance(b, Figure):
            files[f"{b.name}.png"] = b.png
            out += [f"![{b.caption}]({files_dir}/{b.name}.png)", "", f"*{b.caption}*", ""]
    return "\n".join(out), files


def build_report(cfg: ReportConfig) -> tuple[Path, Path]:
    """Writes cfg.output (HTML) and the Markdown version beside it (same name, .md, figures in NAME_files/).
    Returns (html_path, markdown_path). Raises ValueError for unusable inputs."""
    inputs = load_inputs(list(cfg.input_dir))
    blocks = build_document(inputs, cfg)
    html_path = Path(cfg.output)
    md_path = html_path.with_suffix(".md")
    files_dir = html_path.parent / f"{html_path.stem}_files"
    html_path.parent.mkdir(parents=True, exist_ok=True)
    html_path.write_text(render_html(cfg.title, blocks), encoding="utf-8")
    text, files = render_markdown(cfg.title, blocks, files_dir.name)
    files_dir.mkdir(exist_ok=True)
    for stale in files_dir.glob("*.png"):  # a rerun with fewer figures must not leave old ones behind
        if stale.name not in files:
            stale.unlink()
    for name, png in files.items():
        (files_dir / name).write_bytes(png)
    md_path.write_text(text, encoding="utf-8")
    return html_path, md_path
