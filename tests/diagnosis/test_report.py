"""`condground report` on fake sweep, diagnose, probe and attention outputs written in the documented format,
checked in a real headless Chromium."""

import hashlib
import io
import json
import re
import shutil
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from lerobot_condground.core.conditions import NAMED_CONDITIONS
from lerobot_condground.diagnosis.report import ReportConfig, build_report, parse_report_args
from lerobot_condground.evaluation.results import COLUMNS, METADATA_KEY, write_table
from lerobot_condground.evaluation.statistics import paired_difference, rate, variant_differences

TASKS = ("PickPlaceFixedBin-v0", "PickPlaceRandomBin-v0")
CONDITIONS = ["clean", "object_color_3", "receptacle_shape_2", "full_mixed"]
LABELS = {"act": ("act", "", 0.35), "act_modified/full": ("act_modified", "full", 0.85)}
EPISODES = 5
CHROMIUM, CHROMEDRIVER = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")


def png_bytes(color: str = "tab:blue") -> bytes:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(2, 1.5))
    FigureCanvasAgg(fig)
    fig.subplots().scatter([0, 1, 2], [1, 0, 2], color=color)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=40)
    return buf.getvalue()


def checkpoint(label: str, seed: int, task: str) -> dict:
    policy_type, variant, _ = LABELS[label]
    digest = hashlib.sha256(f"{label}/{seed}/{task}".encode()).hexdigest()[:16]
    return {
        "path": f"outputs/train/{label.replace('/', '_')}_{seed}/pretrained_model",
        "hash": digest,
        "label": label,
        "policy_type": policy_type,
        "variant": variant,
        "training_seed": seed,
    }


def sweep_manifest(
    task: str, conditions=CONDITIONS, seed_offset: int = 0, counterbalanced=False, competitor_pool=None
) -> dict:
    grid = {
        "task": task,
        "conditions": list(conditions),
        "condition_specs": {c: asdict(NAMED_CONDITIONS[c]) for c in conditions},
        "counterbalanced": counterbalanced,
        "eval_seeds": 1,
        "n_episodes": EPISODES,
        "batch_size": 5,
        "seed_offset": seed_offset,
        "episode_length": 400,
        "fps": 20,
        "observation_height": 240,
        "observation_width": 320,
    }
    if competitor_pool:
        grid["competitor_pool"] = competitor_pool
    return {
        "kind": "sweep",
        "grid": grid,
        "checkpoints": [checkpoint(label, seed, task) for label in LABELS for seed in (0, 1)],
        "versions": {
            "python": "3.12.3",
            "lerobot": "0.6.1",
            "torch": "2.7.1",
            "mujoco": "3.3.3",
            "lerobot_policy_condground": "0.1.0",
        },
        "command": [
            "condground",
            "sweep",
            f"--env.task={task}",
            "--policy.paths=[a,b]",
            "--output_dir=out dir",
        ],
    }


def sweep_rows(manifest: dict, rng) -> pd.DataFrame:
    grid, rows = manifest["grid"], []
    for ck in manifest["checkpoints"]:
        skill = LABELS[ck["label"]][2]
        for condition in grid["conditions"]:
            for episode in range(grid["n_episodes"]):
                p = 0.95 if condition == "clean" else skill
                stage = 3 if rng.random() < p else int(rng.integers(0, 3))
                wrong = stage < 3 and condition != "clean" and rng.random() < 0.5
                rows.append(
                    {
                        "policy_label": ck["label"],
                        "policy_type": ck["policy_type"],
                        "variant": ck["variant"],
                        "checkpoint": ck["path"],
                        "checkpoint_hash": ck["hash"],
                        "training_seed": ck["training_seed"],
                        "task": grid["task"],
                        "condition": condition,
                        "condition_spec": json.dumps(grid["condition_specs"][condition]),
                        "counterbalanced": grid["counterbalanced"],
                        "eval_seed": 0,
                        "episode": episode,
                        "layout_seed": grid["seed_offset"] + episode,
                        "prompt": "target",
                        "stage": stage,
                        "success": stage >= 3,
                        "pick": stage >= 1,
                        "lift": stage >= 2,
                        "place": stage >= 3,
                        "grasped_first": 2 if wrong else int(stage > 0),
                        "grasped_first_match": "color" if wrong else ("target" if stage else "none"),
                        "grasped_competitor": 2 if wrong else 0,
                        "grasped_competitor_match": "color" if wrong else "none",
                        "selected_competitor_object": wrong,
                        "target_location": "target_receptacle" if stage >= 3 else "elsewhere",
                        "competitor_location": "elsewhere" if wrong else "none",
                        "placed_in_competitor_receptacle": False,
                        "target_x": 0.1,
                        "target_y": 0.0,
                        "target_z": 0.05,
                        "competitor_x": 0.2 if wrong else np.nan,
                        "competitor_y": 0.1 if wrong else np.nan,
                        "competitor_z": 0.05 if wrong else np.nan,
                        "receptacle_x": 0.3,
                        "receptacle_y": -0.1,
                        "steps": 250 if stage >= 3 else 400,
                        "truncated": stage < 3,
                        "physics_unstable": False,
                    }
                )
    frame = pd.DataFrame(rows)
    assert list(frame.columns) == list(COLUMNS)
    return frame


