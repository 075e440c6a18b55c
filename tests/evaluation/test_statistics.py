"""Rates, Wilson intervals, per-seed spread and paired differences of `lerobot_condground.evaluation.statistics`."""

import json

import numpy as np
import pandas as pd
import pytest
from scipy.stats import binomtest

from lerobot_condground.core.conditions import NAMED_CONDITIONS
from lerobot_condground.evaluation.results import COLUMNS
from lerobot_condground.evaluation.statistics import (
    cell_metrics,
    clustered_difference,
    condition_differences,
    paired_difference,
    rate,
    variant_differences,
    wilson_interval,
)


def episode_row(stage: int, **overrides) -> dict:
    """One results row in the sweep format; outcome columns follow the latched stage."""
    condition = overrides.get("condition", "clean")
    row = {
        "policy_label": "act",
        "policy_type": "act",
        "variant": "",
        "checkpoint": "ck/act",
        "checkpoint_hash": "0" * 16,
        "training_seed": 0,
        "task": "PickPlaceFixedBin-v0",
        "condition": condition,
        "condition_spec": json.dumps(NAMED_CONDITIONS[condition].__dict__),
        "counterbalanced": True,
        "eval_seed": 0,
        "episode": 0,
        "layout_seed": 0,
        "prompt": "target",
        "stage": stage,
        "success": stage >= 3,
        "pick": stage >= 1,
        "lift": stage >= 2,
        "place": stage >= 3,
        "grasped_first": 1 if stage else 0,
        "grasped_first_match": "target" if stage else "none",
        "grasped_competitor": 0,
        "grasped_competitor_match": "none",
        "selected_competitor_object": False,
        "target_location": "target_receptacle" if stage >= 3 else "elsewhere",
        "competitor_location": "none",
        "placed_in_competitor_receptacle": False,
        "target_x": 0.1,
        "target_y": 0.2,
        "target_z": 0.05,
        "competitor_x": np.nan,
        "competitor_y": np.nan,
        "competitor_z": np.nan,
        "receptacle_x": 0.3,
        "receptacle_y": -0.1,
        "steps": 300,
        "truncated": stage < 3,
        "physics_unstable": False,
    }
    row.update(overrides)
    assert set(row) == set(COLUMNS)
    return row


@pytest.mark.parametrize("k,n", [(0, 1), (1, 1), (0, 10), (10, 10), (3, 10), (37, 600), (599, 600)])
def test_wilson_bounds_match_scipy(k, n):
    low, high = wilson_interval(k, n)
    ref = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    assert low[0] == pytest.approx(ref.low, abs=1e-12)
    assert high[0] == pytest.approx(ref.high, abs=1e-12)


def test_wilson_without_episodes_is_nan():
    low, high = wilson_interval([0, 2], [0, 4])
    assert np.isnan(low[0]) and np.isnan(high[0])
    assert 0 < low[1] < 0.5 < high[1] < 1


