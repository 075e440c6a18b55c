"""What the report says: each section's paragraphs, tables and figures, as plain data for the templates.

Every section is always present; one whose inputs are missing holds a note saying which command produces
them, so that an absent table is never mistaken for an empty result.
"""

from __future__ import annotations

import math
import platform
import re
import shlex
from dataclasses import dataclass, field
from importlib.metadata import version
from pathlib import Path
from typing import ClassVar

import pandas as pd

from lerobot_condground.core import paper
from lerobot_condground.core.conditions import PAPER_GRID, ROUTING_TASK, TASKS
from lerobot_condground.core.routing import ROUTING_SUBGOALS, SUBGOALS
from lerobot_condground.evaluation.statistics import (
    CELL,
    METRIC_TITLES,
    METRICS,
    SUBGOAL_POOLS,
    SUBGOAL_TITLES,
    cell_metrics,
    condition_differences,
    stage_funnel,
    subgoal_rates,
    variant_differences,
)

from .config import ReportConfig
from .figures import difference_figure, funnel_figure, probe_figure, stage_figure, success_figure
from .formatting import TASK_SHORT, fmt_diff, fmt_number, fmt_rate, metric_cell, pct, seed_spread, task_title
from .inputs import Inputs

TABLE2_ROWS = {  # key in diagnostics.json "table2" -> row title
    "place_shift": "Place shift ↓",
    "phase_retained": "Phase retained ↑",
    "container_silhouette": "Container silhouette ↑",
    "conditional_placement": "Conditional placement ↑",
}
# `condground diagnose` writes these two in percent and says so in `table2_units`.
TABLE2_PERCENT = {"phase_retained", "conditional_placement"}
VARIANT_ORDER = ("standard", "augmentation", "augmentation_attention", "full")


# `kind` lets the templates tell the blocks apart without isinstance.
@dataclass
class Para:
    text: str
    note: bool = False  # set apart: a missing input, an unpaired group, a caveat diagnose recorded
    kind: ClassVar[str] = "para"


@dataclass
class Table:
    id: str
    caption: str
    columns: list[str]
    rows: list[list[str]]
    groups: list[tuple[str, int]] | None = None  # header groups spanning consecutive columns
    open: bool = False  # shown unfolded in the HTML; the full tables follow the figures folded
    kind: ClassVar[str] = "table"


@dataclass
class Figure:
    name: str  # unique and file-name safe once build_document has run
    png: bytes
    caption: str
    kind: ClassVar[str] = "figure"


@dataclass
class Section:
    title: str
    blocks: list[Para | Table | Figure] = field(default_factory=list)

    def note(self, text: str) -> Section:
        self.blocks.append(Para(text, note=True))
        return self


@dataclass
class Document:
    title: str
    intro: list[Para]
    sections: list[Section]

    @property
    def figures(self) -> list[Figure]:
        return [b for s in self.sections for b in s.blocks if isinstance(b, Figure)]


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
        if method in VARIANT_ORDER:
            return VARIANT_ORDER.index(method), label
        return len(VARIANT_ORDER) + (label == "expert"), label

    return sorted(set(labels), key=key)


def _condition_order(conditions) -> list[str]:
    grid = list(PAPER_GRID)

    def key(c: str) -> tuple:
        plain = c.split(" (")[0]  # right after the plain condition: counterbalanced, augmentation competitors
        return (grid.index(plain) if plain in grid else len(grid), plain, c != plain, c)

    return sorted(set(conditions), key=key)


def _task_order(tasks) -> list[str]:
    return sorted(set(tasks), key=lambda t: (TASKS.index(t) if t in TASKS else len(TASKS), t))


def pick_baseline(labels) -> str:
    """`act`, else `act_modified/standard`, else the first label given."""
    labels = list(dict.fromkeys(labels))
    for candidate in ("act", "act_modified/standard"):
        if candidate in labels:
            return candidate
    return labels[0]


# ---------------------------------------------------------------------------------------------- sections


