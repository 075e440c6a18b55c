"""`condground compare`: two recipes trained side by side and paired on the same held-out layouts, end to end
at a tiny budget (real training, real sweeps); the pairing against a published baseline and per condition; the
refusals of arms that differ in budget or data and of held-out layouts a recording trained on."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from helpers import run_cli
from lerobot_condground.evaluation.results import TABLE_COLUMNS, read_table, write_table

ROOT = Path(__file__).resolve().parents[2]
TASK = "PickPlaceFixedBin-v0"
TINY = (
    "--policy.dim_model=32 --policy.n_heads=2 --policy.dim_feedforward=64 --policy.n_encoder_layers=1 "
    "--policy.backbone_width=8 --batch_size=2"
)


def flags(success, seed: int) -> dict:
    """Stage and selection columns of a sweep's rows: a success went through every stage; a failure grasped
    the look-alike."""
    success = np.asarray(success, bool)
    return {"pick": success, "lift": success, "place": success, "selected_competitor_object": ~success,
            "placed_in_competitor_receptacle": np.zeros_like(success), "training_seed": seed}  # fmt: skip


@pytest.fixture(scope="module")
def small_recording(tmp_path_factory) -> Path:
    """Two expert episodes of Task 1 (layout seeds 0 and 1) at the CPU configuration's 96x128."""
    root = tmp_path_factory.mktemp("compare") / "data"
    run_cli(
        "condground", "record", f"--env.task={TASK}", "--env.observation_height=96", "--env.observation_width=128",
        "--dataset.repo_id=local/compare", f"--dataset.root={root}", "--dataset.num_episodes=2", "--progress=false",
    )  # fmt: skip
    return root


def compare(data: Path, out: Path, *flags: str, check: bool = True):
    return run_cli(
        "condground", "compare", f"--env.task={TASK}", "--env.episode_length=10", f"--dataset.root={data}",
        "--baseline.name=small", "--treated.name=wide", "--treated.flags=--policy.dim_feedforward=128",
        f"--train.flags={TINY}", "--train.seeds=0,1", "--train.steps=2", "--train.save_freq=1", "--eval.pool=1",
        "--eval.episodes=2", f"--output_dir={out}", "--progress=false", *flags, check=check,
    )  # fmt: skip


def test_two_recipes_are_trained_scored_paired_published_and_reported(small_recording, tmp_path):
    out, table = tmp_path / "out", tmp_path / "docs" / "levers.csv"
    compare(small_recording, out, f"--table={table}")
    folder = out / "comparisons" / f"{TASK}_wide_vs_small"
    manifest = json.loads((folder / "compare.json").read_text())
    assert manifest["kind"] == "compare" and manifest["differences"] == []
    assert manifest["arms"]["wide"]["flags"] == ["--policy.dim_feedforward=128"]
    rollouts = pd.read_parquet(folder / "rollouts.parquet")
    # 2 arms x 2 runs x 1 checkpoint x 2 held-out layouts, each with its stages, from the real sweeps
    assert len(rollouts) == 8 and set(rollouts["layout_seed"]) == {1_000_000, 1_000_001}
    assert {"arm", "run", "seed", "step", "pick", "selected_competitor_object"} <= set(rollouts.columns)
    for arm in ("small", "wide"):
        for seed in (0, 1):
            swept = read_table(out / "eval" / f"{TASK}_standard_{arm}_s{seed}" / "000002" / "results.parquet")
            mine = rollouts[rollouts["arm"].eq(arm) & rollouts["seed"].eq(seed)].sort_values("layout_seed")
            assert mine["success"].tolist() == swept.sort_values("layout_seed")["success"].tolist()
    row = pd.read_csv(folder / "summary.csv").iloc[0]
    assert (row["lever"], row["baseline_arm"], row["seeds"], row["n"]) == ("wide", "small", 2, 4)
    assert row["treated"] - row["baseline"] == pytest.approx(row["diff"])
    assert (folder / "compare.png").read_bytes()[:4] == b"\x89PNG"
    published = pd.read_csv(table)
    assert published["lever"].tolist() == ["wide"] and "holm_p" in published and "cluster_p" in published
    assert pd.read_csv(table.with_name("levers_rollouts.csv")).groupby("lever").size().to_dict() == {
        "small": 4,
        "wide": 4,
    }

    # A rerun trains and sweeps nothing again: it re-analyses what is there.
    logs = {p: p.stat().st_size for p in (out / "train").glob("*.log")}
    results = {p: p.stat().st_mtime_ns for p in (out / "eval").rglob("results.parquet")}
    compare(small_recording, out)
    assert {p: p.stat().st_size for p in logs} == logs and len(logs) == 4
    assert {p: p.stat().st_mtime_ns for p in results} == results and len(results) == 4

    # The same arm as finished runs: read from their configs (same budget and data), paired the same way.
    runs = ",".join(str(out / "train" / f"{TASK}_standard_wide_s{seed}") for seed in (0, 1))
    compare(small_recording, out, "--treated.flags=", f"--treated.runs={runs}")
    again = json.loads((folder / "compare.json").read_text())
    assert again["arms"]["wide"]["source"] == "runs" and again["differences"] == []
    # its recipe read back from the runs' configs: the flags over the CPU configuration that trained them
    recipe = again["arms"]["wide"]["flags"]
    assert recipe[0] == "--policy.variant=standard" and "--policy.dim_feedforward=128" in recipe
    assert "--policy.dim_model=32" in recipe and not any("device" in f or "use_amp" in f for f in recipe)
    pd.testing.assert_frame_equal(pd.read_csv(folder / "summary.csv").drop(columns="flags"),
                                  pd.DataFrame([row]).drop(columns="flags"), check_dtype=False)  # fmt: skip

    report = tmp_path / "report" / "report.html"
    run_cli("condground", "report", f"--input_dir={folder}", f"--output={report}")
    text = report.with_suffix(".md").read_text()
    assert "Comparisons of training recipes" in text and "wide vs small" in text