def test_cell_metrics_denominators_and_seed_spread():
    # seed 0: stages 0 0 1 1 2 | seed 1: 2 2 3 3 3 -> pick 8/10, lift 6/8, place 3/6, success 3/10
    stages = [0, 0, 1, 1, 2, 2, 2, 3, 3, 3]
    rows = [
        episode_row(
            s, training_seed=i // 5, checkpoint_hash=f"{i // 5:016d}", episode=i % 5, layout_seed=i % 5
        )
        for i, s in enumerate(stages)
    ]
    rows[0].update(selected_competitor_object=True, grasped_competitor=4, competitor_location="elsewhere")
    rows[2].update(selected_competitor_object=True, placed_in_competitor_receptacle=True)
    rows[5].update(placed_in_competitor_receptacle=True)
    # a second cell where nothing is ever picked: the conditional rates have no denominator
    rows += [episode_row(0, condition="full_mixed", episode=i, layout_seed=i) for i in range(4)]
    out = cell_metrics(pd.DataFrame(rows)).set_index("condition")

    clean = out.loc["clean"]
    expected = {
        "success": (3, 10),
        "p_pick": (8, 10),
        "p_lift_given_pick": (6, 8),
        "p_place_given_pick_lift": (3, 6),
        "p_grasped_competitor": (2, 10),
        "p_placed_in_competitor_receptacle": (2, 10),
    }
    for metric, (k, n) in expected.items():
        assert (clean[f"{metric}_k"], clean[f"{metric}_n"]) == (k, n), metric
        assert clean[metric] == pytest.approx(k / n)
        ref = binomtest(k, n).proportion_ci(method="wilson")
        assert (clean[f"{metric}_low"], clean[f"{metric}_high"]) == pytest.approx((ref.low, ref.high))
    assert clean["episodes"] == 10
    # success per seed: 0/5 and 3/5
    assert clean["training_seeds"] == 2
    assert clean["success_seed_mean"] == pytest.approx(0.3)
    assert clean["success_seed_std"] == pytest.approx(np.std([0.0, 0.6], ddof=1))
    assert (clean["success_seed_min"], clean["success_seed_max"]) == pytest.approx((0.0, 0.6))

    empty = out.loc["full_mixed"]
    assert (empty["p_pick_k"], empty["p_pick_n"]) == (0, 4)
    assert empty["p_lift_given_pick_n"] == 0 and np.isnan(empty["p_lift_given_pick"])
    assert np.isnan(empty["p_lift_given_pick_low"]) and np.isnan(empty["p_place_given_pick_lift_high"])
    assert empty["training_seeds"] == 1 and np.isnan(empty["success_seed_std"])


def test_conditional_denominator_uses_every_earlier_stage():
    # an inconsistent row (lift without pick) must not count towards P(lift|pick)
    rows = [episode_row(2), episode_row(0, lift=True), episode_row(1)]
    out = cell_metrics(pd.DataFrame(rows)).iloc[0]
    assert (out["p_lift_given_pick_k"], out["p_lift_given_pick_n"]) == (1, 2)


def _paired(both: int, b_only: int, a_only: int, neither: int) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([1] * both + [0] * b_only + [1] * a_only + [0] * neither, dtype=bool)
    b = np.array([1] * both + [1] * b_only + [0] * a_only + [0] * neither, dtype=bool)
    return a, b


def test_newcombe_matches_published_example():
    # Cavo et al. (2012) complete response before/after consolidation, as analysed in Fagerland,
    # Lydersen & Laake, "Statistical Analysis of Contingency Tables" (2017), ch. 8: table
    # [[59, 6], [16, 80]]; Newcombe square-and-add: -0.0621 (95% CI -0.1186 to -0.0046).
    a, b = _paired(both=59, b_only=6, a_only=16, neither=80)  # b = before, a = after
    d = paired_difference(a, b)
    assert (d["n"], d["b_only"], d["a_only"]) == (161, 6, 16)
    assert d["diff"] == pytest.approx(-0.0621, abs=5e-5)
    assert d["low"] == pytest.approx(-0.1186, abs=5e-5)
    assert d["high"] == pytest.approx(-0.0046, abs=5e-5)
    assert d["p_value"] == pytest.approx(binomtest(6, 22, 0.5).pvalue)


@pytest.mark.parametrize(
    "counts", [(59, 6, 16, 80), (0, 0, 0, 30), (30, 0, 0, 0), (0, 12, 0, 0), (3, 1, 9, 2)]
)
def test_newcombe_contains_estimate_and_is_antisymmetric(counts):
    a, b = _paired(*counts)
    d, swapped = paired_difference(a, b), paired_difference(b, a)
    assert -1 <= d["low"] <= d["diff"] <= d["high"] <= 1
    assert d["diff"] == pytest.approx(b.mean() - a.mean())
    assert (swapped["low"], swapped["high"]) == pytest.approx((-d["high"], -d["low"]))
    assert swapped["p_value"] == pytest.approx(d["p_value"])
    if counts[1] == counts[2] == 0:
        assert d["p_value"] == 1.0


def test_newcombe_coverage_by_simulation():
    rng = np.random.default_rng(20240611)
    covered, trials = 0, 400
    # correlated pairs: a shared latent layout difficulty drives both outcomes
    for _ in range(trials):
        n = 60
        easy = rng.random(n) < 0.6
        a = np.where(easy, rng.random(n) < 0.95, rng.random(n) < 0.3)
        b = np.where(easy, rng.random(n) < 0.7, rng.random(n) < 0.1)
        truth = (0.6 * 0.7 + 0.4 * 0.1) - (0.6 * 0.95 + 0.4 * 0.3)
        d = paired_difference(a, b)
        covered += d["low"] <= truth <= d["high"]
    assert covered / trials >= 0.93, covered / trials