def _paper_success(method: str | None, task: str, condition: str) -> float | None:
    """The paper's success (%) for this cell: Table I under full mixed distractors, standard ACT's clean."""
    if condition == "full_mixed":
        return paper.TABLE1.get(method, {}).get(task)
    quoted = paper.STAGES.get((task, condition), "") if method == "standard" else ""
    return float(quoted.split()[1]) if quoted.startswith("success ") else None


def _section_overview(
    results: pd.DataFrame, metrics: pd.DataFrame, methods, labels, variant_figures: list[Figure]
) -> Section:
    """The pictures a reader looks at first; the tables they summarize follow in the later sections."""
    section = Section("At a glance")
    if results.empty:
        return section.note(
            "No sweep among the inputs: `condground sweep` writes the results these figures show."
        )
    section.blocks.append(
        Para(
            "Success per policy and condition, the stage where episodes stop, and the paired differences "
            "between variants; the full tables follow below (folded in the HTML: click a caption)."
        )
    )
    funnel = stage_funnel(results)
    for task in _task_order(results["task"]):
        tm = metrics[metrics.task == task]
        task_labels = [lb for lb in labels if lb in set(tm.policy_label)]
        conditions = _condition_order(tm.condition)
        reported = {
            (label, c): value
            for label in task_labels
            for c in conditions
            if (value := _paper_success(methods.get(label), task, c)) is not None
        }
        section.blocks += [
            Figure(
                f"success-{task}",
                success_figure(task, tm, task_labels, conditions, reported),
                f"{task_title(task)}: success per policy and condition, 95 % Wilson intervals; open diamonds: "
                "the paper's value for the policy's method where it reports one.",
            ),
            Figure(
                f"funnel-{task}",
                funnel_figure(task, funnel[funnel.task == task], task_labels, conditions),
                f"{task_title(task)}: share of all episodes that picked, picked and lifted, and placed, per "
                "condition: the stage where the bars drop is where the policy fails.",
            ),
            *[f for f in variant_figures if f.name == f"variant-differences-{task}"],
        ]
    return section


def _section_table1(results: pd.DataFrame, methods, labels) -> Section:
    section = Section("Table I: end-to-end success under full mixed distractors")
    full = results[results["condition"] == "full_mixed"] if len(results) else results
    if full.empty:
        return section.note(
            "No full_mixed episodes among the inputs: a `condground sweep` that includes "
            "the full_mixed condition produces this table."
        )
    tasks = _task_order(full["task"])
    m = cell_metrics(full, by=("policy_label", "task")).set_index(["policy_label", "task"])
    paper_tasks = [t for t in TASKS if t in paper.TABLE1["standard"]]
    rows = []
    for label in [lb for lb in labels if lb in set(full["policy_label"])]:
        method = methods.get(label)
        ours = [
            metric_cell(m.loc[(label, t)], "success") if (label, t) in m.index else "not run" for t in tasks
        ]
        reported = paper.TABLE1.get(method, {})
        rows.append(
            [
                label,
                *ours,
                paper.METHODS.get(method, "—"),
                *[f"{reported[t]:.1f}%" if t in reported else "—" for t in paper_tasks],
            ]
        )
    section.blocks += [
        Para(
            "Success % [95 % Wilson interval] (successes/episodes), pooled over training seeds and eval "
            "seeds. The paper's simulation column group (600 rollouts per cell) is printed beside ours; a "
            "policy maps to a paper row by its type and act_modified variant."
        ),
        Table(
            "table-1",
            "Table I: full mixed distractors, success",
            [
                "policy",
                *[task_title(t) for t in tasks],
                "paper method",
                *[TASK_SHORT[t] for t in paper_tasks],
            ],
            rows,
            groups=[("", 1), ("this report", len(tasks)), ("paper (simulation)", 1 + len(paper_tasks))],
            open=True,
        ),
    ]
    return section


def _paper_stage(method: str | None, task: str, condition: str) -> str:
    """What the paper reports for this cell, if anything: Table I's full-mixed success of the three
    methods, and the stage metrics of standard ACT quoted in the Results text."""
    if condition == "full_mixed" and task in paper.TABLE1.get(method, {}):
        return f"success {paper.TABLE1[method][task]:.1f}"
    if method == "standard":
        return paper.STAGES.get((task, condition), "—")
    return "—"