def write_sweep(
    folder: Path,
    task: str,
    seed: int,
    conditions=CONDITIONS,
    seed_offset: int = 0,
    counterbalanced=False,
    competitor_pool=None,
) -> Path:
    manifest = sweep_manifest(task, conditions, seed_offset, counterbalanced, competitor_pool)
    folder.mkdir(parents=True)
    (folder / "sweep.json").write_text(json.dumps(manifest, indent=2))
    write_table(
        sweep_rows(manifest, np.random.default_rng(seed)), folder / "results.parquet", metadata=manifest
    )
    return folder


def write_diagnose(folder: Path) -> Path:
    (folder / "figures").mkdir(parents=True)
    (folder / "figures" / "tsne_shift.png").write_bytes(png_bytes())
    # units as `condground diagnose` writes them: phase retention and conditional placement in percent
    layers = {
        name: {
            "shift": {"pick": 0.01 * i, "place": 0.02 * i},
            "phase_retained": 50.0 + 10 * i,
            "container_silhouette": 0.05 * i,
        }
        for i, name in enumerate(("vision_encoder", "memory", "decoder"))
    }
    data = {
        "kind": "diagnose",
        "policy_label": "act_modified/full",
        "checkpoint": "outputs/train/full_0/pretrained_model",
        "checkpoint_hash": "ab" * 8,
        "task": "PickPlaceRandomBin-v0",
        "pairs": 20,
        "frames": 400,
        "layers": layers,
        "table2": {
            "place_shift": 0.0131,
            "phase_retained": 102.0,
            "container_silhouette": 0.18,
            "conditional_placement": 95.0,
        },
        "table2_units": {
            "place_shift": "1 - cos",
            "phase_retained": "%",
            "container_silhouette": "silhouette",
            "conditional_placement": "%",
        },
        "conditional_placement": {
            "value": 95.0,
            "k": 19,
            "n": 20,
            "condition": "full_mixed",
            "sweep_dir": "x",
        },
        "paper": {"source": "Table II", "columns": {}, "column": "Modified"},
        "figures": {"decoder clean/full shift": "figures/tsne_shift.png"},
        "notes": ["the scripted expert did not place in pairs with seeds [7]"],
        "command": ["condground", "diagnose", "--policy.path=outputs/train/full_0/pretrained_model"],
        "versions": {"python": "3.12.3", "lerobot_policy_condground": "0.1.0"},
    }
    (folder / "diagnostics.json").write_text(json.dumps(data))
    return folder


def write_probe(folder: Path) -> Path:
    target = np.zeros(20, bool)
    swapped = np.arange(20) < 12
    folder.mkdir(parents=True)
    data = {
        "kind": "probe",
        "policy_label": "act_modified/full",
        "checkpoint": "outputs/train/full_0/pretrained_model",
        "checkpoint_hash": "ab" * 8,
        "task": "PickPlaceRandomBin-v0",
        "role": "receptacle",
        "match": "color",
        "condition": "receptacle_color_1",
        "episodes": 20,
        "target": rate(0, 20),
        "swapped": rate(12, 20),
        "difference": paired_difference(target, swapped),
        "command": ["condground", "probe"],
        "versions": {"python": "3.12.3"},
    }
    (folder / "probe.json").write_text(json.dumps(data))
    return folder


def write_attention(folder: Path) -> Path:
    (folder / "stills").mkdir(parents=True)
    (folder / "stills" / "step_0001.png").write_bytes(png_bytes("tab:red"))
    data = {
        "kind": "attention",
        "policy_label": "act_modified/full",
        "checkpoint": "outputs/train/full_0/pretrained_model",
        "task": "PickPlaceRandomBin-v0",
        "condition": "full_mixed",
        "seed": 3,
        "head": 0,
        "frames": 400,
        "video": "attention.mp4",
        "stills": ["stills/step_0001.png"],
        "phase_predicted": [0, 1],
        "attention_mass_mean": {"target_object": 0.41, "competitors": 0.07},
        "command": ["condground", "attention"],
        "versions": {"python": "3.12.3"},
    }
    (folder / "attention.json").write_text(json.dumps(data))
    return folder


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> list[Path]:
    root = tmp_path_factory.mktemp("report_inputs")
    return [
        write_sweep(root / "sweep_t1", TASKS[0], 1),
        write_sweep(root / "sweep_t2", TASKS[1], 2),
        write_diagnose(root / "diag"),
        write_probe(root / "probe"),
        write_attention(root / "attn"),
    ]


