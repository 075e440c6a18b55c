"""`condground diagnose`: the metrics on arrays with known answers, matched pairs that differ only by
the competitors, the output files on tiny act_modified and stock ACT checkpoints, bad input."""

import json

import cv2
import numpy as np
import pandas as pd
import pytest

from lerobot_condground.core import paper
from lerobot_condground.core.configs import EvalEnvConfig, PolicyRefConfig
from lerobot_condground.diagnosis.diagnose import (
    LAYERS,
    DiagnoseConfig,
    DiagnoseOptions,
    collect_matched,
    container_silhouette,
    cosine_shift,
    layer_metrics,
    metrics_from_activations,
    phase_retention,
    run_diagnose,
)
from lerobot_condground.diagnosis.hooks import load_act_family
from lerobot_condground.evaluation.rollout import EnvSpec

TASK = "PickPlaceRandomBin-v0"


# ------------------------------------------------------------------------------------------ metrics
def test_metrics_on_known_answers():
    rng = np.random.default_rng(0)
    clean = rng.normal(size=(40, 8))
    phase = np.repeat([0, 1], 20)
    assert cosine_shift(clean, clean) == pytest.approx(0.0, abs=1e-12)
    assert phase_retention(clean, clean, phase) == pytest.approx(100.0)
    # Scaling keeps every direction (no shift) and doubles the centroid separation.
    assert cosine_shift(clean, 2 * clean) == pytest.approx(0.0, abs=1e-12)
    assert phase_retention(clean, 2 * clean, phase) == pytest.approx(200.0)
    # Orthogonal and opposite vectors.
    assert cosine_shift(np.eye(3), np.roll(np.eye(3), 1, axis=1)) == pytest.approx(1.0)
    assert cosine_shift(clean, -clean) == pytest.approx(2.0)
    # The distractor states collapse the phases onto one point: nothing of the separation is left.
    assert phase_retention(clean, np.ones_like(clean), phase) == pytest.approx(0.0)
    assert phase_retention(clean, clean, np.zeros(40)) is None  # no place frame

    side = np.repeat([0, 1], 20)
    separated = np.where(side[:, None] == 0, -10.0, 10.0) + rng.normal(scale=0.01, size=(40, 4))
    assert container_silhouette(separated, side) > 0.99
    assert abs(container_silhouette(rng.normal(size=(400, 4)), rng.integers(0, 2, 400))) < 0.05
    assert container_silhouette(separated, np.zeros(40, int)) is None  # one side only

    metrics = layer_metrics(clean, clean, phase, side)
    assert metrics["shift"] == {"pick": pytest.approx(0.0, abs=1e-12), "place": pytest.approx(0.0, abs=1e-12)}
    assert metrics["phase_retained"] == pytest.approx(100.0)
    assert metrics["container_silhouette"] == container_silhouette(clean[phase == 1], side[phase == 1])


