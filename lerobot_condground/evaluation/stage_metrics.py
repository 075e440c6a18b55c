"""Stage metrics from per-episode stage indices (0 none, 1 pick, 2 lift, 3 place)."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import pandas as pd

from lerobot_condground.evaluation.statistics import counts

STAGE_METRICS = ("success", "p_pick", "p_lift_given_pick", "p_place_given_pick_lift")


def stage_metrics(stages: Iterable[int]) -> dict:
    """Success, P(pick), P(lift|pick), P(place|pick,lift) as (k, n), each with its own denominator, counted
    as the sweep's statistics count them."""
    stages = np.asarray(list(stages), dtype=int)
    flags = pd.DataFrame(
        {"success": stages >= 3, "pick": stages >= 1, "lift": stages >= 2, "place": stages >= 3}
    )
    return {"episodes": len(stages), **{metric: counts(flags, metric) for metric in STAGE_METRICS}}


def _pct(k: int, n: int) -> str:
    return f"{100 * k / n:5.1f}% ({k}/{n})" if n else "   n/a (0/0)"


def format_table(rows: list[tuple[str, str, dict]], first_column: str = "task") -> str:
    """rows: (task or policy, condition, stage_metrics(...))."""
    header = f"{first_column:<22} {'condition':<20} {'success':>16} {'P(pick)':>16} {'P(lift|pick)':>16} {'P(place|pick,lift)':>19}"
    lines = [header, "-" * len(header)]
    for task, condition, m in rows:
        lines.append(
            f"{task:<22} {condition:<20} {_pct(*m['success']):>16} {_pct(*m['p_pick']):>16} "
            f"{_pct(*m['p_lift_given_pick']):>16} {_pct(*m['p_place_given_pick_lift']):>19}"
        )
    return "\n".join(lines)
