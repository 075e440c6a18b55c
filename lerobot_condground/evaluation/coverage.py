"""Is a comparison's interval honest? Synthetic lever experiments with a known effect, scored by each method.

A lever comparison trains each arm a few times (runs), keeps its last checkpoints and rolls every one out
once on the same held-out layouts. The simulation draws such an experiment from a logistic model,

    logit P(success) = base + effect·[treated] + u_layout + z_arm,layout + v_run + w_run,checkpoint,

with every term normal: layouts that differ in difficulty (u), an arm that suits some layouts more than
others (z), training runs that differ (v) and checkpoints that swing (w). The true difference is the
population's, over new layouts, runs and checkpoints; with effect 0 it is exactly 0 (the arms' terms are
identically distributed). Each method gets the rollouts and returns an interval and a p-value; over many
experiments, `coverage` counts how often the interval holds the truth and how often p < α under effect 0.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.special import expit

from lerobot_condground.evaluation.statistics import ALPHA, paired_difference, run_layout_interval


@dataclass(frozen=True)
class Design:
    """One synthetic comparison; the defaults match the published levers' spread (docs/diagnosis.md)."""

    runs: int = 2
    checkpoints: int = 3
    layouts: int = 50
    base: float = 0.0
    effect: float = 0.0
    layout_sd: float = 1.5
    interaction_sd: float = 0.5
    run_sd: float = 0.3
    checkpoint_sd: float = 0.4

    def true_difference(self) -> float:
        """rate(treated) − rate(baseline) over the population (Gauss–Hermite quadrature of the normal sum)."""
        sd = np.sqrt(self.layout_sd**2 + self.interaction_sd**2 + self.run_sd**2 + self.checkpoint_sd**2)
        x, w = np.polynomial.hermite_e.hermegauss(80)
        w = w / w.sum()
        return float(w @ (expit(self.base + self.effect + sd * x) - expit(self.base + sd * x)))

    def draw(self, rng: np.random.Generator) -> np.ndarray:
        """Outcomes, arms × runs × checkpoints × layouts (arm 0 the baseline)."""
        shape = (2, self.runs, self.checkpoints, self.layouts)
        logit = (
            self.base
            + self.effect * np.arange(2)[:, None, None, None]
            + self.layout_sd * rng.standard_normal(self.layouts)
            + self.interaction_sd * rng.standard_normal((2, 1, 1, self.layouts))
            + self.run_sd * rng.standard_normal((2, self.runs, 1, 1))
            + self.checkpoint_sd * rng.standard_normal((2, self.runs, self.checkpoints, 1))
        )
        return rng.random(shape) < expit(logit)


def newcombe_mcnemar(y: np.ndarray, rng, alpha: float = ALPHA) -> tuple[float, float, float]:
    """The lever protocol of issue 27: (run index, checkpoint rank, layout) pairs taken as independent."""
    d = paired_difference(y[0].ravel(), y[1].ravel(), alpha)
    return d["low"], d["high"], d["p_value"]


def run_layout_t(y: np.ndarray, rng, alpha: float = ALPHA) -> tuple[float, float, float]:
    """`statistics.clustered_difference` (from its parts: the simulation's tables are complete arrays)."""
    m = y.mean(axis=2)  # arms × runs × layouts: checkpoints averaged
    d = m[1].mean(axis=0) - m[0].mean(axis=0)
    out = run_layout_interval(m[0].mean(axis=1), m[1].mean(axis=1), float(d.var(ddof=1)), d.size, alpha)
    return out["low"], out["high"], out["p_value"]


def _bootstrap(
    y: np.ndarray, rng, alpha: float, runs: bool, n_boot: int = 1000
) -> tuple[float, float, float]:
    """Percentile interval of resampled layouts (and, when `runs`, each arm's runs first); the p-value is
    twice the share of resamples on the far side of 0 (a bootstrap test by interval inversion)."""
    m = y.mean(axis=2)  # arms × runs × layouts: checkpoints averaged
    n_runs, n_layouts = m.shape[1], m.shape[2]
    if runs:
        pick = rng.integers(0, n_runs, size=(2, n_boot, n_runs))
        arm = np.stack([m[i][pick[i]].mean(axis=1) for i in range(2)])  # 2 × boot × layouts
    else:
        arm = np.broadcast_to(m.mean(axis=1)[:, None, :], (2, n_boot, n_layouts))
    weights = rng.multinomial(n_layouts, np.full(n_layouts, 1 / n_layouts), size=n_boot) / n_layouts
    diffs = ((arm[1] - arm[0]) * weights).sum(axis=1)
    low, high = np.quantile(diffs, [alpha / 2, 1 - alpha / 2])
    p = min(1.0, 2 * min((diffs <= 0).mean(), (diffs >= 0).mean()))
    return float(low), float(high), float(p)


def layout_bootstrap(y: np.ndarray, rng, alpha: float = ALPHA) -> tuple[float, float, float]:
    """Layouts resampled, the runs kept: honest about layouts, blind to training variance."""
    return _bootstrap(y, rng, alpha, runs=False)


def hierarchical_bootstrap(y: np.ndarray, rng, alpha: float = ALPHA) -> tuple[float, float, float]:
    """Each arm's runs resampled, then the layouts (shared by both arms, so the pairing is kept)."""
    return _bootstrap(y, rng, alpha, runs=True)


METHODS: dict[str, Callable] = {
    "newcombe_mcnemar": newcombe_mcnemar,
    "layout_bootstrap": layout_bootstrap,
    "hierarchical_bootstrap": hierarchical_bootstrap,
    "run_layout_t": run_layout_t,
}


def coverage(
    effect_design: Design, null_design: Design, n_sim: int, seed: int = 0, alpha: float = ALPHA, methods=None
) -> pd.DataFrame:
    """One row per method: how often its interval holds the true difference of `effect_design`, how often
    p < alpha under `null_design` (whose effect must be 0), and the interval's median width."""
    if null_design.effect != 0:
        raise ValueError(
            f"null_design.effect must be 0 (the false-positive rate needs a null); got {null_design.effect}"
        )
    truth = effect_design.true_difference()
    rows = []
    for name in methods or METHODS:
        method = METHODS[name]
        rng = np.random.default_rng(seed)  # every method sees the same experiments
        held, false_positives, widths = 0, 0, []
        for _ in range(n_sim):
            low, high, _ = method(effect_design.draw(rng), rng, alpha)
            held += low <= truth <= high
            widths.append(high - low)
            false_positives += method(null_design.draw(rng), rng, alpha)[2] < alpha
        rows.append({
            "method": name, "coverage": held / n_sim, "false_positive_rate": false_positives / n_sim,
            "n_sim": n_sim, "median_width": float(np.median(widths)), "true_difference": truth,
        })  # fmt: skip
    return pd.DataFrame(rows)
