"""The report's own matplotlib figures, each returned as PNG bytes."""

from __future__ import annotations

import io
import math

import numpy as np
import pandas as pd

from lerobot_condground.evaluation.statistics import METRIC_TITLES, METRICS

from .formatting import task_title


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
    for ax, metric in zip(axes, panels, strict=False):
        for offset, label in zip(_series_offsets(len(labels)), labels, strict=False):
            cell = metrics[metrics["policy_label"] == label].set_index("condition").reindex(conditions)
            y = cell[metric].to_numpy(float)
            err = np.vstack(
                [y - cell[f"{metric}_low"].to_numpy(float), cell[f"{metric}_high"].to_numpy(float) - y]
            )
            ax.errorbar(
                x + offset,
                100 * y,
                yerr=100 * _nonnegative(err),
                fmt="o",
                ms=3.5,
                capsize=2,
                lw=1,
                label=label,
            )
        _condition_axis(ax, conditions, f"{METRIC_TITLES[metric]} (%)", (-5, 105))
    return _panels_done(
        fig, axes, len(panels), min(4, max(1, len(labels))),
        f"{task_title(task)}: stage metrics per condition (95 % Wilson intervals)",
    )  # fmt: skip


def _condition_axis(ax, conditions: list[str], title: str, ylim: tuple[float, float]) -> None:
    ax.set_title(title, fontsize=9)
    ax.set_ylim(*ylim)
    ax.set_xticks(np.arange(len(conditions)), conditions, rotation=60, ha="right", fontsize=7)
    ax.tick_params(axis="y", labelsize=7)
    ax.grid(axis="y", alpha=0.3)


def _panels_done(fig, axes, used: int, ncol: int, title: str) -> bytes:
    """Hides the unused panels, puts the first panel's legend under all and the title over all."""
    for ax in axes[used:]:
        ax.set_visible(False)
    handles, names = axes[0].get_legend_handles_labels()
    fig.legend(handles, names, loc="outside lower center", ncol=ncol, fontsize=8)
    fig.suptitle(title, fontsize=10)
    return _png(fig)


def difference_figure(title: str, diffs: pd.DataFrame, series: str, conditions: list[str]) -> bytes:
    labels = list(dict.fromkeys(diffs[series]))
    fig, (ax,) = _new_figure(min(18.0, max(6.0, _panel_width(len(conditions), len(labels)))), 3.6)
    x = np.arange(len(conditions))
    for offset, label in zip(_series_offsets(len(labels)), labels, strict=False):
        cell = diffs[diffs[series] == label].set_index("condition").reindex(conditions)
        y = cell["diff"].to_numpy(float)
        err = np.vstack([y - cell["low"].to_numpy(float), cell["high"].to_numpy(float) - y])
        ax.errorbar(
            x + offset, 100 * y, yerr=100 * _nonnegative(err), fmt="o", ms=3.5, capsize=2, lw=1, label=label
        )
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
        err = np.vstack(
            [
                y - np.array([s.get("low", np.nan) for s in stats], float),
                np.array([s.get("high", np.nan) for s in stats], float) - y,
            ]
        )
        ax.bar(x + offset, 100 * y, width=0.32, label=f"{arm} prompt")
        # errorbar, not bar(yerr=): bar's own error bars trip a NumPy deprecation on (2, n) arrays
        ax.errorbar(x + offset, 100 * y, yerr=100 * _nonnegative(err), fmt="none", capsize=3, ecolor="0.2")
    ax.set_xticks(x, [name for name, _ in probes], fontsize=7)
    ax.set_ylim(0, 105)
    ax.set_ylabel("competitor selected (%)", fontsize=8)
    ax.legend(fontsize=7)
    ax.set_title("Prompt-swap probe (95 % Wilson intervals)", fontsize=9)
    return _png(fig)


def success_figure(
    task: str, metrics: pd.DataFrame, labels: list[str], conditions: list[str], paper: dict
) -> bytes:
    """Success per policy and condition with 95 % Wilson intervals; `paper[(label, condition)]` (in %) as
    an open diamond of the policy's colour where the paper reports that cell."""
    fig, (ax,) = _new_figure(min(18.0, max(6.0, _panel_width(len(conditions), len(labels)))), 3.6)
    x = np.arange(len(conditions))
    for i, (offset, label) in enumerate(zip(_series_offsets(len(labels)), labels, strict=False)):
        cell = metrics[metrics["policy_label"] == label].set_index("condition").reindex(conditions)
        y = cell["success"].to_numpy(float)
        err = np.vstack([y - cell["success_low"].to_numpy(float), cell["success_high"].to_numpy(float) - y])
        ax.errorbar(x + offset, 100 * y, yerr=100 * _nonnegative(err), fmt="o", ms=4, capsize=2, lw=1,
                    color=f"C{i}", label=label)  # fmt: skip
        reported = [(j, paper[(label, c)]) for j, c in enumerate(conditions) if (label, c) in paper]
        if reported:
            j, value = zip(*reported, strict=True)
            ax.plot(np.array(j) + offset, value, "D", mfc="none", mec=f"C{i}", ms=7, mew=1.2)
    if paper:
        ax.plot([], [], "D", mfc="none", mec="0.3", ms=7, label="paper (same colour)")
    ax.set_ylim(-5, 105)
    ax.set_ylabel("success (%)", fontsize=8)
    ax.set_xticks(x, conditions, rotation=60, ha="right", fontsize=7)
    ax.grid(axis="y", alpha=0.3)
    fig.legend(loc="outside lower center", ncol=min(4, max(1, len(labels) + bool(paper))), fontsize=8)
    ax.set_title(f"{task_title(task)}: success per policy and condition (95 % Wilson intervals)", fontsize=9)
    return _png(fig)


FUNNEL_STAGES = ("picked", "lifted", "placed")


def funnel_figure(task: str, funnel: pd.DataFrame, labels: list[str], conditions: list[str]) -> bytes:
    """Per policy, the share of all episodes that got at least as far as each stage, per condition: where
    the bars drop is the stage that fails. `funnel` has policy_label, condition, stage, rate, low, high."""
    cols = min(2, len(labels))
    rows = math.ceil(len(labels) / cols)
    width = min(18.0, cols * max(4.5, 0.9 + 0.45 * len(conditions)))
    fig, axes = _new_figure(width, 0.8 + 2.5 * rows, rows, cols)
    x = np.arange(len(conditions))
    for ax, label in zip(axes, labels, strict=False):
        for i, stage in enumerate(FUNNEL_STAGES):
            cell = funnel[(funnel.policy_label == label) & (funnel.stage == stage)]
            cell = cell.set_index("condition").reindex(conditions)
            y = cell["rate"].to_numpy(float)
            err = np.vstack([y - cell["low"].to_numpy(float), cell["high"].to_numpy(float) - y])
            ax.bar(x + (i - 1) * 0.27, 100 * y, width=0.27, color=f"C{i}", label=stage)
            ax.errorbar(x + (i - 1) * 0.27, 100 * y, yerr=100 * _nonnegative(err), fmt="none", capsize=1.5,
                        ecolor="0.2", lw=0.8)  # fmt: skip
        _condition_axis(ax, conditions, label, (0, 105))
    return _panels_done(
        fig, axes, len(labels), 3,
        f"{task_title(task)}: episodes reaching each stage (% of all, 95 % Wilson intervals)",
    )  # fmt: skip
