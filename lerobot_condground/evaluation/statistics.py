"""Rates, intervals and paired differences over per-episode results tables.

Every rate carries its own numerator and denominator: the conditional stage probabilities are taken
over the episodes that reached the previous stage, so their `n` is smaller than the cell's episode
count. Intervals are Wilson score intervals (statsmodels). Differences are paired: the same layout
seed is evaluated under every condition and by every checkpoint, so two outcomes of one layout are
not independent, and an interval for independent samples would be too wide or too narrow.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import pandas as pd
from scipy import stats
from statsmodels.stats.contingency_tables import mcnemar
from statsmodels.stats.multitest import multipletests
from statsmodels.stats.proportion import proportion_confint

from lerobot_condground.core.routing import ROUTING_SUBGOALS, SUBGOALS

ALPHA = 0.05

# metric -> (numerator column, denominator column or None for every episode). The stage flags are
# latched (lift implies pick), but the denominators still name every earlier stage so that a table
# with an inconsistent row cannot inflate a conditional rate.
METRICS: dict[str, tuple[str, tuple[str, ...]]] = {
    "success": ("success", ()),
    "p_pick": ("pick", ()),
    "p_lift_given_pick": ("lift", ("pick",)),
    "p_place_given_pick_lift": ("place", ("pick", "lift")),
    "p_grasped_competitor": ("selected_competitor_object", ()),
    "p_placed_in_competitor_receptacle": ("placed_in_competitor_receptacle", ()),
}
METRIC_TITLES = {
    "success": "success",
    "p_pick": "P(pick)",
    "p_lift_given_pick": "P(lift|pick)",
    "p_place_given_pick_lift": "P(place|pick,lift)",
    "p_grasped_competitor": "competitor grasped",
    "p_placed_in_competitor_receptacle": "placed in competitor receptacle",
}
# Metrics whose denominator is every episode: only these pair episode by episode.
PAIRABLE = {m: col for m, (col, given) in METRICS.items() if not given}
CELL = ("policy_label", "task", "condition")
# layout_seed is implied by (eval_seed, episode) within one sweep; keying on it as well turns rows of sweeps
# run with different seed offsets into unmatched rows (refused) instead of pairs of different layouts.
CONDITION_PAIRING = ("checkpoint_hash", "eval_seed", "episode", "layout_seed", "prompt")
VARIANT_PAIRING = (
    "task",
    "condition",
    "training_seed_index",
    "checkpoint_index",
    "eval_seed",
    "episode",
    "layout_seed",
    "prompt",
)


def wilson_interval(k, n, alpha: float = ALPHA) -> tuple[np.ndarray, np.ndarray]:
    """Wilson score bounds for arrays of counts; NaN where n = 0 (no episodes, no interval)."""
    k = np.atleast_1d(np.asarray(k, dtype=float))
    n = np.atleast_1d(np.asarray(n, dtype=float))
    low = np.full(k.shape, np.nan)
    high = np.full(k.shape, np.nan)
    has = n > 0
    if has.any():
        low[has], high[has] = proportion_confint(k[has], n[has], alpha=alpha, method="wilson")
    return low, high


def rate(k: int, n: int, alpha: float = ALPHA) -> dict:
    """{k, n, rate, low, high} of one proportion, plain floats (JSON-ready); NaN rate and bounds when n = 0."""
    low, high = wilson_interval(k, n, alpha)
    return {
        "k": int(k),
        "n": int(n),
        "rate": k / n if n else float("nan"),
        "low": float(low[0]),
        "high": float(high[0]),
    }


# InstrumentRouting-v0's subgoals pooled: the two whose destination depends on the instrument's state, and all.
SUBGOAL_POOLS = {"routing": ROUTING_SUBGOALS, "overall": SUBGOALS}
SUBGOAL_TITLES = {
    **{s: f"{s} (routing)" if s in ROUTING_SUBGOALS else s for s in SUBGOALS},
    "routing": f"routing: {' + '.join(ROUTING_SUBGOALS)}",
    "overall": "overall",
}


def subgoal_rates(df: pd.DataFrame, by: Sequence[str] = ("condition",)) -> list[dict]:
    """Success per InstrumentRouting-v0 subgoal and group of `by`, then per pool of SUBGOAL_POOLS: one dict
    {**group, subgoal, k, n, rate, low, high} per cell, groups in order of appearance. A subgoal a group did
    not run has no cell; a pool holds the subgoals of it that were run."""
    cells = []
    for key, group in df.groupby(list(by), sort=False, dropna=False):
        names = dict(zip(by, key if isinstance(key, tuple) else (key,)))
        for name in (*SUBGOALS, *SUBGOAL_POOLS):
            rows = group[group["subgoal"].isin(SUBGOAL_POOLS.get(name, (name,)))]
            if len(rows):
                cells.append(
                    {**names, "subgoal": name, **rate(int(_flags(rows, "success").sum()), len(rows))}
                )
    return cells


def _flags(df: pd.DataFrame, column: str) -> np.ndarray:
    values = df[column]
    if values.isna().any():
        raise ValueError(
            f"Column {column!r} holds missing values; stage and selection flags must be true or false"
        )
    return values.to_numpy().astype(bool)


def counts(df: pd.DataFrame, metric: str) -> tuple[int, int]:
    """(k, n) of one metric of METRICS over the rows of df."""
    numerator, given = METRICS[metric]
    mask = np.ones(len(df), dtype=bool)
    for column in given:
        mask &= _flags(df, column)
    return int((_flags(df, numerator) & mask).sum()), int(mask.sum())


def stage_funnel(df: pd.DataFrame, by: Sequence[str] = CELL) -> pd.DataFrame:
    """Per cell, the episodes that got at least as far as each stage, over all episodes: picked, picked and
    lifted, and placed after both (columns `stage`, `k`, `n`, `rate`, `low`, `high`)."""
    rows = []
    for key, cell in df.groupby(list(by), sort=True, dropna=False):
        reached = np.ones(len(cell), bool)
        for stage, column in (("picked", "pick"), ("lifted", "lift"), ("placed", "place")):
            reached = reached & cell[column].fillna(False).astype(bool).to_numpy()
            rows.append(
                {**dict(zip(by, key, strict=True)), "stage": stage, "k": int(reached.sum()), "n": len(cell)}
            )
    out = pd.DataFrame(rows, columns=[*by, "stage", "k", "n"])
    out["rate"] = out["k"] / out["n"].clip(lower=1)
    out["low"], out["high"] = wilson_interval(out["k"], out["n"])
    return out


def cell_metrics(df: pd.DataFrame, by: Sequence[str] = CELL) -> pd.DataFrame:
    """One row per cell: `<m>_k`, `<m>_n`, `<m>`, `<m>_low`, `<m>_high` for every metric in METRICS,
    `episodes`, and the spread of success across training seeds (`success_seed_mean/std/min/max`,
    `training_seeds`). The seed spread is of per-checkpoint success rates; its std is NaN with one seed."""
    by = list(by)
    rows = []
    for key, cell in df.groupby(by, sort=True, dropna=False):
        key = key if isinstance(key, tuple) else (key,)
        row: dict = dict(zip(by, key))
        row["episodes"] = len(cell)
        for metric in METRICS:
            k, n = counts(cell, metric)
            row[f"{metric}_k"], row[f"{metric}_n"] = k, n
        per_seed = cell.groupby("training_seed")["success"].apply(lambda s: s.astype(bool).mean())
        row["training_seeds"] = len(per_seed)
        row["success_seed_mean"] = per_seed.mean()
        row["success_seed_std"] = per_seed.std(ddof=1) if len(per_seed) > 1 else np.nan
        row["success_seed_min"] = per_seed.min()
        row["success_seed_max"] = per_seed.max()
        rows.append(row)
    out = pd.DataFrame(rows)
    if out.empty:
        return pd.DataFrame(columns=by + ["episodes"])
    for metric in METRICS:
        k, n = out[f"{metric}_k"].to_numpy(), out[f"{metric}_n"].to_numpy()
        with np.errstate(invalid="ignore", divide="ignore"):
            out[metric] = np.where(n > 0, k / np.maximum(n, 1), np.nan)
        out[f"{metric}_low"], out[f"{metric}_high"] = wilson_interval(k, n)
    return out


def paired_difference(a, b, alpha: float = ALPHA) -> dict:
    """rate(b) − rate(a) over matched episodes (a[i] and b[i] share a layout), with Newcombe's
    hybrid score interval for paired proportions and McNemar's exact p-value.

    Pass the reference first: `paired_difference(clean, condition)` gives condition − clean.
    Returns n, `b_only` / `a_only` (the discordant counts), `k_a`, `k_b`, `rate_a`, `rate_b`,
    `diff`, `low`, `high`, `p_value`; rates and bounds are NaN when n = 0."""
    a = np.asarray(a).astype(bool).ravel()
    b = np.asarray(b).astype(bool).ravel()
    if a.shape != b.shape:
        raise ValueError(f"Paired outcomes need equal lengths; got {a.size} and {b.size}")
    n = int(a.size)
    both, b_only, a_only = int((a & b).sum()), int((b & ~a).sum()), int((a & ~b).sum())
    neither = n - both - b_only - a_only
    out = {"n": n, "b_only": b_only, "a_only": a_only, "k_a": int(a.sum()), "k_b": int(b.sum())}
    if n == 0:
        return {**out, **dict.fromkeys(("rate_a", "rate_b", "diff", "low", "high", "p_value"), float("nan"))}
    p_b, p_a = out["k_b"] / n, out["k_a"] / n
    lows, highs = wilson_interval([out["k_b"], out["k_a"]], [n, n], alpha)
    (l_b, l_a), (u_b, u_a) = lows.tolist(), highs.tolist()
    # Newcombe (1998), "Improved confidence intervals for the difference between binomial proportions
    # based on paired data", Stat Med 17:2635-2650, method 10: square-and-add the Wilson distances
    # of the two marginal rates, less their covariance through the phi coefficient of the 2x2 table.
    # As in that paper, a positive ad - bc is shrunk by n/2 (and set to 0 if it does not exceed n/2),
    # which keeps the interval from being too narrow when the outcomes agree by chance.
    margins = (both + b_only) * (a_only + neither) * (both + a_only) * (b_only + neither)
    ad_bc = both * neither - b_only * a_only
    if margins == 0:
        phi = 0.0
    elif ad_bc > n / 2:
        phi = (ad_bc - n / 2) / math.sqrt(margins)
    elif ad_bc >= 0:
        phi = 0.0
    else:
        phi = ad_bc / math.sqrt(margins)
    diff = p_b - p_a
    d_low = math.sqrt(max((p_b - l_b) ** 2 - 2 * phi * (p_b - l_b) * (u_a - p_a) + (u_a - p_a) ** 2, 0.0))
    d_high = math.sqrt(max((u_b - p_b) ** 2 - 2 * phi * (u_b - p_b) * (p_a - l_a) + (p_a - l_a) ** 2, 0.0))
    # Exact McNemar: a binomial test on the discordant pairs; p = 1 when there are none.
    p_value = float(mcnemar([[both, b_only], [a_only, neither]], exact=True).pvalue)
    return {
        **out,
        "rate_a": p_a,
        "rate_b": p_b,
        "diff": diff,
        "low": max(diff - d_low, -1.0),
        "high": min(diff + d_high, 1.0),
        "p_value": p_value,
    }


def layout_means(rollouts: pd.DataFrame) -> pd.DataFrame:
    """Success of each training run on each layout, its checkpoints averaged: runs × layouts.
    `rollouts` has the columns `run`, `layout` and `success` (one row per rollout)."""
    missing = {"run", "layout", "success"} - set(rollouts.columns)
    if missing:
        raise ValueError(f"rollouts need the columns run, layout, success; missing {sorted(missing)}")
    table = rollouts.pivot_table(index="run", columns="layout", values="success", aggfunc="mean")
    holes = table.isna()
    if holes.to_numpy().any():
        run, layout = holes.stack()[lambda h: h].index[0]
        raise ValueError(f"run {run} has no rollout on layout {layout}; every run must cover every layout")
    return table.astype(float)


def clustered_difference(a: pd.DataFrame, b: pd.DataFrame, alpha: float = ALPHA) -> dict:
    """rate(b) − rate(a) for two arms of several training runs each, scored on the same layouts.

    The layout is the unit of pairing and the training run the unit of replication: the pooled rollouts
    of one layout are not independent (the same layout, seen by every checkpoint of every run), and a
    claim about an arm is a claim about a new training run, so the interval adds the spread of the arms'
    runs to the spread over layouts: var = var(d_l)/L + s²(1/R_a + 1/R_b), where d_l is the layout's
    difference of run-averaged success and s² the pooled variance of the arms' run rates (on common
    layouts, so layout difficulty cancels from it). The interval and p use Student's t with Welch–Satterthwaite
    degrees of freedom: with two runs an arm the training variance rests on two runs each, and the
    interval says so by its width. Both arms' runs must cover the same layouts. The simulation that
    chose this method over bootstraps and Newcombe/McNemar: `lerobot_condground/evaluation/coverage.py`.

    Returns layouts, runs_a, runs_b, rate_a, rate_b, diff, low, high, p_value, df, and seed_effects
    (run i of b less run i of a, runs in sorted order, as many as the smaller arm has)."""
    ma, mb = layout_means(a), layout_means(b)
    if set(ma.columns) != set(mb.columns):
        only = sorted(set(ma.columns) ^ set(mb.columns))
        raise ValueError(f"the arms were scored on different layouts (in one arm only: {only[:5]})")
    d = mb[ma.columns].mean(axis=0).to_numpy() - ma.mean(axis=0).to_numpy()
    layout_var = float(d.var(ddof=1)) if d.size > 1 else float("nan")
    return run_layout_interval(
        ma.mean(axis=1).to_numpy(), mb.mean(axis=1).to_numpy(), layout_var, d.size, alpha
    )


def run_layout_interval(run_a, run_b, layout_var: float, layouts: int, alpha: float = ALPHA) -> dict:
    """`clustered_difference` from its parts: each run's rate over the common layouts (arm a, arm b, runs
    in order) and the variance over layouts of the layout-wise difference (or a bound on it, where only
    checkpoint rates survive)."""
    run_a, run_b = np.asarray(run_a, dtype=float), np.asarray(run_b, dtype=float)
    ra, rb = run_a.size, run_b.size
    diff = float(run_b.mean() - run_a.mean())
    out = {
        "layouts": layouts, "runs_a": ra, "runs_b": rb, "rate_a": float(run_a.mean()), "rate_b": float(run_b.mean()),
        "diff": diff, "seed_effects": (run_b[: min(ra, rb)] - run_a[: min(ra, rb)]).tolist(),
    }  # fmt: skip
    if min(ra, rb) < 2 or layouts < 2:
        # One run cannot show how much training runs differ: no interval is honest then.
        return {**out, **dict.fromkeys(("low", "high", "p_value", "df"), float("nan"))}
    # One run variance for both arms, pooled: two runs an arm leave each arm's own variance 1 degree of
    # freedom, and the arms of a lever share the recipe that makes runs differ (seeded init and batches).
    pooled = ((ra - 1) * run_a.var(ddof=1) + (rb - 1) * run_b.var(ddof=1)) / (ra + rb - 2)
    parts = np.array([layout_var / layouts, pooled * (1 / ra + 1 / rb)])
    dofs = np.array([layouts - 1, ra + rb - 2])
    var = parts.sum()
    if var == 0:
        # Every run of each arm agrees on every layout: the difference is what it is.
        return {**out, "low": diff, "high": diff, "p_value": float(diff == 0), "df": float("inf")}
    df = float(var**2 / np.sum(parts**2 / dofs))
    half = stats.t.ppf(1 - alpha / 2, df) * math.sqrt(var)
    p_value = float(2 * stats.t.sf(abs(diff) / math.sqrt(var), df))
    return {**out, "low": max(diff - half, -1.0), "high": min(diff + half, 1.0), "p_value": p_value, "df": df}


def holm(p_values) -> np.ndarray:
    """Holm's step-down adjustment of a family of p-values (statsmodels); NaN stays NaN."""
    p = np.asarray(p_values, dtype=float)
    out = np.full(p.shape, np.nan)
    has = ~np.isnan(p)
    if has.any():
        out[has] = multipletests(p[has], method="holm")[1]
    return out