def _section_stages(results: pd.DataFrame, m: pd.DataFrame, methods, labels) -> Section:
    section = Section("Stage metrics per policy, task and condition")
    if results.empty:
        return section.note(
            "No sweep among the inputs: `condground sweep` writes the per-episode results "
            "these tables and plots come from."
        )
    conditions = _condition_order(results["condition"])
    rows = []
    for label in labels:
        for task in _task_order(results["task"]):
            for condition in conditions:
                hit = m[(m.policy_label == label) & (m.task == task) & (m.condition == condition)]
                if hit.empty:
                    continue
                r = hit.iloc[0]
                rows.append(
                    [
                        label,
                        task,
                        condition,
                        str(int(r["episodes"])),
                        *[metric_cell(r, metric) for metric in METRICS],
                        seed_spread(r),
                        _paper_stage(methods.get(label), task, condition),
                    ]
                )
    section.blocks += [
        Para(
            "Each cell: rate [95 % Wilson interval] (k/n). Conditional probabilities use their own "
            "denominators: P(lift|pick) over the episodes that picked, P(place|pick,lift) over those that "
            "also lifted. 'competitor grasped' and 'placed in competitor receptacle' are over all episodes. "
            "The seed column is the mean ± sd [min, max] of per-checkpoint success across training seeds."
        ),
        Table(
            "stage-table",
            "Stage metrics",
            [
                "policy",
                "task",
                "condition",
                "episodes",
                *[METRIC_TITLES[x] for x in METRICS],
                "success across training seeds",
                "paper (%)",
            ],
            rows,
        ),
    ]
    for task in _task_order(results["task"]):
        tm = m[m.task == task]
        task_labels = [lb for lb in labels if lb in set(tm.policy_label)]
        section.blocks.append(
            Figure(
                f"stages-{task}",
                stage_figure(task, tm, task_labels, _condition_order(tm.condition)),
                f"{task_title(task)}: stage metrics across the condition grid, one series per policy, "
                "95 % Wilson intervals.",
            )
        )
    return section


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


def _section_condition_differences(results: pd.DataFrame, labels) -> Section:
    section = Section("Paired differences: condition − clean")
    if results.empty or "clean" not in set(results["condition"]) or set(results["condition"]) == {"clean"}:
        return section.note(
            "Needs a sweep with the clean condition and at least one other condition for "
            "the same checkpoints."
        )
    diffs, failures = _differences_by_group(results, ["policy_label", "task"], condition_differences)
    for failure in failures:
        section.note(f"Not paired: {failure}")
    if diffs.empty:
        return section.note(
            "No condition could be paired with clean episodes of the same checkpoints and layouts."
        )
    conditions = _condition_order(diffs["condition"])
    diffs = diffs.assign(_l=diffs.policy_label.map(labels.index), _c=diffs.condition.map(conditions.index))
    diffs = diffs.sort_values(["_l", "task", "_c"], kind="stable")
    section.blocks += [
        Para(
            "Success under each condition minus clean success, episode by episode on the same checkpoint "
            "and layout seed. Interval: Newcombe's hybrid score interval for paired proportions (1998, "
            "method 10); p: exact McNemar test on the discordant pairs."
        ),
        Table(
            "condition-differences",
            "Condition − clean (success)",
            [
                "policy",
                "task",
                "condition",
                "clean",
                "condition rate",
                "difference [95 % CI]",
                "only clean / only condition",
            ],
            [
                [
                    r.policy_label,
                    r.task,
                    r.condition,
                    f"{pct(r.rate_reference)}%",
                    f"{pct(r.rate_condition)}%",
                    fmt_diff(r._asdict()),
                    f"{r.reference_only} / {r.condition_only}",
                ]
                for r in diffs.itertuples()
            ],
        ),
    ]
    for task in _task_order(diffs["task"]):
        td = diffs[diffs.task == task]
        section.blocks.append(
            Figure(
                f"condition-differences-{task}",
                difference_figure(
                    f"{task_title(task)}: success under condition − clean (Newcombe 95 % CI)",
                    td,
                    "policy_label",
                    _condition_order(td.condition),
                ),
                f"{task_title(task)}: paired difference of success, condition − clean, per policy.",
            )
        )
    return section


