"""Stage metrics from per-episode stage indices (0 none, 1 pick, 2 lift, 3 place)."""

from __future__ import annotations

from collections.abc import Iterable


def stage_metrics(stages: Iterable[int]) -> dict:
    """Success, P(pick), P(lift|pick), P(place|pick,lift), each with its own denominator."""
    stages = list(stages)
    n = len(stages)
    picked = sum(s >= 1 for s in stages)
    lifted = sum(s >= 2 for s in stages)
    placed = sum(s >= 3 for s in stages)
    return {
        "episodes": n,
        "success": (placed, n),
        "p_pick": (picked, n),
        "p_lift_given_pick": (lifted, picked),
        "p_place_given_pick_lift": (placed, lifted),
    }


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