def _pairable_column(metric: str) -> str:
    if metric in PAIRABLE:
        return PAIRABLE[metric]
    if metric in PAIRABLE.values():
        return metric
    raise ValueError(
        f"Metric {metric!r} cannot be paired episode by episode; allowed: {', '.join(PAIRABLE)} "
        f"(conditional probabilities have different denominators in the two arms)"
    )


def _pair(reference: pd.DataFrame, other: pd.DataFrame, keys: Sequence[str], column: str, cell: str) -> dict:
    keys = list(keys)
    for side, frame in (("reference", reference), ("compared", other)):
        dup = frame.duplicated(keys, keep=False)
        if dup.any():
            first = frame.loc[dup, keys].iloc[0].to_dict()
            raise ValueError(
                f"{cell}: the {side} rows repeat the pairing key {first} ({int(dup.sum())} rows share keys)"
            )
    merged = reference[keys + [column]].merge(
        other[keys + [column]], on=keys, how="outer", suffixes=("_a", "_b"), indicator=True
    )
    unmatched = merged[merged["_merge"] != "both"]
    if len(unmatched):
        side = unmatched["_merge"].map({"left_only": "reference only", "right_only": "compared only"})
        example = unmatched[keys].iloc[0].to_dict()
        raise ValueError(
            f"{cell}: {len(unmatched)} episodes have no partner on {keys} "
            f"({side.value_counts().to_dict()}; e.g. {example})"
        )
    return paired_difference(merged[f"{column}_a"].to_numpy(), merged[f"{column}_b"].to_numpy())