def _section_variant_differences(results: pd.DataFrame, labels) -> Section:
    section = Section("Paired differences: variant − baseline")
    # The scripted expert is the oracle every table shows, not a variant to compare against.
    results = results[results.policy_type != "expert"] if len(results) else results
    labels = [lb for lb in labels if len(results) and lb in set(results["policy_label"])]
    if not len(results) or not (results.groupby("task")["policy_label"].nunique() >= 2).any():
        return section.note("Needs sweeps of at least two policies (the expert aside) on the same task.")
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
        section.note(f"Not paired: {failure}")
    frames = [f for f in frames if not f.empty]
    if not frames:
        return section.note(
            "No variant shares conditions, eval seeds and training seed indices with the baseline."
        )
    diffs = pd.concat(frames, ignore_index=True)
    conditions = _condition_order(diffs["condition"])
    diffs = diffs.assign(_c=diffs.condition.map(conditions.index)).sort_values(["task", "_c"], kind="stable")
    section.blocks += [
        Para(
            f"Success of each policy minus the baseline {baseline!r}, paired on task, condition, training "
            "seed index, checkpoint index within the run, eval seed and episode (same layout). Newcombe "
            "interval and exact McNemar p as above, every pair taken as independent; beside it the "
            "layout-clustered, run-aware interval, which takes the layout as the pairing unit and the "
            "training run as the replicate (none with one run a policy)."
        ),
        Table(
            "variant-differences",
            f"Variant − {baseline} (success)",
            [
                "policy",
                "task",
                "condition",
                baseline,
                "policy rate",
                "difference [95 % CI]",
                "layout-clustered, run-aware",
                f"only {baseline} / only policy",
            ],
            [
                [
                    r.policy_label,
                    r.task,
                    r.condition,
                    f"{pct(r.rate_baseline)}%",
                    f"{pct(r.rate_policy)}%",
                    fmt_diff(r._asdict()),
                    _interval(r._asdict(), "cluster_low", "cluster_high", "cluster_p"),
                    f"{r.baseline_only} / {r.policy_only}",
                ]
                for r in diffs.itertuples()
            ],
        ),
    ]
    for task in _task_order(diffs["task"]):
        td = diffs[diffs.task == task]
        section.blocks.append(
            Figure(
                f"variant-differences-{task}",
                difference_figure(
                    f"{task_title(task)}: success of variant − {baseline} (Newcombe 95 % CI)",
                    td,
                    "policy_label",
                    _condition_order(td.condition),
                ),
                f"{task_title(task)}: paired difference of success, variant − {baseline}.",
            )
        )
    return section


def _unique_names(entries: list[tuple[Path, dict]]) -> list[str]:
    """Column names for diagnose outputs: the label, qualified by task and then folder where needed."""
    names = [d.get("policy_label") or folder.name for folder, d in entries]
    if len(set(names)) < len(names):
        names = [f"{n} ({d.get('task', '?')})" for n, (_, d) in zip(names, entries, strict=True)]
    if len(set(names)) < len(names):
        names = [f"{n} [{folder.name}]" for n, (folder, _) in zip(names, entries, strict=True)]
    return names