@pytest.fixture(scope="module")
def report(inputs, tmp_path_factory) -> tuple[Path, Path]:
    out = tmp_path_factory.mktemp("report") / "report.html"
    return build_report(
        ReportConfig(input_dir=[str(p) for p in inputs], output=str(out), title="test report")
    )


EXPECTED_ROWS = {
    "table-1": 2,  # policies
    "stage-table": 2 * 2 * 4,  # policies x tasks x conditions
    "condition-differences": 2 * 2 * 3,  # policies x tasks x non-clean conditions
    "variant-differences": 1 * 2 * 4,  # non-baseline policies x tasks x conditions
    "table-2": 4,  # the paper's four metrics
    "layer-diagnostics": 3,
    "probe": 1,
    "attention": 1,
    "provenance": 5 + 1,  # inputs + the report itself
}


def test_report_renders_in_headless_chromium(report):
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} is absent (the Makefile installs Debian's chromium and chromium-driver)")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage"):
        options.add_argument(flag)
    options.binary_location = str(CHROMIUM)
    # An explicit driver path: Selenium Manager never runs, so nothing is downloaded.
    driver = webdriver.Chrome(options=options, service=Service(executable_path=str(CHROMEDRIVER)))
    try:
        driver.get(report[0].resolve().as_uri())
        state = driver.execute_script("""
            const rows = {};
            for (const t of document.querySelectorAll('table')) rows[t.id] = t.tBodies[0].rows.length;
            const imgs = Array.from(document.images);
            return {
                title: document.title,
                rows: rows,
                images: imgs.length,
                loaded: imgs.filter(i => i.complete && i.naturalWidth > 0).length,
                external: imgs.filter(i => !i.src.startsWith('data:image/png;base64,')).length,
                links: document.querySelectorAll('link, script').length,
                paperHeader: Array.from(document.querySelectorAll('#table-1 th')).map(th => th.textContent),
                // What a reader sees first: the first section, and what follows the title and intro.
                firstSection: document.querySelector('h2').textContent,
                firstBlocks: Array.from(document.querySelectorAll('h2 ~ *')).slice(0, 4).map(e => e.tagName),
                folded: Array.from(document.querySelectorAll('table')).filter(
                    t => t.closest('details') && !t.closest('details').open).map(t => t.id),
                visibleFolded: document.getElementById('stage-table').checkVisibility(),
                visibleClicked: (() => {
                    document.querySelector('#details-stage-table summary').click();
                    return document.getElementById('stage-table').checkVisibility();
                })(),
                actRow: Array.from(document.querySelectorAll('#table-1 tbody tr')).map(tr => tr.innerText),
            };
        """)
    finally:
        driver.quit()
    assert state["title"] == "test report"
    assert state["rows"] == EXPECTED_ROWS
    # The report opens on its figures; every table but Table I is folded until its caption is clicked.
    assert state["firstSection"] == "At a glance" and state["firstBlocks"][1:4] == ["FIGURE"] * 3
    assert sorted(state["folded"]) == sorted(set(EXPECTED_ROWS) - {"table-1"})
    assert state["visibleFolded"] is False and state["visibleClicked"] is True
    # 2 success and 2 funnel plots at a glance, 2 stage plots, 2 condition-difference plots, 2
    # variant-difference plots, t-SNE, attention still, probe
    assert state["images"] == 13
    assert state["loaded"] == state["images"]
    assert state["external"] == 0 and state["links"] == 0
    assert "paper (simulation)" in state["paperHeader"]
    act_row = next(r for r in state["actRow"] if r.startswith("act\t"))
    assert "Standard ACT" in act_row and "39.5%" in act_row and "14.0%" in act_row
    assert re.search(r"\d+\.\d% \[\d+\.\d, \d+\.\d\] \(\d+/10\)", act_row), (
        act_row
    )  # 2 seeds x 5 episodes per task


def test_report_numbers_follow_the_inputs(inputs, report):
    text = report[0].read_text()
    frame = pd.read_parquet(inputs[0] / "results.parquet")
    cell = frame[(frame.policy_label == "act") & (frame.condition == "full_mixed")]
    k, n = int(cell.success.sum()), len(cell)
    assert f"({k}/{n})" in text
    assert "Newcombe" in text and "McNemar" in text
    # two training runs a policy: the variant difference carries the run-aware interval beside Newcombe's
    d = variant_differences(frame, "act").iloc[0]
    assert (
        f"{100 * d['diff']:+.1f} pp [{100 * d['cluster_low']:+.1f}, {100 * d['cluster_high']:+.1f}]" in text
    )
    assert "+60.0 pp" in text  # probe: 12/20 swapped vs 0/20 target
    assert (
        "condground sweep --env.task=PickPlaceFixedBin-v0 &#x27;--policy.paths=[a,b]&#x27; &#x27;--output_dir=out dir&#x27;"
        in text
    )
    assert (
        "102.0%" in text and "10200" not in text and "95.0% (19/20)" in text
    )  # percent as diagnose writes it
    assert "act_modified/full (paper: Modified)" in text and "108.5%" in text
    assert "did not place in pairs with seeds [7]" in text
    assert "step_0001, predicted phase 1" in text and "target_object: 0.4100" in text


def test_markdown_links_existing_pngs(report):
    html_path, md_path = report
    assert md_path == html_path.with_suffix(".md") and md_path.is_file()
    text = md_path.read_text()
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text)
    assert len(links) == 13
    for link in links:
        path = md_path.parent / link
        assert path.is_file() and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", link
        assert path.parent.name == f"{html_path.stem}_files"
    assert "| policy | this report: T1 PickPlaceFixedBin-v0 |" in text
    assert text.count("\n| act_modified/full | ") >= 2


