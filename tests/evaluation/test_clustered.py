"""The run-aware, layout-paired comparison (`statistics.clustered_difference`), Holm, and the simulation that
chose it (`evaluation.coverage`): its interval must hold a known difference and its test keep a null."""

import numpy as np
import pandas as pd
import pytest

from lerobot_condground.evaluation.coverage import Design, coverage
from lerobot_condground.evaluation.statistics import clustered_difference, holm


def arm(rates_by_run: list[list[float]], checkpoints: int = 1) -> pd.DataFrame:
    """Rollouts of one arm: run r succeeds on layout l in round(rate × checkpoints) of its checkpoints."""
    rows = []
    for run, rates in enumerate(rates_by_run):
        for layout, rate in enumerate(rates):
            wins = round(rate * checkpoints)
            rows += [
                {"run": run, "checkpoint": c, "layout": layout, "success": c < wins}
                for c in range(checkpoints)
            ]
    return pd.DataFrame(rows)


def test_difference_is_of_run_averaged_rates_and_seed_effects_pair_runs_in_order():
    a = arm([[1, 0, 0, 0], [1, 1, 0, 0]])
    b = arm([[1, 1, 1, 0], [1, 1, 1, 1]])
    d = clustered_difference(a, b)
    assert (d["rate_a"], d["rate_b"], d["diff"]) == (0.375, 0.875, 0.5)
    assert d["seed_effects"] == [0.5, 0.5]
    assert (d["layouts"], d["runs_a"], d["runs_b"]) == (4, 2, 2)


def test_interval_widens_when_training_runs_disagree():
    """Same pooled rates, same layouts: runs that disagree must make the interval wider and p larger."""
    layouts = 40
    steady_a = arm([[i % 4 == 0 for i in range(layouts)]] * 2)  # 25 % in both runs
    steady_b = arm([[i % 2 == 0 for i in range(layouts)]] * 2)  # 50 % in both runs
    shaky_b = arm([[True] * 30 + [False] * 10, [i % 4 == 0 for i in range(layouts)]])  # 75 % and 25 %: 50 %
    steady, shaky = clustered_difference(steady_a, steady_b), clustered_difference(steady_a, shaky_b)
    assert steady["diff"] == shaky["diff"] == 0.25
    assert shaky["high"] - shaky["low"] > 2 * (steady["high"] - steady["low"])
    assert shaky["p_value"] > 0.05 > steady["p_value"]


def test_one_run_per_arm_gives_no_interval():
    d = clustered_difference(arm([[1, 0, 1]]), arm([[1, 1, 1]]))
    assert d["diff"] == pytest.approx(1 / 3)
    assert np.isnan(d["low"]) and np.isnan(d["p_value"])


def test_identical_runs_everywhere_give_a_point_interval():
    d = clustered_difference(arm([[1, 1], [1, 1]]), arm([[1, 1], [1, 1]]))
    assert (d["diff"], d["low"], d["high"], d["p_value"]) == (0.0, 0.0, 0.0, 1.0)


def test_refuses_arms_on_different_layouts_and_runs_with_missing_layouts():
    a = arm([[1, 0], [1, 0]])
    b = arm([[1, 0], [1, 0]]).assign(layout=lambda t: t.layout + 1)
    with pytest.raises(ValueError, match="different layouts"):
        clustered_difference(a, b)
    holey = arm([[1, 0], [1, 0]]).iloc[:-1]
    with pytest.raises(ValueError, match="run 1 has no rollout on layout 1"):
        clustered_difference(a, holey)
    with pytest.raises(ValueError, match="missing \\['layout'\\]"):
        clustered_difference(a.drop(columns="layout"), a)


def test_holm_adjusts_a_family_and_keeps_nan():
    adjusted = holm([0.01, 0.04, np.nan, 0.03])
    assert adjusted[0] == pytest.approx(0.03)
    assert adjusted[1] == adjusted[3] == pytest.approx(0.06)
    assert np.isnan(adjusted[2])


def test_true_difference_matches_monte_carlo():
    design = Design(effect=0.5, runs=300, checkpoints=2, layouts=300)
    y = design.draw(np.random.default_rng(3))
    assert y[1].mean() - y[0].mean() == pytest.approx(design.true_difference(), abs=0.02)
    assert Design().true_difference() == 0.0


def test_chosen_method_covers_and_the_old_protocol_does_not():
    """Small and seeded; the large run is docs/statistics/coverage.csv. Run-to-run spread as published."""
    table = coverage(
        Design(effect=0.5), Design(), n_sim=150, seed=1, methods=["newcombe_mcnemar", "run_layout_t"]
    ).set_index("method")
    # 150 experiments: a method that truly covers 95 % falls below 0.90 here with probability about 1 %.
    assert table.loc["run_layout_t", "coverage"] >= 0.90
    assert table.loc["run_layout_t", "false_positive_rate"] <= 0.06
    # Pairs taken as independent and training runs ignored: too narrow, too many false positives.
    assert table.loc["newcombe_mcnemar", "coverage"] < 0.85
    assert table.loc["newcombe_mcnemar", "false_positive_rate"] > 0.15


def test_coverage_refuses_a_null_design_with_an_effect():
    with pytest.raises(ValueError, match="null_design.effect must be 0"):
        coverage(Design(effect=0.5), Design(effect=0.1), n_sim=1)