def _section_table2(diagnostics: list[tuple[Path, dict]]) -> Section:
    section = Section("Table II: decoder-state diagnostics")
    if not diagnostics:
        return section.note(
            "No diagnose output among the inputs: `condground diagnose` writes "
            "diagnostics.json with these metrics and the t-SNE figures."
        )
    names = _unique_names(diagnostics)
    # the paper column each policy corresponds to, as diagnose recorded it
    columns = [
        f"{n} (paper: {d['paper']['column']})" if (d.get("paper") or {}).get("column") else n
        for n, (_, d) in zip(names, diagnostics, strict=True)
    ]
    rows = []
    for key, title in TABLE2_ROWS.items():
        ours = []
        for _, d in diagnostics:
            units = d.get("table2_units") or {}
            percent = units.get(key, "%" if key in TABLE2_PERCENT else "") == "%"
            text = fmt_number((d.get("table2") or {}).get(key), percent)
            counted = d.get(key) if isinstance(d.get(key), dict) else {}
            if counted.get("n"):
                text += f" ({counted['k']}/{counted['n']})"
            ours.append(text)
        reported = [fmt_number(paper.TABLE2[p][key], key in TABLE2_PERCENT) for p in paper.TABLE2]
        rows.append([title, *ours, *reported])
    tasks = sorted({str(d.get("task", "?")) for _, d in diagnostics})
    section.blocks += [
        Para(
            f"Computed on {', '.join(tasks)} (the paper's Table II is Task 2). Shift: place-phase "
            "clean-to-full cosine distance; phase retained: full-to-clean pick/place centroid separation; "
            "silhouette: container-position silhouette under full distractors; conditional placement: "
            "P(place|pick,lift) under full distractors, from the sweep given to diagnose."
        ),
        Table(
            "table-2",
            "Table II: decoder-state diagnostics",
            ["metric", *columns, *paper.TABLE2],
            rows,
            groups=[("", 1), ("this report", len(names)), ("paper (Task 2)", len(paper.TABLE2))],
        ),
    ]
    for name, (_, d) in zip(names, diagnostics, strict=True):
        for note in d.get("notes") or []:
            section.note(f"{name}: {note}")
    layer_rows = []
    for name, (_, d) in zip(names, diagnostics, strict=True):
        for layer, values in (d.get("layers") or {}).items():
            shift = values.get("shift") or {}
            layer_rows.append(
                [
                    name,
                    layer,
                    fmt_number(shift.get("pick")),
                    fmt_number(shift.get("place")),
                    fmt_number(values.get("phase_retained"), True),
                    fmt_number(values.get("container_silhouette")),
                ]
            )
    if layer_rows:
        section.blocks.append(
            Table(
                "layer-diagnostics",
                "Diagnostics per layer",
                [
                    "policy",
                    "layer",
                    "shift (pick)",
                    "shift (place)",
                    "phase retained",
                    "container silhouette",
                ],
                layer_rows,
            )
        )
    return section


def _section_tsne(diagnostics: list[tuple[Path, dict]]) -> Section:
    section = Section("t-SNE projections")
    figures = [
        (folder, d, name, rel) for folder, d in diagnostics for name, rel in (d.get("figures") or {}).items()
    ]
    if not figures:
        return section.note("No t-SNE figures: `condground diagnose` writes them under its figures/ folder.")
    section.blocks.append(
        Para(
            "Illustrative only: the quantitative comparisons above are computed in the "
            "original feature space."
        )
    )
    for folder, d, name, rel in figures:
        label = d.get("policy_label", folder.name)
        section.blocks.append(
            Figure(
                f"tsne-{label}-{name}", (folder / rel).read_bytes(), f"{label} · {d.get('task', '')}: {name}"
            )
        )
    return section


def _still_caption(d: dict, rel: str) -> str:
    """Policy, scene and head of an attention still; its step and the phase predicted there when the
    file name carries the step (`step_0042.png`, as `condground attention` writes)."""
    caption = (
        f"{d.get('policy_label', '')} · {d.get('task', '')} · {d.get('condition', '')} · "
        f"seed {d.get('seed', '?')} · head {d.get('head', '?')}: {Path(rel).stem}"
    )
    match = re.search(r"(\d+)$", Path(rel).stem)
    phases = d.get("phase_predicted") or []
    if match and int(match.group(1)) < len(phases) and phases[int(match.group(1))] is not None:
        caption += f", predicted phase {phases[int(match.group(1))]}"
    return caption


def _section_attention(attention: list[tuple[Path, dict]]) -> Section:
    section = Section("Attention stills")
    stills = [(folder, d, rel) for folder, d in attention for rel in (d.get("stills") or [])]
    if not stills:
        return section.note("No attention stills: `condground attention` writes them with its video.")
    rows = []
    for name, (folder, d) in zip(_unique_names(attention), attention, strict=True):
        mass = d.get("attention_mass_mean") or {}
        rows.append(
            [
                name,
                str(d.get("task", "")),
                str(d.get("condition", "")),
                str(d.get("seed", "")),
                str(d.get("head", "")),
                str(d.get("frames", "")),
                "\n".join(f"{k}: {fmt_number(v)}" for k, v in mass.items()) or "—",
                str(folder / d["video"]) if d.get("video") else "—",
            ]
        )
    section.blocks += [
        Para("The supervised decoder head's attention over the episode; the video is not embedded."),
        Table(
            "attention",
            "Attention episodes",
            ["policy", "task", "condition", "seed", "head", "steps", "mean attention mass", "video"],
            rows,
        ),
    ]
    for folder, d, rel in stills:
        section.blocks.append(
            Figure(
                f"attention-{d.get('policy_label', folder.name)}-{Path(rel).stem}",
                (folder / rel).read_bytes(),
                _still_caption(d, rel),
            )
        )
    return section


