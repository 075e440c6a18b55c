"""How rates, differences, diagnostic values and task names are written in tables, captions and titles."""

from __future__ import annotations

import math

TASK_SHORT = {"PickPlaceFixedBin-v0": "T1", "PickPlaceRandomBin-v0": "T2"}


def pct(x: float, digits: int = 1) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100 * x:.{digits}f}"


def fmt_rate(k: int, n: int, low: float, high: float) -> str:
    if not n:
        return "n/a (0/0)"
    return f"{pct(k / n)}% [{pct(low)}, {pct(high)}] ({int(k)}/{int(n)})"


def fmt_diff(d) -> str:
    if d is None or not d.get("n") or d.get("diff") is None or math.isnan(d["diff"]):
        return "n/a"
    p = d.get("p_value")
    p_text = "" if p is None else f", McNemar p={p:.3g}"
    return f"{100 * d['diff']:+.1f} pp [{100 * d['low']:+.1f}, {100 * d['high']:+.1f}] (n={d['n']}{p_text})"


def fmt_number(value, percent: bool = False) -> str:
    """A diagnostic value: 4 decimals, or one decimal and % for values diagnose writes in percent."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "—"
    if not isinstance(value, (int, float)):
        return str(value)
    return f"{value:.1f}%" if percent else f"{value:.4f}"


def seed_spread(row) -> str:
    seeds = int(row["training_seeds"])
    if seeds <= 1:
        return f"{pct(row['success_seed_mean'])}% (1 seed)"
    return (
        f"{pct(row['success_seed_mean'])}% ± {pct(row['success_seed_std'])} "
        f"[{pct(row['success_seed_min'])}, {pct(row['success_seed_max'])}] ({seeds} seeds)"
    )


def metric_cell(row, metric: str) -> str:
    return fmt_rate(row[f"{metric}_k"], row[f"{metric}_n"], row[f"{metric}_low"], row[f"{metric}_high"])


def task_title(task: str) -> str:
    return f"{TASK_SHORT[task]} {task}" if task in TASK_SHORT else task