def test_missing_inputs_leave_a_note(inputs, tmp_path):
    html_path, _ = build_report(ReportConfig(input_dir=[str(inputs[3])], output=str(tmp_path / "r.html")))
    text = html_path.read_text()
    assert 'id="probe"' in text and 'id="table-1"' not in text and 'id="table-2"' not in text
    assert (
        text.count('class="note"') == 10
    )  # at a glance, table I, stages, 2 difference sections, subgoals, table II, t-SNE, attention, comparisons


def test_parse_report_args_accepts_repeated_and_comma_separated_dirs():
    cfg = parse_report_args(
        [
            "--input_dir=a",
            "--input_dir",
            "b",
            "--input_dir=c,d",
            "--input_dir=[e, f]",
            "--output=x/r.html",
            "--title=Run 3: ablation, [draft]",
        ]
    )
    assert cfg.input_dir == ["a", "b", "c", "d", "e", "f"]
    assert (cfg.output, cfg.title) == ("x/r.html", "Run 3: ablation, [draft]")  # not read as YAML
    assert parse_report_args([]).output == "outputs/report/report.html"


def test_refuses_dir_without_known_json(tmp_path):
    (tmp_path / "stray").mkdir()
    (tmp_path / "stray" / "notes.json").write_text("{}")
    with pytest.raises(
        ValueError,
        match=r"stray: none of sweep.json, subgoals.json, diagnostics.json, probe.json, attention.json",
    ):
        build_report(ReportConfig(input_dir=[str(tmp_path / "stray")], output=str(tmp_path / "r.html")))
    assert not (tmp_path / "r.html").exists()


def test_refuses_episodes_in_two_sweep_dirs(inputs, tmp_path):
    copy = shutil.copytree(inputs[0], tmp_path / "sweep_t1_again")
    with pytest.raises(ValueError, match=r"episodes appear in more than one sweep directory .*sweep_t1"):
        build_report(ReportConfig(input_dir=[str(inputs[0]), str(copy)], output=str(tmp_path / "r.html")))
    with pytest.raises(ValueError, match="given twice"):
        build_report(
            ReportConfig(input_dir=[str(inputs[0]), str(inputs[0])], output=str(tmp_path / "r.html"))
        )


def test_refuses_parquet_missing_a_column(tmp_path):
    folder = tmp_path / "broken"
    manifest = sweep_manifest(TASKS[0])
    folder.mkdir()
    (folder / "sweep.json").write_text(json.dumps(manifest))
    frame = sweep_rows(manifest, np.random.default_rng(0)).drop(columns=["lift"])
    table = pa.Table.from_pandas(frame, preserve_index=False)
    pq.write_table(
        table.replace_schema_metadata({METADATA_KEY: json.dumps(manifest).encode()}),
        folder / "results.parquet",
    )
    with pytest.raises(ValueError, match=r"broken: .*lacks columns \['lift'\]"):
        build_report(ReportConfig(input_dir=[str(folder)], output=str(tmp_path / "r.html")))