def test_arms_that_differ_in_budget_or_data_are_refused_unless_allowed(small_recording, tmp_path):
    out = tmp_path / "out"
    refused = compare(small_recording, out, "--treated.flags=--steps=4", check=False)
    assert refused.returncode == 2
    assert "small and wide differ in budget or data (steps: 2 -> 4)" in refused.stderr
    assert "--allow_differences=true" in refused.stderr and not out.exists()
    other = compare(small_recording, out, f"--treated.flags=--dataset.root={tmp_path}", check=False)
    assert f"dataset.root: {small_recording.resolve()} -> {tmp_path.resolve()}" in other.stderr
    assert not out.exists()


def test_a_recording_inside_the_working_directory_is_named_relative_to_it(tmp_path, monkeypatch):
    """Differences go into published tables: they must not name this machine's folders."""
    from lerobot_condground.experiments.compare import Arm, differences

    monkeypatch.chdir(tmp_path)

    def arm(root: Path) -> Arm:
        return Arm("a", "flags", [], [], {"dataset.root": str(root)}, [2])

    found = differences(arm(Path("data/clean")), arm(tmp_path / "data" / "clutter"))
    assert found == ["dataset.root: data/clean -> data/clutter"]


def test_held_out_layouts_a_recording_trained_on_are_refused(small_recording, tmp_path):
    refused = compare(small_recording, tmp_path / "out", "--eval.seed_offset=1", check=False)
    assert refused.returncode == 2
    assert "trained on 1 of the held-out layouts (seeds 1)" in refused.stderr
    assert not (tmp_path / "out").exists()


def test_a_lever_is_paired_against_a_published_baseline_without_its_runs(tmp_path):
    """docs/learning-curve/levers.py --published_baseline (`--baseline.rollouts`) reads the baseline's pooled
    rollouts from the rollouts table, pairs the lever's sweeps
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
        sys.executable, str(ROOT / "docs" / "learning-curve" / "levers.py"), f"--task={task}", "--data=unused", "--baseline=base",
        "--published_baseline", "--steps=6", "--every=1", "--seeds=0,1", "--episodes=20", f"--out={out}", "--lever=big=--policy.dim_model=512",
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
        str(Path(sys.executable).parent / "condground"), "compare", f"--env.task={task}", "--baseline.name=base",
        f"--baseline.rollouts={docs / 'levers_rollouts.csv'}", "--treated.name=aug",
        "--treated.flags=--policy.variant=augmentation", "--train.steps=6", "--train.save_freq=1", "--eval.pool=2",
        "--eval.episodes=10", f"--output_dir={out}", f"--table={docs / 'levers.csv'}", "--stage=analyse",
        "--eval.conditions=clean,full_mixed",
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
    assert "has 0 rollouts of base" in refused.stderr and "object_color_3" in refused.stderr

    # Scored again under one condition: that condition's rows are replaced, the other's are kept.
    subprocess.run(
        [c.replace("clean,full_mixed", "full_mixed") for c in command], check=True, capture_output=True
    )
    again = pd.read_csv(docs / "levers.csv")
    assert sorted(again["condition"]) == ["clean", "full_mixed"]
    assert pd.read_csv(docs / "levers_rollouts.csv").groupby(["lever", "condition"]).size()[
        "aug"
    ].to_dict() == {"clean": 40, "full_mixed": 40}


def fake_run(folder: Path, config: str) -> Path:
    """A training run folder whose last checkpoint's train_config.json holds `config` (untrusted text)."""
    path = folder / "checkpoints" / "last" / "pretrained_model" / "train_config.json"
    path.parent.mkdir(parents=True)
    path.write_text(config)
    return folder