def test_paired_difference_rejects_unequal_lengths():
    with pytest.raises(ValueError, match="equal lengths"):
        paired_difference([True, False], [True])


def _grid_table(rng) -> pd.DataFrame:
    """Two labels x two training seeds x clean + two conditions x two eval seeds x 6 episodes, shuffled."""
    rows = []
    for label, skill in (("act", 0.4), ("act_modified/full", 0.9)):
        for seed in (0, 1):
            for condition in ("clean", "object_color_3", "full_mixed"):
                for eval_seed in (0, 1):
                    for episode in range(6):
                        p = 0.95 if condition == "clean" else skill
                        rows.append(
                            episode_row(
                                3 if rng.random() < p else int(rng.integers(0, 3)),
                                policy_label=label,
                                policy_type=label.split("/")[0],
                                variant=label.partition("/")[2],
                                checkpoint=f"ck/{label}/{seed}",
                                checkpoint_hash=f"{len(label):08x}{seed:08x}",
                                training_seed=seed,
                                condition=condition,
                                eval_seed=eval_seed,
                                episode=episode,
                                layout_seed=1000 * eval_seed + episode,
                            )
                        )
    df = pd.DataFrame(rows)
    return df.sample(frac=1.0, random_state=int(rng.integers(1 << 30))).reset_index(drop=True)


def test_condition_differences_pair_by_layout_not_row_order():
    df = _grid_table(np.random.default_rng(3))
    out = condition_differences(df).set_index(["policy_label", "condition"])
    assert len(out) == 4 and set(out["reference"]) == {"clean"}
    for (label, condition), row in out.iterrows():
        keys = ["checkpoint_hash", "eval_seed", "episode"]
        ref = df[(df.policy_label == label) & (df.condition == "clean")].set_index(keys)["success"]
        cond = df[(df.policy_label == label) & (df.condition == condition)].set_index(keys)["success"]
        expected = paired_difference(ref.sort_index().to_numpy(), cond.sort_index().to_numpy())
        assert row["n"] == 24
        assert row["diff"] == pytest.approx(cond.mean() - ref.mean())
        assert (row["low"], row["high"], row["p_value"]) == pytest.approx(
            (expected["low"], expected["high"], expected["p_value"])
        )
        assert (row["condition_only"], row["reference_only"]) == (expected["b_only"], expected["a_only"])


def test_condition_differences_refuse_mismatched_pairs():
    df = _grid_table(np.random.default_rng(4))
    missing = df.drop(df[(df.policy_label == "act") & (df.condition == "full_mixed")].index[0])
    with pytest.raises(
        ValueError, match=r"act / PickPlaceFixedBin-v0 / full_mixed vs clean: 1 episodes have no partner"
    ):
        condition_differences(missing)
    duplicated = pd.concat([df, df[(df.condition == "object_color_3")].iloc[:1]], ignore_index=True)
    with pytest.raises(ValueError, match="object_color_3 vs clean: the compared rows repeat the pairing key"):
        condition_differences(duplicated)
    with pytest.raises(ValueError, match="cannot be paired"):
        condition_differences(df, metric="p_lift_given_pick")


def test_condition_differences_of_competitor_selection():
    df = _grid_table(np.random.default_rng(5))
    df.loc[df.condition == "full_mixed", "selected_competitor_object"] = True
    out = condition_differences(df, metric="p_grasped_competitor")
    assert (out[out.condition == "full_mixed"]["diff"] == 1.0).all()
    assert (out[out.condition == "object_color_3"]["diff"] == 0.0).all()