def test_refuses_parquet_of_another_grid(tmp_path):
    manifest = sweep_manifest(TASKS[0])
    other = json.loads(json.dumps(manifest))
    other["grid"]["n_episodes"] = 600
    folder = tmp_path / "other_grid"
    folder.mkdir()
    (folder / "sweep.json").write_text(json.dumps(other))
    write_table(sweep_rows(manifest, np.random.default_rng(0)), folder / "results.parquet", metadata=manifest)
    with pytest.raises(
        ValueError, match=r"other_grid: results.parquet was written for another grid .*n_episodes"
    ):
        build_report(ReportConfig(input_dir=[str(folder)], output=str(tmp_path / "r.html")))

    # same grid, but the rows hold a condition the grid does not list
    folder = tmp_path / "extra_condition"
    folder.mkdir()
    (folder / "sweep.json").write_text(json.dumps(manifest))
    rows = sweep_rows(manifest, np.random.default_rng(0))
    rows.loc[rows.condition == "object_color_3", "condition"] = "object_color_2"
    write_table(rows, folder / "results.parquet", metadata=manifest)
    with pytest.raises(
        ValueError, match=r"extra_condition: results.parquet does not match sweep.json: conditions"
    ):
        build_report(ReportConfig(input_dir=[str(folder)], output=str(tmp_path / "r.html")))


def test_refuses_rows_edited_to_contradict_themselves(tmp_path):
    manifest = sweep_manifest(TASKS[0])
    folder = tmp_path / "edited"
    folder.mkdir()
    (folder / "sweep.json").write_text(json.dumps(manifest))
    rows = sweep_rows(manifest, np.random.default_rng(0))
    failed = rows.index[~rows.place.astype(bool)][0]
    rows.loc[failed, "success"] = True  # a failure turned into a success, nothing else touched
    write_table(rows, folder / "results.parquet", metadata=manifest)
    with pytest.raises(ValueError, match=r"edited/results.parquet: 1 rows contradict themselves"):
        build_report(ReportConfig(input_dir=[str(folder)], output=str(tmp_path / "r.html")))


def test_sweeps_split_by_condition_are_paired_across_dirs(tmp_path):
    clean = write_sweep(tmp_path / "clean", TASKS[0], 1, ["clean"])
    rest = write_sweep(tmp_path / "rest", TASKS[0], 2, ["object_color_3", "full_mixed"])
    html_path, _ = build_report(
        ReportConfig(input_dir=[str(clean), str(rest)], output=str(tmp_path / "r.html"))
    )
    text = html_path.read_text()
    table = text[text.index('id="condition-differences"') :]
    assert table[: table.index("</table>")].count("<tr>") == 1 + 2 * 2  # header + policies x conditions
    assert "Not paired" not in text


def test_counterbalanced_and_augmentation_competitor_sweeps_are_their_own_conditions(tmp_path):
    # the same checkpoints, layouts and condition with permuted or other assets: other scene distributions
    plain = write_sweep(tmp_path / "plain", TASKS[0], 1, ["clean", "full_mixed"])
    permuted = write_sweep(tmp_path / "cb", TASKS[0], 2, ["full_mixed"], counterbalanced=True)
    pool = write_sweep(tmp_path / "aug", TASKS[0], 3, ["full_mixed"], competitor_pool="augmentation")
    _, md_path = build_report(
        ReportConfig(input_dir=[str(pool), str(plain), str(permuted)], output=str(tmp_path / "r.html"))
    )
    stages = md_path.read_text().split("## Stage metrics")[1].split("\n## ")[0]
    rows = [line for line in stages.splitlines() if "act_modified/full" in line]
    assert [row.split(" | ")[2] for row in rows] == [
        "clean", "full_mixed", "full_mixed (augmentation competitors)", "full_mixed (counterbalanced)"
    ]  # fmt: skip
    table1 = md_path.read_text().split("## Table I")[1].split("\n## ")[0]
    assert "counterbalanced" not in table1 and "augmentation" not in table1  # the paper's plain full_mixed


def test_sweeps_of_other_layouts_combine_but_do_not_pair(tmp_path):
    # the same checkpoints and episode indices under another seed offset: other layouts, not duplicates
    first = write_sweep(tmp_path / "offset0", TASKS[0], 1, ["clean"])
    second = write_sweep(tmp_path / "offset1", TASKS[0], 2, ["full_mixed"], seed_offset=1_000_000)
    html_path, _ = build_report(
        ReportConfig(input_dir=[str(first), str(second)], output=str(tmp_path / "r.html"))
    )
    text = html_path.read_text()
    assert 'id="table-1"' in text and 'id="condition-differences"' not in text
    assert text.count("Not paired: ") == 2 and "episodes have no partner" in text