# ------------------------------------------------------------------------------------------ matched pairs
def test_matched_frames_differ_only_by_competitors(tiny_checkpoints):
    loaded, spec = load_act_family(PolicyRefConfig(path=str(tiny_checkpoints[0])), EvalEnvConfig(task=TASK))
    checked = []

    def on_frame(obs_ref, obs_dis, env_ref, env_dis):
        np.testing.assert_allclose(obs_ref["agent_pos"], obs_dis["agent_pos"], atol=1e-6)
        for label in (1, 2):  # target object and receptacle move identically
            np.testing.assert_allclose(
                env_ref.entity_pose(label)[0], env_dis.entity_pose(label)[0], atol=1e-6
            )
        changed = np.abs(obs_ref["pixels"]["top"].astype(int) - obs_dis["pixels"]["top"]).max(-1) > 8
        competitors = (
            cv2.dilate((env_dis.render_segmentation() >= 3).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        )
        assert changed.any(), "the competitors must show"
        assert (changed & ~competitors).mean() < 0.002, "pixels away from the competitors changed"
        checked.append(1)

    distractor = EnvSpec(**{**spec.__dict__, "condition": "full_mixed"})
    data = collect_matched(
        loaded, spec, distractor, seeds=[3], stride=15, batch_size=8, progress=False, on_frame=on_frame
    )
    assert len(checked) == len(data["phase"]) >= 4
    assert set(np.unique(data["phase"])) == {0, 1}
    assert data["expert_success"].tolist() == [True]
    for layer in LAYERS:
        ref, dis = data[f"{layer}_reference"], data[f"{layer}_distractor"]
        assert ref.shape == dis.shape and ref.shape[0] == len(checked)
        assert not np.allclose(ref, dis), f"{layer}: the competitors must change the activations"
    assert data["vision_encoder_reference"].shape[1] == 512  # ResNet-18 channels, one camera
    assert data["decoder_reference"].shape[1] == 32  # dim_model


# ------------------------------------------------------------------------------------------ command
def test_flags_parse_and_command_round_trips():
    import draccus

    from lerobot_condground.core.provenance import command_line

    cfg = draccus.parse(
        DiagnoseConfig,
        args=[
            "--policy.path=some/ckpt",
            "--env.task=PickPlaceRandomBin-v0",
            "--output_dir=d",
            "--diagnose.pairs=3",
            "--diagnose.frame_stride=2",
            "--diagnose.distractor_condition=receptacle_shape_2",
            "--sweep_dir=s",
            "--policy.device=cpu",
        ],
    )
    assert (cfg.policy.path, cfg.diagnose.pairs, cfg.diagnose.frame_stride, cfg.sweep_dir) == (
        "some/ckpt",
        3,
        2,
        "s",
    )
    assert cfg.env.condition == "clean" and cfg.diagnose.distractor_condition == "receptacle_shape_2"
    line = command_line("diagnose", cfg)
    assert line[:2] == ["condground", "diagnose"] and draccus.parse(DiagnoseConfig, args=line[2:]) == cfg


def _diagnose(checkpoint, out, pairs=2, stride=12, **kw) -> dict:
    cfg = DiagnoseConfig(
        policy=PolicyRefConfig(path=str(checkpoint)),
        env=EvalEnvConfig(task=TASK),
        diagnose=DiagnoseOptions(pairs=pairs, frame_stride=stride, seed=1),
        output_dir=str(out),
        progress=False,
        **kw,
    )
    path = run_diagnose(cfg)
    return json.loads((path / "diagnostics.json").read_text())


def test_diagnose_act_modified_files_and_sweep(tiny_checkpoints, tmp_path):
    from lerobot_condground.evaluation.checkpoints import checkpoint_hash

    checkpoint = tiny_checkpoints[0]
    digest = checkpoint_hash(str(checkpoint))
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    rows = [  # 3 lifted, 2 of them placed, under full_mixed; other rows must not count
        {
            "checkpoint_hash": digest,
            "task": TASK,
            "condition": "full_mixed",
            "prompt": "target",
            "lift": lifted,
            "place": placed,
        }
        for lifted, placed in ((True, True), (True, True), (True, False), (False, False))
    ] + [
        {
            "checkpoint_hash": digest,
            "task": TASK,
            "condition": "clean",
            "prompt": "target",
            "lift": True,
            "place": False,
        },
        {
            "checkpoint_hash": "0" * 16,
            "task": TASK,
            "condition": "full_mixed",
            "prompt": "target",
            "lift": True,
            "place": False,
        },
        {
            "checkpoint_hash": digest,
            "task": TASK,
            "condition": "full_mixed",
            "prompt": "swapped",
            "lift": True,
            "place": False,
        },
    ]
    for i, row in enumerate(rows):  # one episode each
        row.update(eval_seed=0, episode=i, layout_seed=1_000_000 + i)
    pd.DataFrame(rows).to_parquet(sweep / "results.parquet")
    manifest = {
        "grid": {"task": TASK, "counterbalanced": False},
        "checkpoints": [{"hash": digest}, {"hash": "0" * 16}],
    }
    (sweep / "sweep.json").write_text(json.dumps(manifest))
    # Rows the sweep's manifest does not vouch for, or another scene distribution, are refused, not counted.
    from lerobot_condground.diagnosis.diagnose import conditional_placement

    for changed, message in (
        ({"checkpoints": [{"hash": digest}]}, "checkpoint_hash='0000000000000000'.*is not part of the run"),
        ({"grid": {"task": TASK, "counterbalanced": True}}, r"plain ones \(counterbalanced\)"),
        (
            {"grid": {"task": TASK, "competitor_pool": "augmentation"}},
            r"plain ones \(augmentation competitors\)",
        ),
    ):
        (sweep / "sweep.json").write_text(json.dumps({**manifest, **changed}))
        with pytest.raises(ValueError, match=message):
            conditional_placement(str(sweep), digest, TASK, "full_mixed")
    (sweep / "sweep.json").write_text(json.dumps(manifest))

    out = tmp_path / "diag"
    result = _diagnose(checkpoint, out, sweep_dir=str(sweep))
    assert result["kind"] == "diagnose"
    for key in (
        "policy_label",
        "checkpoint",
        "checkpoint_hash",
        "task",
        "pairs",
        "frames",
        "layers",
        "table2",
        "paper",
        "figures",
        "command",
        "versions",
    ):
        assert key in result, key
    assert result["policy_label"] == "act_modified/full" and result["checkpoint_hash"] == digest
    assert result["pairs"] == 2 and result["frames"] == sum(result["frames_per_phase"].values()) > 0
    assert set(result["layers"]) == set(LAYERS)
    for metrics in result["layers"].values():
        assert set(metrics) == {"shift", "phase_retained", "container_silhouette"}
        assert set(metrics["shift"]) == {"pick", "place"}
        assert 0 <= metrics["shift"]["place"] <= 2
    decoder = result["layers"]["decoder"]
    assert result["table2"]["place_shift"] == decoder["shift"]["place"]
    assert result["table2"]["phase_retained"] == decoder["phase_retained"]
    assert result["table2"]["conditional_placement"] == pytest.approx(100 * 2 / 3)
    assert result["conditional_placement"]["k"] == 2 and result["conditional_placement"]["n"] == 3
    assert result["paper"]["columns"] == paper.TABLE2 and result["paper"]["column"] == "Modified"
    assert result["max_state_difference"] < 1e-6
    assert (
        result["command"][:2] == ["condground", "diagnose"]
        and f"--policy.path={checkpoint}" in result["command"]
    )
    for rel in result["figures"].values():
        assert (out / rel).is_file() and (out / rel).stat().st_size > 1000
    assert set(result["figures"]) == {"tsne_condition", "tsne_container"}
    # The saved activations reproduce every number.
    recomputed = metrics_from_activations(out / "activations.npz")
    for layer in LAYERS:
        assert recomputed[layer]["shift"]["place"] == pytest.approx(result["layers"][layer]["shift"]["place"])
        assert recomputed[layer]["phase_retained"] == pytest.approx(result["layers"][layer]["phase_retained"])


def test_diagnose_stock_act(act_checkpoint, tmp_path):
    result = _diagnose(act_checkpoint, tmp_path / "act", pairs=1, stride=20)
    assert result["policy_label"] == "act" and result["paper"]["column"] == "Standard"
    assert result["table2"]["conditional_placement"] is None
    assert any("--sweep_dir" in note for note in result["notes"])
    assert result["layers"]["decoder"]["shift"]["pick"] is not None


def test_bad_input(tiny_checkpoints, tmp_path):
    fake = tmp_path / "diffusion"
    fake.mkdir()
    (fake / "config.json").write_text(json.dumps({"type": "diffusion"}))
    from safetensors.torch import save_file

    save_file({}, str(fake / "model.safetensors"))  # whole, or the weights check would refuse it first
    with pytest.raises(ValueError, match=r"'diffusion' policy.*ACT-family.*act_modified"):
        _diagnose(fake, tmp_path / "x")
    with pytest.raises(ValueError, match="ACT-family"):
        _diagnose("expert", tmp_path / "x")
    with pytest.raises(ValueError, match=r"distractor_condition='full_mixd'.*allowed: clean"):
        run_diagnose(
            DiagnoseConfig(
                policy=PolicyRefConfig(path=str(tiny_checkpoints[0])),
                diagnose=DiagnoseOptions(distractor_condition="full_mixd"),
                output_dir=str(tmp_path / "x"),
            )
        )
    with pytest.raises(ValueError, match=r"--env.condition='nope'"):
        run_diagnose(
            DiagnoseConfig(
                policy=PolicyRefConfig(path=str(tiny_checkpoints[0])),
                env=EvalEnvConfig(condition="nope"),
                output_dir=str(tmp_path / "x"),
            )
        )
    with pytest.raises(ValueError, match=r"camera 'top' at 96x128 \(env renders 240x320\)"):
        run_diagnose(
            DiagnoseConfig(
                policy=PolicyRefConfig(path=str(tiny_checkpoints[0])),
                env=EvalEnvConfig(observation_height=240, observation_width=320),
                output_dir=str(tmp_path / "x"),
            )
        )
    assert not (tmp_path / "x").exists(), "bad input must fail before any output"