def test_variant_differences_pair_on_training_seed_and_layout():
    df = _grid_table(np.random.default_rng(6))
    out = variant_differences(df, "act")
    assert set(out["policy_label"]) == {"act_modified/full"} and len(out) == 3
    keys = ["training_seed", "eval_seed", "episode"]
    for _, row in out.iterrows():
        cell = df[df.condition == row["condition"]]
        base = cell[cell.policy_label == "act"].set_index(keys)["success"].sort_index()
        other = cell[cell.policy_label == "act_modified/full"].set_index(keys)["success"].sort_index()
        expected = paired_difference(base.to_numpy(), other.to_numpy())
        assert row["n"] == 24 and row["baseline"] == "act"
        assert (row["diff"], row["low"], row["high"]) == pytest.approx(
            (expected["diff"], expected["low"], expected["high"])
        )

    # Training seeds pair by rank within each policy: seeds 10, 11 pair with 0, 1.
    other_seeds = df.copy()
    other_seeds.loc[other_seeds.policy_label == "act_modified/full", "training_seed"] += 10
    pd.testing.assert_frame_equal(variant_differences(other_seeds, "act"), out)
    one_seed_less = df[(df.policy_label == "act") | (df.training_seed == df.training_seed.min())]
    with pytest.raises(
        ValueError,
        match="act_modified/full vs act / PickPlaceFixedBin-v0 / clean: 12 episodes have no partner",
    ):
        variant_differences(one_seed_less, "act")
    with pytest.raises(ValueError, match="Baseline 'expert' is not among"):
        variant_differences(df, "expert")


def test_rate_and_difference_are_json_ready():
    r = rate(3, 10)
    ref = binomtest(3, 10).proportion_ci(method="wilson")
    assert r == {"k": 3, "n": 10, "rate": 0.3, "low": pytest.approx(ref.low), "high": pytest.approx(ref.high)}
    assert np.isnan(rate(0, 0)["rate"]) and np.isnan(rate(0, 0)["low"])
    d = paired_difference(*_paired(2, 3, 1, 4))
    assert all(type(v) in (int, float) for v in d.values())
    assert json.loads(json.dumps(d)) == d


def test_pairs_refuse_rows_of_other_layouts():
    # a sweep rerun with another seed offset: same (eval_seed, episode), other layouts
    df = _grid_table(np.random.default_rng(7))
    shifted = df.condition == "full_mixed"
    df.loc[shifted, "layout_seed"] += 10_000
    with pytest.raises(ValueError, match="full_mixed vs clean: 48 episodes have no partner"):
        condition_differences(df)
    with pytest.raises(ValueError, match="no partner"):
        variant_differences(
            df.assign(layout_seed=np.where(df.policy_label == "act", df.layout_seed, df.layout_seed + 1)),
            "act",
        )


def test_variant_differences_pair_pooled_checkpoints_by_rank_and_replicate_over_runs():
    """Three late checkpoints a run (the protocol): checkpoint k of run i pairs with checkpoint k of the
    baseline's run i, and the run-aware interval replicates over the runs, not the pooled pairs."""
    df = _grid_table(np.random.default_rng(8))
    pooled = pd.concat(
        [
            df.assign(
                checkpoint=df.checkpoint + f"/checkpoints/{step:06d}",
                checkpoint_hash=df.checkpoint_hash + f"{step:06d}",
            )
            for step in (4000, 5000, 6000)
        ],
        ignore_index=True,
    )
    out = variant_differences(pooled, "act").set_index("condition")
    single = variant_differences(df, "act").set_index("condition")
    assert (out["n"] == 3 * single["n"]).all() and (out["runs"] == 2).all()
    assert (out["diff"] == single["diff"]).all()
    row = out.loc["full_mixed"]
    cell = df[df.condition == "full_mixed"]
    runs = {
        label: cell[cell.policy_label == label].assign(
            run=lambda t: t.training_seed, layout=lambda t: t.episode + 100 * t.eval_seed
        )
        for label in ("act", "act_modified/full")
    }
    expected = clustered_difference(runs["act"], runs["act_modified/full"])
    assert (row["cluster_low"], row["cluster_high"], row["cluster_p"]) == pytest.approx(
        (expected["low"], expected["high"], expected["p_value"])
    )
    assert row["cluster_high"] > row["cluster_low"]
    # A baseline swept at its final checkpoint only has no partner for the treated's earlier ones.
    final_only = pd.concat([pooled[pooled.policy_label != "act"], df[df.policy_label == "act"]])
    with pytest.raises(ValueError, match="have no partner"):
        variant_differences(final_only, "act")