def test_a_report_replaces_only_what_it_wrote(inputs, tmp_path):
    cfg = ReportConfig(input_dir=[str(inputs[2]), str(inputs[4])], output=str(tmp_path / "r.html"))
    html_path, md_path = build_report(cfg)
    files = md_path.parent / "r_files"
    ours = sorted(p.name for p in files.glob("*.png"))
    assert ours, "figures beside the Markdown"
    (files / "holiday.png").write_bytes(png_bytes())  # the user's own file in the report's folder
    build_report(ReportConfig(input_dir=[str(inputs[4])], output=cfg.output))  # fewer figures
    left = sorted(p.name for p in files.glob("*.png"))
    assert "holiday.png" in left and set(ours) - set(left), "the report's stale figures go, the user's stays"

    # Output names that would clobber something: the Markdown itself, a file another tool wrote.
    for output, fragment in (
        (tmp_path / "r.md", "is not allowed; allowed: a file name ending in .html"),
        (tmp_path / "notes.html", "which condground report did not write"),
    ):
        if output.suffix == ".html":
            output.write_text("<p>my notes</p>")
        before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
        with pytest.raises((ValueError, FileExistsError), match=re.escape(fragment)):
            build_report(ReportConfig(input_dir=[str(inputs[4])], output=str(output)))
        assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before


def test_a_report_never_writes_through_a_link(inputs, tmp_path):
    cfg = ReportConfig(input_dir=[str(inputs[4])], output=str(tmp_path / "r.html"))
    build_report(cfg)
    victim = tmp_path / "victim.txt"
    victim.write_text("mine")
    figure = next((tmp_path / "r_files").glob("*.png"))
    figure.unlink()
    figure.symlink_to(victim)
    with pytest.raises(PermissionError, match="would write through the link"):
        build_report(cfg)
    assert victim.read_text() == "mine"


def test_a_report_that_died_half_way_does_not_block_its_rerun(inputs, tmp_path, monkeypatch):
    cfg = ReportConfig(input_dir=[str(inputs[4])], output=str(tmp_path / "r.html"))

    def disk_full(self, data):
        raise OSError(28, "No space left on device")

    with monkeypatch.context() as patch:
        patch.setattr(Path, "write_bytes", disk_full)  # the HTML is written, the first figure is not
        with pytest.raises(OSError, match="No space left"):
            build_report(cfg)
    assert (tmp_path / "r.html").exists()
    html_path, md_path = build_report(cfg)
    assert md_path.exists() and list((tmp_path / "r_files").glob("*.png"))


def test_input_json_cannot_reach_outside_its_folder_or_inject_html(inputs, tmp_path):
    secret = tmp_path / "secret.png"
    secret.write_bytes(png_bytes())
    for rel in ("../secret.png", str(secret), "figures/../../secret.png"):
        diag = tmp_path / f"diag{len(rel)}"
        shutil.copytree(inputs[2], diag)
        data = json.loads((diag / "diagnostics.json").read_text())
        data["figures"] = {"shift": rel}
        (diag / "diagnostics.json").write_text(json.dumps(data))
        with pytest.raises(
            ValueError, match=f"figure {re.escape(repr(rel))} listed in its JSON is outside {diag}"
        ):
            build_report(ReportConfig(input_dir=[str(diag)], output=str(tmp_path / "x.html")))

    diag = tmp_path / "diag_html"
    shutil.copytree(inputs[2], diag)
    data = json.loads((diag / "diagnostics.json").read_text())
    data["notes"] = ['<img src=x onerror="alert(1)"> | <script>alert(2)</script>']
    (diag / "diagnostics.json").write_text(json.dumps(data))
    html_path, md_path = build_report(ReportConfig(input_dir=[str(diag)], output=str(tmp_path / "h.html")))
    for path in (html_path, md_path):
        text = path.read_text()
        assert "<script>alert" not in text and "<img src=x" not in text, path
        assert "&lt;script&gt;alert(2)&lt;/script&gt;" in text, path