@pytest.mark.parametrize(
    "setup, flags, named",
    [
        (lambda d: (d / "mine.csv").write_text("name,score\nann,3\n"), ["--table={d}/mine.csv"],
         "mine.csv exists and is not a lever table"),
        (lambda d: None, ["--table={d}/levers.txt"], "levers.txt is not allowed; allowed: a .csv file"),
        (lambda d: pd.DataFrame({"lever": ["base"], "task": [TASK], "seed": [0], "step": [6], "layout_seed": [1_000_000],
                                 "success": ["yes"]}).to_csv(d / "r.csv", index=False),
         ["--baseline.rollouts={d}/r.csv"], "success='yes' in row 2; allowed: 0 or 1"),
        (lambda d: None, ["--treated.flags=", "--treated.runs={d}/a,{d}/b"], "train_config.json: not a finished"),
        (lambda d: [fake_run(d / n, "{not json") for n in "ab"], ["--treated.flags=", "--treated.runs={d}/a,{d}/b"],
         "train_config.json"),
        (lambda d: [fake_run(d / n, '{"steps": "6000", "save_freq": 2000}') for n in "ab"],
         ["--treated.flags=", "--treated.runs={d}/a,{d}/b"], "steps '6000' and save_freq 2000 are not step counts"),
        (lambda d: [fake_run(d / n, '{"steps": 6, "save_freq": 2}') for n in "a"],
         ["--treated.flags=", "--treated.runs={d}/a,{d}/a"], "is given twice"),
        (lambda d: [fake_run(d / n, json.dumps({"steps": 6, "save_freq": 2, "policy": {"type": "act_modified", "variant": v}}))
                    for n, v in (("a", "standard"), ("b", "full"))],
         ["--treated.flags=", "--treated.runs={d}/a,{d}/b"], "the runs differ in their policy settings"),
        (lambda d: [fake_run(d / n, '{"steps": 6, "save_freq": 2, "policy": [1]}') for n in "ab"],
         ["--treated.flags=", "--treated.runs={d}/a,{d}/b"], "its policy is list, not an object of settings"),
        (lambda d: [fake_run(d / n, json.dumps({"steps": 6, "save_freq": 2, "policy": {"type": "act_modified", "variant": "x"}}))
                    for n in "ab"],
         ["--treated.flags=", "--treated.runs={d}/a,{d}/b"], "Unknown act_modified variant 'x'; allowed:"),
    ],
)  # fmt: skip
def test_hostile_tables_and_runs_are_one_line_before_any_work(
    setup, flags, named, tmp_path, monkeypatch, capsys
):
    """A user's file as --table, a rollouts table with garbage, runs that are not runs or a run given twice:
    one line naming the value, exit code 2, the user's files untouched, nothing written."""
    from lerobot_condground.cli import main

    monkeypatch.chdir(tmp_path)
    setup(tmp_path)
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    args = ["compare", f"--env.task={TASK}", "--baseline.name=base", "--treated.name=big", "--train.steps=6",
            "--train.save_freq=1", "--eval.episodes=2", "--stage=analyse", "--output_dir=out",
            *(f.format(d=tmp_path) for f in flags)]  # fmt: skip
    assert main(args) == 2
    err = [line for line in capsys.readouterr().err.strip().splitlines() if "third-party plugin" not in line]
    assert len(err) == 1 and err[0].startswith("condground compare:") and named in err[0], err
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before
    assert not (tmp_path / "out").exists()
