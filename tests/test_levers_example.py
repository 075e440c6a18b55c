"""examples/levers.py, which every published lever and curve comes from: the wall-clock minutes it reads from
training logs (resumed runs, tqdm skipping steps at GPU rates) and its pairing against a published baseline."""

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from lerobot_condground.evaluation.results import TABLE_COLUMNS, write_table

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def levers():
    spec = importlib.util.spec_from_file_location("levers", ROOT / "examples" / "levers.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def flags(success, seed: int) -> dict:
    """Stage and selection columns of a sweep's rows: a success went through every stage; a failure grasped
    the look-alike."""
    success = np.asarray(success, bool)
    return {"pick": success, "lift": success, "place": success, "selected_competitor_object": ~success,
            "placed_in_competitor_receptacle": np.zeros_like(success), "training_seed": seed}  # fmt: skip


def bar(done: int, total: int, seconds: int) -> str:
    """One tqdm line as `condground train` writes it."""
    return f"Training:  {100 * done // total}%| | {done}/{total} [{seconds // 60:02d}:{seconds % 60:02d}<00:10,  1.00step/s]"


def test_minutes_add_up_over_a_resumed_run(levers, tmp_path):
    # 6000 steps, 2 s a step until a kill at step 2500; resumed from the 2000 checkpoint at 1 s a step.
    first = [bar(k, 6000, 2 * k) for k in range(0, 2501)]
    second = [bar(k, 4000, k) for k in range(0, 4001)]
    log = tmp_path / "run.log"
    log.write_text("\r".join(first) + "\n# resumed\n" + "\r".join(second))
    assert levers.elapsed_minutes(log, 1000, 6000) == pytest.approx(2000 / 60)
    # the steps past 2000 of the killed run were lost: they do not count
    assert levers.elapsed_minutes(log, 3000, 6000) == pytest.approx((4000 + 1000) / 60)
    assert levers.elapsed_minutes(log, 6000, 6000) == pytest.approx((4000 + 4000) / 60)


def test_gpu_logs_skip_steps_and_a_step_not_reached_is_refused(levers, tmp_path):
    # At GPU rates tqdm writes every 7th step or so; a run never resumed needs no total.
    log = tmp_path / "run.log"
    log.write_text("\r".join(bar(k, 1500, k // 10) for k in [*range(0, 1200, 7), 1500]))
    assert levers.elapsed_minutes(log, 1000) == pytest.approx((994 // 10) / 60)  # the last line at or before
    assert levers.elapsed_minutes(log, 1500) == pytest.approx(150 / 60)
    cut = tmp_path / "cut.log"
    cut.write_text("\r".join(bar(k, 1500, k) for k in range(0, 800)))  # still training
    with pytest.raises(SystemExit, match="no progress line at step 1000"):
        levers.elapsed_minutes(cut, 1000)


def test_a_lever_is_paired_against_a_published_baseline_without_its_runs(tmp_path):
    """--published_baseline reads the baseline's pooled rollouts from the rollouts table, pairs the lever's sweeps
    against them layout by layout, and leaves the baseline's published rows as they were."""
    task, layouts, rng = "PickPlaceFixedBin-v0", range(1_000_000, 1_000_020), np.random.default_rng(0)
    docs, out = tmp_path / "docs", tmp_path / "out"
    docs.mkdir()
    published = pd.DataFrame(
        [{"lever": "base", "task": task, "seed": seed, "step": step, "layout_seed": layout, "success": int(rng.random() < 0.4)}
         for seed in (0, 1) for step in (4, 5, 6) for layout in layouts]
    )  # fmt: skip
    published.to_csv(docs / "levers_rollouts.csv", index=False)
    lever = {}
    for seed in (0, 1):
        for step in (4, 5, 6):
            success = rng.random(len(layouts)) < 0.8
            lever[(seed, step)] = success
            rows = pd.DataFrame({c: [None] * len(layouts) for c in TABLE_COLUMNS})
            rows = rows.assign(
                condition="clean",
                layout_seed=list(layouts)[::-1],
                success=success[::-1],
                **flags(success[::-1], seed),
            )  # unsorted
            write_table(
                rows, out / "eval" / f"{task}_standard_big_s{seed}" / f"{step:06d}" / "results.parquet"
            )
    command = [
        sys.executable, str(ROOT / "examples" / "levers.py"), f"--task={task}", "--data=unused", "--baseline=base",
        "--published_baseline", "--steps=6", "--every=1", "--seeds=0,1", f"--out={out}", "--lever=big=--policy.dim_model=512",
        f"--csv={docs / 'levers.csv'}", "--stage=analyse",
    ]  # fmt: skip
    subprocess.run(command, check=True, capture_output=True, text=True)
    row = pd.read_csv(docs / "levers.csv").iloc[0]
    assert (row["lever"], row["baseline_arm"], row["n"]) == ("big", "base", 120)
    assert row["baseline"] == pytest.approx(published["success"].mean(), abs=1e-4)
    assert row["treated"] == pytest.approx(np.mean([s.mean() for s in lever.values()]), abs=1e-4)
    rollouts = pd.read_csv(docs / "levers_rollouts.csv")
    kept = rollouts[rollouts["lever"].eq("base")].reset_index(drop=True)
    pd.testing.assert_frame_equal(kept[published.columns], published)  # a `condition` column is added beside
    lever = rollouts[rollouts["lever"].eq("big")]
    assert len(lever) == 120 and lever["condition"].eq("clean").all() and kept["condition"].isna().all()

    wrong = [c.replace("--baseline=base", "--baseline=other") for c in command]
    refused = subprocess.run(wrong, capture_output=True, text=True)
    assert refused.returncode != 0
    assert "has no rollouts of other" in refused.stderr


def test_each_condition_is_paired_on_its_own_and_a_missing_one_is_refused(tmp_path):
    """--conditions=clean,full_mixed: one comparison row per condition, each pairing the lever's rollouts of that
    condition against the baseline's of the same condition and layouts; every rollout keeps its condition; a
    condition the baseline was not scored under is refused by name."""
    task, layouts, rng = "PickPlaceRandomBin-v0", list(range(1_000_000, 1_000_010)), np.random.default_rng(1)
    docs, out = tmp_path / "docs", tmp_path / "out"
    docs.mkdir()
    chance = {"clean": (0.9, 0.8), "full_mixed": (0.2, 0.7)}  # baseline, lever
    published = pd.DataFrame(
        [{"lever": "base", "task": task, "condition": c, "seed": seed, "step": step, "layout_seed": layout,
          "success": int(rng.random() < chance[c][0])}
         for c in chance for seed in (0, 1) for step in (5, 6) for layout in layouts]
    )  # fmt: skip
    published.to_csv(docs / "levers_rollouts.csv", index=False)
    lever = {c: [] for c in chance}
    for seed in (0, 1):
        for step in (5, 6):
            parts = []
            for condition, (_, p) in chance.items():
                success = rng.random(len(layouts)) < p
                lever[condition].append(success)
                parts.append(pd.DataFrame({c: [None] * len(layouts) for c in TABLE_COLUMNS}).assign(
                    condition=condition, layout_seed=layouts[::-1], success=success[::-1],
                    **flags(success[::-1], seed)))  # fmt: skip
            write_table(
                pd.concat(parts, ignore_index=True),
                out / "eval" / f"{task}_standard_aug_s{seed}" / f"{step:06d}" / "results.parquet",
            )
    command = [
        sys.executable, str(ROOT / "examples" / "levers.py"), f"--task={task}", "--data=unused", "--baseline=base",
        "--published_baseline", "--steps=6", "--every=1", "--pool=2", "--seeds=0,1", f"--out={out}",
        "--lever=aug=--policy.variant=augmentation", f"--csv={docs / 'levers.csv'}", "--stage=analyse",
        "--conditions=clean,full_mixed",
    ]  # fmt: skip
    subprocess.run(command, check=True, capture_output=True, text=True)
    rows = pd.read_csv(docs / "levers.csv").set_index("condition")
    assert list(rows.index) == ["clean", "full_mixed"] and (rows["n"] == 40).all()
    for condition in chance:
        base = published[published["condition"].eq(condition)]["success"].mean()
        assert rows.loc[condition, "baseline"] == pytest.approx(base, abs=1e-4)
        assert rows.loc[condition, "treated"] == pytest.approx(np.mean(lever[condition]), abs=1e-4)
        seeds = [np.mean(lever[condition][2 * s : 2 * s + 2]) for s in (0, 1)]
        effects = [float(e) for e in rows.loc[condition, "seed_effects"].split()]
        base_runs = published[published["condition"].eq(condition)].groupby("seed")["success"].mean()
        assert effects == pytest.approx([seeds[s] - base_runs[s] for s in (0, 1)], abs=1e-4)
        assert (
            rows.loc[condition, "cluster_low"]
            < rows.loc[condition, "diff"]
            < rows.loc[condition, "cluster_high"]
        )
    # Holm over the table's two comparisons: the smaller p doubled, the larger kept (or raised to it).
    small, large = sorted(rows["cluster_p"])
    assert sorted(rows["holm_p"]) == pytest.approx(
        [min(2 * small, 1), max(min(2 * small, 1), large)], abs=1e-4
    )
    funnel = pd.read_csv(docs / "levers_funnel.csv").set_index("condition")
    assert list(funnel["lever"]) == ["aug", "aug"] and (funnel["episodes"] == 40).all()
    for condition in chance:
        assert funnel.loc[condition, "p_pick"] == pytest.approx(np.mean(lever[condition]), abs=1e-4)
        assert funnel.loc[condition, "p_grasped_competitor_k"] == 40 - np.sum(lever[condition])
    rollouts = pd.read_csv(docs / "levers_rollouts.csv")
    assert rollouts[rollouts["lever"].eq("aug")].groupby("condition").size().to_dict() == {
        "clean": 40,
        "full_mixed": 40,
    }

    refused = subprocess.run(
        [c.replace("clean,full_mixed", "clean,object_color_3") for c in command],
        capture_output=True,
        text=True,
    )
    assert refused.returncode != 0
    assert "has no rollouts of base" in refused.stderr and "object_color_3" in refused.stderr

    # Scored again under one condition: that condition's rows are replaced, the other's are kept.
    subprocess.run(
        [c.replace("clean,full_mixed", "full_mixed") for c in command], check=True, capture_output=True
    )
    again = pd.read_csv(docs / "levers.csv")
    assert sorted(again["condition"]) == ["clean", "full_mixed"]
    assert pd.read_csv(docs / "levers_rollouts.csv").groupby(["lever", "condition"]).size()[
        "aug"
    ].to_dict() == {"clean": 40, "full_mixed": 40}