def comparison(folder: Path, **changes) -> Path:
    """A comparison folder as `condground compare` writes it (its JSON and figure), with `changes` to the JSON."""
    folder.mkdir(parents=True)
    (folder / "compare.png").write_bytes(png_bytes())
    row = {"lever": "aug", "baseline_arm": "std", "task": "PickPlaceFixedBin-v0", "condition": "full_mixed",
           "seeds": 2, "n": 300, "baseline": 0.02, "treated": 0.3, "diff": 0.28, "diff_low": 0.2, "diff_high": 0.35,
           "p": 1e-9, "cluster_low": 0.05, "cluster_high": 0.51, "cluster_p": 0.03, "seed_effects": "+0.2 +0.36",
           "differences": ""}  # fmt: skip
    data = {
        "kind": "compare",
        "summary": [row],
        "figure": "compare.png",
        "command": ["condground", "compare"],
    }
    (folder / "compare.json").write_text(json.dumps({**data, **changes}))
    return folder


def test_a_comparison_is_a_section_and_its_json_stays_in_its_folder(tmp_path):
    html_path, md_path = build_report(
        ReportConfig(input_dir=[str(comparison(tmp_path / "cmp"))], output=str(tmp_path / "r.html"))
    )
    text = md_path.read_text()
    assert "| aug vs std | T1 PickPlaceFixedBin-v0 | full_mixed | 2 | 300 | 2.0% | 30.0% |" in text
    assert "+28.0 pp [+5.0, +51.0], p=0.03" in text and "+28.0 pp [+20.0, +35.0], p=1e-09" in text
    secret = tmp_path / "secret.png"
    secret.write_bytes(png_bytes())
    bad = comparison(tmp_path / "out", figure="../secret.png")
    with pytest.raises(ValueError, match="figure '../secret.png' listed in its JSON is outside"):
        build_report(ReportConfig(input_dir=[str(bad)], output=str(tmp_path / "x.html")))
    bad = comparison(tmp_path / "text", summary=[{"diff": "0.5; <script>"}])
    with pytest.raises(ValueError, match="summary has diff='0.5; <script>'; allowed: a number"):
        build_report(ReportConfig(input_dir=[str(bad)], output=str(tmp_path / "y.html")))


def test_a_tampered_manifest_deletes_nothing(inputs, tmp_path):
    out = tmp_path / "r.html"
    build_report(ReportConfig(input_dir=[str(inputs[4])], output=str(out)))
    victim = tmp_path / "victim.png"
    victim.write_bytes(png_bytes())
    (tmp_path / "r_files" / "condground-report.json").write_text(json.dumps({"figures": ["../victim.png"]}))
    with pytest.raises(ValueError, match="is damaged .*not a plain PNG file name"):
        build_report(ReportConfig(input_dir=[str(inputs[4])], output=str(out)))
    assert victim.is_file()
    # A user's figure claimed by an edited manifest, by name alone or with a made-up hash: kept.
    holiday = tmp_path / "r_files" / "holiday.png"
    holiday.write_bytes(png_bytes())
    ours = [p.name for p in (tmp_path / "r_files").glob("*.png") if p != holiday]
    for figures in ([*ours, "holiday.png"], {**dict.fromkeys(ours), "holiday.png": "0" * 64}):
        (tmp_path / "r_files" / "condground-report.json").write_text(json.dumps({"figures": figures}))
        build_report(ReportConfig(input_dir=[str(inputs[4])], output=str(out)))
        assert holiday.read_bytes() == png_bytes()


def write_subgoals(folder: Path, successes: dict, scored_by: str = "env") -> Path:
    """A `condground subgoals` directory: successes[condition][subgoal] of 5 trials succeed."""
    runs, rows = {}, []
    for condition, per_subgoal in successes.items():
        ck = checkpoint("act", 0, condition)
        runs[condition] = {
            "checkpoint": ck,
            "subgoals": list(per_subgoal),
            "trials": 5,
            "command": ["condground", "subgoals", f"--condition={condition}"],
        }
        for index, (subgoal, k) in enumerate(per_subgoal.items()):
            for trial in range(5):
                rows.append(
                    {
                        "policy_label": ck["label"], "policy_type": ck["policy_type"], "variant": "",
                        "checkpoint": ck["path"], "checkpoint_hash": ck["hash"], "training_seed": 0,
                        "task": "InstrumentRouting-v0", "condition": condition, "condition_spec": "{}",
                        "counterbalanced": False, "eval_seed": 0, "episode": trial, "layout_seed": index * 100 + trial,
                        "success": trial < k, "steps": 50, "truncated": False, "subgoal": subgoal,
                        "destination": "left", "scored_by": scored_by,
                    }
                )  # fmt: skip
    folder.mkdir(parents=True)
    manifest = {"kind": "subgoals", "task": "InstrumentRouting-v0", "mode": "sim", "runs": runs}
    (folder / "subgoals.json").write_text(json.dumps(manifest))
    write_table(rows, folder / "results.parquet", metadata=manifest)
    return folder