def condition_differences(
    df: pd.DataFrame, metric: str = "success", reference: str = "clean"
) -> pd.DataFrame:
    """condition − reference for each policy_label/task/condition, pairing each episode with the
    reference episode of the same checkpoint, eval seed, episode index, layout seed and prompt. A policy/task without reference rows has nothing to pair and yields no rows; a cell whose
    keys do not match the reference one to one raises ValueError naming the cell."""
    column = _pairable_column(metric)
    rows = []
    for (label, task), group in df.groupby(["policy_label", "task"], sort=True):
        ref = group[group["condition"] == reference]
        if ref.empty:
            continue
        for condition, cell in group[group["condition"] != reference].groupby("condition", sort=False):
            name = f"{label} / {task} / {condition} vs {reference}"
            d = _pair(ref, cell, CONDITION_PAIRING, column, name)
            rows.append(
                {
                    "policy_label": label,
                    "task": task,
                    "condition": condition,
                    "reference": reference,
                    "metric": metric,
                    **_rename(d, "reference", "condition"),
                }
            )
    return pd.DataFrame(rows)


def variant_differences(df: pd.DataFrame, baseline_label: str, metric: str = "success") -> pd.DataFrame:
    """policy − baseline for each other policy_label/task/condition, pairing episodes on task,
    condition, training-seed index (the k-th smallest training seed of each policy: two variants
    trained with seeds 0,1,2 and 1000,1001,1002 still pair), checkpoint index within that run (the k-th
    checkpoint by path, so the pooled late checkpoints of two runs pair step by step), eval seed, episode
    index, layout seed and prompt: the checkpoints differ, the layout and the indices are shared. Cells the
    baseline did not run are skipped; cells with keys that do not match one to one raise ValueError naming
    the cell. Beside Newcombe's interval (every pair independent), `cluster_low`, `cluster_high` and
    `cluster_p` are `clustered_difference`'s: the layout pairs, the training run replicates (NaN with one
    run an arm)."""
    column = _pairable_column(metric)
    if baseline_label not in set(df["policy_label"]):
        raise ValueError(
            f"Baseline {baseline_label!r} is not among the policy labels {sorted(set(df['policy_label']))}"
        )
    run = ["policy_label", "task", "training_seed"]
    df = df.assign(
        training_seed_index=df.groupby(["policy_label", "task"])["training_seed"]
        .rank(method="dense")
        .astype(int)
        - 1,
        checkpoint_index=df.assign(_ck=df["checkpoint"].fillna("").astype(str))
        .groupby(run)["_ck"]
        .rank(method="dense")
        .astype(int)
        - 1,
    )
    base = df[df["policy_label"] == baseline_label]
    rows = []
    for (label, task, condition), cell in df[df["policy_label"] != baseline_label].groupby(
        list(CELL), sort=True
    ):
        ref = base[(base["task"] == task) & (base["condition"] == condition)]
        if ref.empty:
            continue
        name = f"{label} vs {baseline_label} / {task} / {condition}"
        d = _pair(ref, cell, VARIANT_PAIRING, column, name)
        c = clustered_difference(_runs_by_layout(ref, column), _runs_by_layout(cell, column))
        rows.append(
            {
                "policy_label": label,
                "baseline": baseline_label,
                "task": task,
                "condition": condition,
                "metric": metric,
                **_rename(d, "baseline", "policy"),
                "runs": min(c["runs_a"], c["runs_b"]),
                "cluster_low": c["low"],
                "cluster_high": c["high"],
                "cluster_p": c["p_value"],
            }
        )
    return pd.DataFrame(rows)


def _runs_by_layout(cell: pd.DataFrame, column: str) -> pd.DataFrame:
    """One arm's paired rows as `layout_means`' input: the run is the training-seed index, the layout the
    episode's pairing key without it."""
    layout = cell[["eval_seed", "episode", "layout_seed", "prompt"]].astype(str).agg("/".join, axis=1)
    return pd.DataFrame(
        {"run": cell["training_seed_index"], "layout": layout, "success": cell[column].astype(float)}
    )


def _rename(d: dict, a: str, b: str) -> dict:
    """paired_difference's a/b keys under the names of the two arms."""
    names = {
        "k_a": f"k_{a}",
        "k_b": f"k_{b}",
        "rate_a": f"rate_{a}",
        "rate_b": f"rate_{b}",
        "a_only": f"{a}_only",
        "b_only": f"{b}_only",
    }
    return {names.get(k, k): v for k, v in d.items()}