def _section_probe(probes: list[tuple[Path, dict]]) -> Section:
    section = Section("Prompt-swap probe")
    if not probes:
        return section.note(
            "No probe output among the inputs: `condground probe` runs each layout with "
            "the target's prompt and with a competitor's prompt swapped in."
        )

    def arm(s):
        s = s or {}
        return fmt_rate(s.get("k", 0), s.get("n", 0), s.get("low", math.nan), s.get("high", math.nan))

    names = _unique_names(probes)
    rows = [
        [
            name,
            str(d.get("condition", "")),
            str(d.get("selection", d.get("role", ""))),
            str(d.get("episodes", "")),
            arm(d.get("target")),
            arm(d.get("swapped")),
            fmt_diff(d.get("difference")),
            paper.probe_range("target", "–"),
            paper.probe_range("swapped", "–"),
        ]
        for name, (_, d) in zip(names, probes, strict=True)
    ]
    section.blocks += [
        Para(
            "Competitor selection with the target's prompt and with a competitor's crop swapped in, on the "
            "same layouts. The paper reports 0–1 % competitor selection with the target prompt and 35–91 % "
            "swapped. Difference: swapped − target, Newcombe paired interval, exact McNemar p."
        ),
        Table(
            "probe",
            "Prompt-swap probe: competitor selected",
            [
                "policy",
                "condition",
                "selection measured",
                "layouts",
                "target prompt",
                "swapped prompt",
                "swapped − target",
                "target",
                "swapped",
            ],
            rows,
            groups=[("this report", 7), ("paper", 2)],
        ),
        Figure(
            "probe",
            probe_figure(list(zip(names, (d for _, d in probes), strict=True))),
            "Competitor selection with the target prompt and the swapped prompt, per probe.",
        ),
    ]
    return section


def _interval(row: dict, low: str, high: str, p: str) -> str:
    values = [row.get(k) for k in ("diff", low, high, p)]
    if any(v is None or (isinstance(v, float) and math.isnan(v)) for v in values[:3]):
        return "n/a (one run an arm shows no training spread)" if low.startswith("cluster") else "n/a"
    d, lo, hi, pv = values
    return f"{100 * d:+.1f} pp [{100 * lo:+.1f}, {100 * hi:+.1f}], p={pv:.3g}"


def _section_comparisons(comparisons: list[tuple[Path, dict]]) -> Section:
    section = Section("Comparisons of training recipes")
    if not comparisons:
        return section.note(
            "No comparison among the inputs: `condground compare` trains two recipes side by side and pairs "
            "their late checkpoints on the same held-out layouts; give its comparison folder as --input_dir."
        )
    rows, figures = [], []
    for folder, data in comparisons:
        for row in data["summary"]:
            rows.append([
                f"{row.get('lever')} vs {row.get('baseline_arm')}", task_title(str(row.get("task", ""))),
                str(row.get("condition", "")), str(row.get("seeds", "")), str(row.get("n", "")),
                f"{pct(row.get('baseline'))}%", f"{pct(row.get('treated'))}%",
                _interval(row, "cluster_low", "cluster_high", "cluster_p"), str(row.get("seed_effects", "")),
                _interval(row, "diff_low", "diff_high", "p"), str(row.get("differences") or "none"),
            ])  # fmt: skip
        figures.append(
            Figure(
                f"compare-{folder.name}",
                (folder / (data.get("figure") or "compare.png")).read_bytes(),
                f"{folder.name}: held-out success of every checkpoint (95 % Wilson intervals), per condition.",
            )
        )
    columns = ["comparison", "task", "condition", "seeds", "pooled pairs", "baseline", "treated",
               "difference (layout-clustered, run-aware)", "per-seed effects", "Newcombe / McNemar (pairs as independent)",
               "budget or data differences"]  # fmt: skip
    section.blocks += [
        Para(
            "treated − baseline over the pooled late checkpoints of every training run, on the same held-out "
            "layouts. The run-aware interval takes the layout as the pairing unit and the training run as the "
            "replicate (Student's t, Welch–Satterthwaite degrees of freedom); with two runs an arm the training "
            "spread rests on two runs each. The Newcombe interval treats every pooled pair as independent and "
            "is shown for comparison with earlier tables only."
        ),
        Table("comparisons", "Comparisons: treated − baseline", columns, rows, open=True),
        *figures,
    ]
    return section