def test_subgoal_section_tables_each_condition_beside_the_paper(tmp_path):
    from scipy.stats import binomtest

    all_five = dict.fromkeys(("pick", "inspect", "route", "place", "home"), 5)
    sim = write_subgoals(tmp_path / "sim", {"cue": all_five, "no_cue": {**all_five, "route": 2, "place": 1}})
    real = write_subgoals(tmp_path / "real", {"no_cue": {"route": 4}}, scored_by="operator")
    html_path, md_path = build_report(
        ReportConfig(input_dir=[str(sim), str(real)], output=str(tmp_path / "r.html"))
    )
    table = next(line for line in md_path.read_text().splitlines() if line.startswith("| subgoal |"))
    assert table == (
        "| subgoal | this report: cue | this report: no_cue | this report: no_cue (operator-scored) "
        "| paper: cue | paper: no_cue |"
    )  # the paper did not run explicit: no column for it

    def cell(k, n):
        ci = binomtest(k, n).proportion_ci(method="wilson")
        return f"{100 * k / n:.1f}% [{100 * ci.low:.1f}, {100 * ci.high:.1f}] ({k}/{n})"

    rows = {line.split(" | ")[0].lstrip("| "): line for line in md_path.read_text().splitlines()}
    assert (
        rows["route (routing)"]
        == f"| route (routing) | {cell(5, 5)} | {cell(2, 5)} | {cell(4, 5)} | 10/10 (pooled) | 5/10 (pooled) |"
    )
    assert rows["pick"] == f"| pick | {cell(5, 5)} | {cell(5, 5)} | not run | 5/5 | 5/5 |"
    assert rows["routing: route + place"].endswith(f"| {cell(3, 10)} | {cell(4, 5)} | 10/10 | 5/10 |")
    assert rows["overall"] == f"| overall | {cell(25, 25)} | {cell(18, 25)} | {cell(4, 5)} | 25/25 | 20/25 |"
    text = html_path.read_text()
    assert 'id="subgoals"' in text and "condground subgoals --condition=no_cue" in text

    copy = shutil.copytree(sim, tmp_path / "sim_again")
    with pytest.raises(ValueError, match=r"trials appear in more than one subgoals directory .*sim"):
        build_report(ReportConfig(input_dir=[str(sim), str(copy)], output=str(tmp_path / "r2.html")))


def test_values_from_the_inputs_stay_text_in_markdown(inputs, tmp_path):
    """A policy label or a note can carry Markdown: a remote image, a javascript: link, a heading, a table row.
    Rendered by a CommonMark parser, the report's Markdown shows them as the text they are."""
    from markdown_it import MarkdownIt

    image, link = "![pixel](https://evil.example/p.png)", "[run](javascript:alert(1))"
    sweep = tmp_path / "sweep"
    shutil.copytree(inputs[0], sweep)
    rows = pq.read_table(sweep / "results.parquet")
    frame = rows.to_pandas()
    frame["policy_label"] = frame["policy_label"].replace("act", f"act {image} {link}")
    pq.write_table(pa.Table.from_pandas(frame, preserve_index=False).replace_schema_metadata(rows.schema.metadata),
                   sweep / "results.parquet")  # fmt: skip
    manifest = json.loads((sweep / "sweep.json").read_text())  # the label as the sweep itself was given it
    for ck in manifest["checkpoints"]:
        ck["label"] = f"act {image} {link}" if ck["label"] == "act" else ck["label"]
    (sweep / "sweep.json").write_text(json.dumps(manifest))
    diag = tmp_path / "diag"
    shutil.copytree(inputs[2], diag)
    data = json.loads((diag / "diagnostics.json").read_text())
    data["notes"] = [f"{image} {link}\n# Owned\n| a | b |\n- listed **bold** `code`"]
    (diag / "diagnostics.json").write_text(json.dumps(data))
    _, md_path = build_report(
        ReportConfig(input_dir=[str(sweep), str(diag)], output=str(tmp_path / "r.html"))
    )
    rendered = MarkdownIt("commonmark").enable("table").render(md_path.read_text())
    assert "evil.example" in rendered and "javascript:alert" in rendered  # shown ...
    assert 'src="https://evil' not in rendered and 'href="javascript' not in rendered  # ... never live
    assert "<h1>Owned" not in rendered and "<strong>bold" not in rendered and "<li>listed" not in rendered
    assert image in rendered and "<code>code</code>" in rendered
    # Every figure the report links is its own PNG, in its own folder.
    assert all(src.startswith("r_files/") for src in re.findall(r'<img src="([^"]+)"', rendered))