OPERATOR = " (operator-scored)"


def _paper_subgoal(condition: str, subgoal: str) -> str:
    """The paper's count for a row of the subgoal table: it reports all five subgoals and the two routing
    ones pooled; the others were unaffected, so 5/5 each (overall minus routing is 15/15)."""
    study = paper.SUBGOAL_STUDY[condition]
    if subgoal in SUBGOAL_POOLS:
        k, n = study[subgoal]
    elif subgoal in ROUTING_SUBGOALS:
        return "{}/{} (pooled)".format(*study["routing"])
    else:
        k = n = paper.SUBGOAL_TRIALS
    return f"{k}/{n}"


def _section_subgoals(trials: pd.DataFrame) -> Section:
    section = Section(f"VLA case study: success per subgoal ({ROUTING_TASK})")
    if trials.empty:
        return section.note(
            "No subgoal trials among the inputs: `condground subgoals` evaluates each subgoal of "
            f"{ROUTING_TASK} from its own initial state under the cue, no_cue and explicit conditions."
        )
    # Trials scored on the arm are another experiment than the simulated ones: their own columns.
    trials = trials.assign(
        arm=trials["condition"] + trials["scored_by"].map(lambda by: OPERATOR if by == "operator" else "")
    )
    order = list(paper.SUBGOAL_STUDY)
    arms = sorted(
        set(trials["arm"]),
        key=lambda a: (
            order.index(a.removesuffix(OPERATOR)) if a.removesuffix(OPERATOR) in order else len(order),
            a,
        ),
    )
    studied = [c for c in order if c in set(trials["condition"])]
    by = {(c["subgoal"], c["arm"]): c for c in subgoal_rates(trials, by=("arm",))}
    rows = []
    for name in (*SUBGOALS, *SUBGOAL_POOLS):
        if any((name, arm) in by for arm in arms):
            ours = [by.get((name, arm)) for arm in arms]
            rows.append(
                [
                    SUBGOAL_TITLES[name],
                    *[fmt_rate(c["k"], c["n"], c["low"], c["high"]) if c else "not run" for c in ours],
                    *[_paper_subgoal(condition, name) for condition in studied],
                ]
            )
    policies = "; ".join(
        f"{arm}: {', '.join(sorted(set(trials.loc[trials['arm'] == arm, 'policy_label'])))}" for arm in arms
    )
    section.blocks += [
        Para(
            "Success % [95 % Wilson interval] (successes/trials) per subgoal, each from its own initial state; "
            f"{' and '.join(ROUTING_SUBGOALS)} are the routing subgoals, whose destination depends on the "
            "instrument's state. "
            + "; ".join(f"{c}: {study['method']}" for c, study in paper.SUBGOAL_STUDY.items())
            + f" (the conditions are not equally informed). Policies: {policies}."
        ),
        Para(
            "The paper (π0.5, 5 trials per subgoal and condition) reports the five subgoals and the two routing "
            "subgoals pooled; a non-routing subgoal's 5/5 follows from its statement that those subgoals were "
            "unaffected, and a routing subgoal's row shows the pooled route + place count.",
            note=True,
        ),
        Table(
            "subgoals",
            "Success per subgoal and condition",
            ["subgoal", *arms, *studied],
            rows,
            groups=[("", 1), ("this report", len(arms)), ("paper", len(studied))],
        ),
    ]
    return section


def _versions_text(versions) -> str:
    return "; ".join(f"{k} {v}" for k, v in (versions or {}).items()) or "—"


def _command_text(command) -> str:
    if isinstance(command, list):
        return shlex.join(str(c) for c in command)
    return str(command) if command else "—"


def _runs(data: dict) -> list[dict]:
    """A subgoals directory's runs, one per condition, each with its command and checkpoint."""
    return list((data.get("runs") or {}).values()) if data.get("kind") == "subgoals" else []


def _commands_text(data: dict) -> str:
    if data.get("kind") == "subgoals":
        return "\n".join(_command_text(run.get("command")) for run in _runs(data)) or "—"
    return _command_text(data.get("command"))


def _checkpoints_text(data: dict) -> str:
    if data.get("kind") in ("sweep", "subgoals"):
        checkpoints = [run.get("checkpoint") or {} for run in _runs(data)] or data.get("checkpoints", [])
        return (
            "\n".join(
                f"{c.get('label')}: {c.get('path')} (hash {c.get('hash')}, "
                f"training seed {c.get('training_seed')})"
                for c in checkpoints
            )
            or "—"
        )
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


def _section_provenance(inputs: Inputs, cfg: ReportConfig) -> Section:
    rows = [
        [
            str(folder),
            str(d.get("kind")),
            _commands_text(d),
            _versions_text(d.get("versions")),
            _checkpoints_text(d),
        ]
        for folder, d in inputs.sources
    ]
    command = ["condground", "report", *[f"--input_dir={x}" for x in cfg.input_dir], f"--output={cfg.output}"]
    rows.append(["(this report)", "report", shlex.join(command), _versions_text(report_versions()), "—"])
    columns = ["input", "kind", "command", "versions", "checkpoints (path, hash)"]
    return Section(
        "Provenance", [Table("provenance", "Inputs: commands, versions, checkpoints", columns, rows)]
    )


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "-", text).strip("-").lower() or "figure"


def _name_figures(figures: list[Figure]) -> None:
    """Figure names become HTML ids and Markdown file names, so they must be unique and file-name safe."""
    taken: set[str] = set()
    for figure in figures:
        name = base = _slug(figure.name)
        i = 1
        while name in taken:
            i += 1
            name = f"{base}-{i}"
        taken.add(name)
        figure.name = name


def build_document(inputs: Inputs, cfg: ReportConfig) -> Document:
    results = inputs.results
    methods = _label_methods(results) if len(results) else {}
    labels = _label_order(results["policy_label"], methods) if len(results) else []
    metrics = cell_metrics(results, by=CELL) if len(results) else None  # the overview's and the stages'
    intro = []
    if len(results):
        sweeps = results["source"].nunique()
        intro.append(
            Para(
                f"{len(results)} episodes from {sweeps} sweep director{'y' if sweeps == 1 else 'ies'}: "
                f"policies {', '.join(labels)}; tasks {', '.join(_task_order(results['task']))}; "
                f"{results['condition'].nunique()} conditions; {results['checkpoint_hash'].nunique()} "
                "checkpoints. Intervals are 95 %."
            )
        )
    variants = _section_variant_differences(results, labels)
    # Its figures lead the report; its table stays with the other tables.
    variant_figures = [b for b in variants.blocks if isinstance(b, Figure)]
    variants.blocks = [b for b in variants.blocks if not isinstance(b, Figure)]
    if variant_figures:
        variants.blocks.append(Para("The plots of these differences are in 'At a glance' above."))
    document = Document(
        cfg.title,
        intro,
        [
            _section_overview(results, metrics, methods, labels, variant_figures),
            _section_table1(results, methods, labels),
            _section_stages(results, metrics, methods, labels),
            _section_condition_differences(results, labels),
            variants,
            _section_subgoals(inputs.subgoals),
            _section_table2(inputs.diagnostics),
            _section_tsne(inputs.diagnostics),
            _section_attention(inputs.attention),
            _section_probe(inputs.probes),
            _section_comparisons(inputs.comparisons),
            _section_provenance(inputs, cfg),
        ],
    )
    _name_figures(document.figures)
    return document
