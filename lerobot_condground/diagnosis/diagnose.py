"""`condground diagnose`: representation diagnostics of an ACT-family checkpoint (paper Table II, Figure 2).

Matched pairs: for each pair seed the scripted expert runs in the reference env (`--env.condition`,
default `clean`), and exactly its actions are replayed in a distractor env
(`--diagnose.distractor_condition`, default `full_mixed`) reset with the same seed. The layouts put
the two targets at the same poses under one seed, so the robot, the target object and the
receptacle move identically and the two frames of a matched step differ only by the competitors
(checked: the targets' initial poses must agree, and the robot state difference is recorded).

At every `--diagnose.frame_stride`-th step both observations go through the policy's own
pre-processor (as in lerobot-eval) and one forward pass (inference mode, z = 0) whose activations
are captured with forward hooks, for stock `act` and `act_modified` alike:

- `vision_encoder`: the backbone feature map of each camera averaged over space, cameras concatenated,
- `memory`: the transformer encoder output averaged over its tokens,
- `decoder`: the decoder output averaged over the action queries.

Per layer: the cosine shift 1 - cos(reference, distractor) averaged over the matched frames of each
phase (pick = expert phase 0, place = phase 1); phase retention = the distance between the pick and
place centroids under distractors over that distance in the reference condition (%); container
silhouette = the silhouette (euclidean) of the distractor place-phase states labelled by the target
receptacle's side (left/right in the top camera image, i.e. the sign of the receptacle's y).
`table2` holds the decoder values beside the conditional placement P(place | pick, lift) under the
distractor condition read from a `condground sweep` (`--sweep_dir`), and `paper` Table II's values.

Writes `diagnostics.json`, `activations.npz` (every captured activation and the per-frame metadata,
enough to recompute every number) and the t-SNE figures under `figures/`.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from lerobot_condground.core import paper
from lerobot_condground.core.conditions import check_condition
from lerobot_condground.core.configs import EvalEnvConfig, PolicyRefConfig, check_seed
from lerobot_condground.core.provenance import command_line, versions
from lerobot_condground.diagnosis.hooks import ACTProbe, acting_model, load_act_family

logger = logging.getLogger(__name__)

LAYERS = ("vision_encoder", "memory", "decoder")
PHASES = ("pick", "place")  # expert phase label 0 (acquire the object), 1 (transport and place)
SIDES = ("left", "right")  # of the target receptacle in the top camera image: y < 0, y >= 0
SIDE_AXIS = "y"


# ---------------------------------------------------------------------------------------------- configs
@dataclass
class DiagnoseOptions:
    # Matched clean/distractor episode pairs; pair i uses reset seed `seed + i`.
    pairs: int = 20
    seed: int = 0
    # Keep every k-th step of each episode.
    frame_stride: int = 1
    # The condition whose frames are matched against the reference condition's.
    distractor_condition: str = "full_mixed"
    # Matched frames per forward pass (each pass holds both frames of each pair).
    batch_size: int = 16
    # t-SNE of the decoder's place-phase states (figures only; the metrics use the raw features).
    tsne_perplexity: float = 30.0
    tsne_seed: int = 0


@dataclass
class DiagnoseConfig:
    policy: PolicyRefConfig = field(default_factory=PolicyRefConfig)
    # --env.condition: the reference condition of the matched pairs (default clean).
    env: EvalEnvConfig = field(default_factory=EvalEnvConfig)
    diagnose: DiagnoseOptions = field(default_factory=DiagnoseOptions)
    output_dir: str = "outputs/diagnose"
    # A `condground sweep` output directory: conditional placement under the distractor condition is
    # read from its results.parquet (rows of this checkpoint's hash). Optional.
    sweep_dir: str | None = None
    progress: bool = True

    def __post_init__(self):
        # This command's defaults for the shared groups (see core/configs.py on why not a default_factory).
        self.env.condition = self.env.condition or "clean"


# ---------------------------------------------------------------------------------------------- metrics
def cosine_shift(reference: np.ndarray, other: np.ndarray) -> float | None:
    """Mean over matched rows of 1 - cos(reference_i, other_i); None without rows."""
    reference, other = np.asarray(reference, dtype=np.float64), np.asarray(other, dtype=np.float64)
    if len(reference) == 0:
        return None
    norms = np.linalg.norm(reference, axis=1) * np.linalg.norm(other, axis=1)
    cos = (reference * other).sum(1) / np.maximum(norms, 1e-12)
    return float(np.mean(1.0 - cos))


def phase_retention(reference: np.ndarray, other: np.ndarray, phase: np.ndarray) -> float | None:
    """100 * |c_other(pick) - c_other(place)| / |c_ref(pick) - c_ref(place)| with c the phase centroids;
    None when a phase has no frame or the reference centroids coincide."""
    phase = np.asarray(phase)
    pick, place = phase == 0, phase == 1
    if not pick.any() or not place.any():
        return None
    reference, other = np.asarray(reference, dtype=np.float64), np.asarray(other, dtype=np.float64)
    d_ref = np.linalg.norm(reference[pick].mean(0) - reference[place].mean(0))
    d_other = np.linalg.norm(other[pick].mean(0) - other[place].mean(0))
    return float(100.0 * d_other / d_ref) if d_ref > 0 else None


def container_silhouette(states: np.ndarray, side: np.ndarray) -> float | None:
    """Silhouette (euclidean) of states labelled by container side; None when it is undefined
    (one side only, or no more samples than labels)."""
    from sklearn.metrics import silhouette_score

    side = np.asarray(side)
    labels = np.unique(side)
    if len(labels) < 2 or len(side) <= len(labels):
        return None
    return float(silhouette_score(np.asarray(states, dtype=np.float64), side, metric="euclidean"))


def layer_metrics(reference: np.ndarray, other: np.ndarray, phase: np.ndarray, side: np.ndarray) -> dict:
    phase, side = np.asarray(phase), np.asarray(side)
    place = phase == 1
    return {
        "shift": {
            name: cosine_shift(reference[phase == i], other[phase == i]) for i, name in enumerate(PHASES)
        },
        "phase_retained": phase_retention(reference, other, phase),
        "container_silhouette": container_silhouette(other[place], side[place]),
    }


def metrics_from_activations(path: str | Path) -> dict:
    """Recomputes every layer's metrics from a saved activations.npz."""
    data = np.load(path)
    return {
        layer: layer_metrics(
            data[f"{layer}_reference"], data[f"{layer}_distractor"], data["phase"], data["side"]
        )
        for layer in LAYERS
    }


def conditional_placement(
    sweep_dir: str | None, checkpoint_hash: str, task: str, condition: str
) -> tuple[dict, str | None]:
    """P(place | pick, lift) of this checkpoint under `condition` in a sweep: ({value %, k, n}, note)."""
    empty = {"value": None, "k": None, "n": None}
    if not sweep_dir:
        return empty, "conditional placement needs a sweep: pass --sweep_dir=DIR of a `condground sweep` run"
    import pandas as pd

    from lerobot_condground.core.conditions import ConditionSpec
    from lerobot_condground.core.files import read_json_object
    from lerobot_condground.evaluation.results import EPISODE_KEY, refuse_rows_outside, scene_distribution

    path = Path(sweep_dir) / "results.parquet"
    if not path.is_file():
        raise FileNotFoundError(
            f"--sweep_dir={sweep_dir!r} has no results.parquet (a `condground sweep` output_dir)"
        )
    rows = pd.read_parquet(path)
    missing = {"checkpoint_hash", "task", "condition", "lift", "place"} - set(rows.columns)
    if missing:
        raise ValueError(f"{path} lacks the sweep columns {sorted(missing)}")
    manifest_path = Path(sweep_dir) / "sweep.json"
    if not manifest_path.is_file():
        raise FileNotFoundError(f"--sweep_dir={sweep_dir!r} has results.parquet but no sweep.json")
    manifest = read_json_object(manifest_path, "Sweep manifest")
    grid = manifest.get("grid") or {}
    if suffix := scene_distribution(grid):
        raise ValueError(
            f"--sweep_dir={sweep_dir!r} is a sweep of other scenes than its conditions' plain ones{suffix}; "
            "give a plain one"
        )
    hashes = {c.get("hash") for c in manifest.get("checkpoints", [])}
    refuse_rows_outside(path, rows, ["checkpoint_hash"], lambda h: h in hashes, "sweep.json")
    key = list(EPISODE_KEY)
    repeated = rows.duplicated([k for k in key if k in rows.columns], keep=False)
    if repeated.any():
        raise ValueError(
            f"{path} holds {int(repeated.sum())} rows of repeated episodes; it is not one sweep's"
        )
    names = {c: ConditionSpec.parse(c).name for c in rows["condition"].unique()}
    selected = rows[
        (rows["checkpoint_hash"] == checkpoint_hash)
        & (rows["task"] == task)
        & (rows["condition"].map(names) == condition)
    ]
    if "prompt" in rows.columns:
        selected = selected[selected["prompt"] == "target"]
    if selected.empty:
        return empty, (
            f"the sweep in {sweep_dir} has no {task} / {condition} episodes of checkpoint {checkpoint_hash}; "
            f"it holds hashes {sorted(rows['checkpoint_hash'].unique())[:8]}"
        )
    lifted = selected["lift"].astype(bool)
    k, n = int((selected["place"].astype(bool) & lifted).sum()), int(lifted.sum())
    if n == 0:
        return {
            "value": None,
            "k": 0,
            "n": 0,
        }, f"no sweep episode of this checkpoint reached lift under {condition}"
    return {"value": 100.0 * k / n, "k": k, "n": n}, None


# ---------------------------------------------------------------------------------------------- matched pairs
def check_matched(reference_env, distractor_env, seed: int) -> None:
    """The targets must start at the same poses in both envs under one seed."""
    a, b = reference_env.layout, distractor_env.layout
    for name, label, ea, eb in (
        ("target object", 1, a.target_object, b.target_object),
        ("target receptacle", 2, a.target_receptacle, b.target_receptacle),
    ):
        same_layout = ea.asset == eb.asset and ea.xy == eb.xy and ea.yaw == eb.yaw
        pa, qa = reference_env.entity_pose(label)
        pb, qb = distractor_env.entity_pose(label)
        if not same_layout or not (np.allclose(pa, pb, atol=1e-6) and np.allclose(qa, qb, atol=1e-6)):
            raise ValueError(
                f"Seed {seed}: the {name} starts at different poses in {reference_env.condition.name} "
                f"({ea.asset} at {np.round(pa, 4)}) and {distractor_env.condition.name} ({eb.asset} at {np.round(pb, 4)}); "
                "matched pairs need the same targets (same task and counterbalancing)"
            )


def container_side(env) -> int:
    """0: the target receptacle is left of the table centre in the top camera image (y < 0), 1: right."""
    return int(env.layout.target_receptacle.xy[1] >= 0)


class _Collector:
    """Buffers matched frames and runs them through the policy in batches."""

    def __init__(self, loaded, probe: ACTProbe, batch_size: int):
        self.loaded, self.probe, self.batch_size = loaded, probe, batch_size
        self.buffer: list[tuple] = []
        self.activations = {layer: {"reference": [], "distractor": []} for layer in LAYERS}

    def add(self, reference_obs, distractor_obs, reference_env, distractor_env) -> None:
        self.buffer.append((reference_obs, distractor_obs, reference_env, distractor_env))
        if len(self.buffer) >= self.batch_size:
            self.flush()

    def flush(self) -> None:
        if not self.buffer:
            return
        import torch

        from lerobot_condground.evaluation.rollout import policy_batch

        n = len(self.buffer)
        observations = [b[0] for b in self.buffer] + [b[1] for b in self.buffer]
        envs = [b[2] for b in self.buffer] + [b[3] for b in self.buffer]
        with torch.inference_mode():
            batch = policy_batch(self.loaded, observations, envs)
            self.probe.forward(self.loaded.policy, batch)
            captured = self.probe.activations()
        for layer, values in captured.items():
            self.activations[layer]["reference"].append(values[:n])
            self.activations[layer]["distractor"].append(values[n:])
        self.buffer = []

    def arrays(self) -> dict[str, np.ndarray]:
        return {
            f"{layer}_{cond}": np.concatenate(parts[cond]).astype(np.float32)
            for layer, parts in self.activations.items()
            for cond in ("reference", "distractor")
        }


def collect_matched(
    loaded,
    reference_spec,
    distractor_spec,
    seeds: list[int],
    stride: int,
    batch_size: int,
    progress: bool = True,
    on_frame=None,
) -> dict:
    """Runs the matched pairs and returns activations and per-frame metadata as numpy arrays.
    on_frame(reference_obs, distractor_obs, reference_env, distractor_env) sees every kept frame."""
    from tqdm import tqdm

    from lerobot_condground.envs.expert import ScriptedExpert

    reference_env, distractor_env = reference_spec.make(), distractor_spec.make()
    expert = ScriptedExpert()
    meta = {
        key: []
        for key in (
            "pair",
            "seed",
            "step",
            "phase",
            "side",
            "state_reference",
            "state_distractor",
            "image_difference",
        )
    }
    expert_success, steps_run = [], []
    try:
        with ACTProbe(acting_model(loaded.policy)) as probe:
            collector = _Collector(loaded, probe, batch_size)
            for pair, seed in enumerate(tqdm(seeds, desc="matched pairs", unit="pair", disable=not progress)):
                obs_ref, _ = reference_env.reset(seed=int(seed))
                obs_dis, _ = distractor_env.reset(seed=int(seed))
                check_matched(reference_env, distractor_env, seed)
                expert.reset(reference_env)
                side = container_side(reference_env)
                info_ref = {}
                step = 0
                for step in range(reference_spec.episode_length):
                    action = expert.act()
                    if step % stride == 0:
                        collector.add(obs_ref, obs_dis, reference_env, distractor_env)
                        if on_frame is not None:
                            on_frame(obs_ref, obs_dis, reference_env, distractor_env)
                        meta["pair"].append(pair)
                        meta["seed"].append(seed)
                        meta["step"].append(step)
                        meta["phase"].append(expert.phase_label)  # as recorded datasets label the frame
                        meta["side"].append(side)
                        meta["state_reference"].append(obs_ref["agent_pos"])
                        meta["state_distractor"].append(obs_dis["agent_pos"])
                        frames = [(obs_ref["pixels"][c], obs_dis["pixels"][c]) for c in obs_ref["pixels"]]
                        meta["image_difference"].append(
                            float(np.mean([np.abs(a.astype(np.int16) - b).mean() for a, b in frames]))
                        )
                    obs_ref, _, term_ref, trunc_ref, info_ref = reference_env.step(action)
                    obs_dis, _, term_dis, trunc_dis, _ = distractor_env.step(action)
                    if term_ref or trunc_ref or term_dis or trunc_dis:
                        break
                collector.flush()  # batches hold one pair: act_modified encodes its prompt crops once per pair
                expert_success.append(bool(info_ref.get("place", False)))
                steps_run.append(step + 1)
            arrays = collector.arrays()
    finally:
        reference_env.close()
        distractor_env.close()
    arrays.update({key: np.asarray(values) for key, values in meta.items()})
    arrays["expert_success"] = np.asarray(expert_success)
    arrays["episode_steps"] = np.asarray(steps_run)
    return arrays


# ---------------------------------------------------------------------------------------------- figures
def tsne_figures(
    states_ref: np.ndarray,
    states_dis: np.ndarray,
    side: np.ndarray,
    out_dir: Path,
    perplexity: float,
    seed: int,
    title: str,
    names: tuple[str, str],
) -> tuple[dict, np.ndarray | None, str | None]:
    """Shared t-SNE of reference + distractor place-phase decoder states; two PNGs (by condition, by side)."""
    n = len(states_ref) + len(states_dis)
    if n < 4:
        return {}, None, f"t-SNE skipped: {n} place-phase states (need at least 4)"
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from sklearn.manifold import TSNE

    x = np.concatenate([states_ref, states_dis]).astype(np.float64)
    embedding = TSNE(
        n_components=2, perplexity=float(min(perplexity, n - 1)), random_state=seed, init="pca"
    ).fit_transform(x)
    condition = np.r_[np.zeros(len(states_ref), int), np.ones(len(states_dis), int)]
    sides = np.r_[side, side]
    out_dir.mkdir(parents=True, exist_ok=True)
    figures = {}
    panels = (
        ("tsne_condition", "by condition", condition, names, ("tab:blue", "tab:red")),
        ("tsne_container", "by container side", sides, SIDES, ("tab:green", "tab:purple")),
    )
    for name, subtitle, labels, label_names, colors in panels:
        fig, ax = plt.subplots(figsize=(4.2, 4.0), dpi=120)
        for value, (label_name, color) in enumerate(zip(label_names, colors)):
            for marker, cond in (("o", 0), ("^", 1)):
                mask = (labels == value) & (condition == cond)
                if mask.any():
                    legend = label_name if name == "tsne_condition" else f"{label_name} ({names[cond]})"
                    ax.scatter(
                        *embedding[mask].T,
                        s=10,
                        c=color,
                        marker=marker,
                        alpha=0.7,
                        label=legend,
                        linewidths=0,
                    )
        ax.set_title(f"{title}\nplace-phase decoder states {subtitle}", fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
        ax.legend(fontsize=6, loc="best", frameon=False)
        fig.tight_layout()
        path = out_dir / f"{name}.png"
        fig.savefig(path)
        plt.close(fig)
        figures[name] = path
    return figures, embedding, None


# ---------------------------------------------------------------------------------------------- command
def format_diagnostics(result: dict) -> str:
    """A short text table: our layers, then Table II beside the paper's columns."""
    lines = [
        f"{result['policy_label']} ({result['checkpoint_hash']}), {result['task']}: {result['pairs']} pairs, "
        f"{result['frames']} matched frames ({result['reference_condition']} vs {result['distractor_condition']})"
    ]
    fmt = lambda v, pct=False: "   n/a" if v is None else (f"{v:6.1f}%" if pct else f"{v:7.4f}")  # noqa: E731
    lines.append(
        f"{'layer':<15} {'pick shift':>10} {'place shift':>11} {'phase retained':>15} {'silhouette':>11}"
    )
    for layer, m in result["layers"].items():
        lines.append(
            f"{layer:<15} {fmt(m['shift']['pick']):>10} {fmt(m['shift']['place']):>11} "
            f"{fmt(m['phase_retained'], True):>15} {fmt(m['container_silhouette']):>11}"
        )
    cols = list(result["paper"]["columns"])
    lines.append("")
    lines.append(f"{'Table II (decoder)':<26} {'ours':>8} " + " ".join(f"{c:>9}" for c in cols))
    for key, pct in (
        ("place_shift", False),
        ("phase_retained", True),
        ("container_silhouette", False),
        ("conditional_placement", True),
    ):
        paper = " ".join(f"{fmt(result['paper']['columns'][c][key], pct):>9}" for c in cols)
        lines.append(f"{key:<26} {fmt(result['table2'][key], pct):>8} {paper}")
    for note in result.get("notes", []):
        lines.append(f"note: {note}")
    return "\n".join(lines)


def run_diagnose(cfg: DiagnoseConfig) -> Path:
    """Matched-pair activations of one ACT-family checkpoint -> DIR/diagnostics.json (+ figures, npz)."""
    opts = cfg.diagnose
    if opts.pairs < 1:
        raise ValueError(f"--diagnose.pairs={opts.pairs} must be at least 1")
    check_seed("--diagnose.seed", opts.seed, opts.pairs)
    if not 0 <= opts.tsne_seed < 2**32:  # scikit-learn's random_state range
        raise ValueError(f"--diagnose.tsne_seed={opts.tsne_seed} is not allowed; allowed: 0 to {2**32 - 1}")
    if opts.frame_stride < 1:
        raise ValueError(f"--diagnose.frame_stride={opts.frame_stride} must be at least 1")
    if opts.batch_size < 1:
        raise ValueError(f"--diagnose.batch_size={opts.batch_size} must be at least 1")
    if not opts.tsne_perplexity > 0:
        raise ValueError(f"--diagnose.tsne_perplexity={opts.tsne_perplexity} must be positive")
    reference_condition = check_condition(cfg.env.condition or "clean", "--env.condition")
    distractor_condition = check_condition(opts.distractor_condition, "--diagnose.distractor_condition")
    if reference_condition == distractor_condition:
        raise ValueError(
            f"--diagnose.distractor_condition={opts.distractor_condition!r} equals the reference "
            f"--env.condition={cfg.env.condition!r}; matched pairs need two different conditions"
        )
    loaded, reference_spec = load_act_family(cfg.policy, cfg.env)
    distractor_spec = replace(reference_spec, condition=distractor_condition)
    from lerobot_condground.core.conditions import ConditionSpec
    from lerobot_condground.envs.layout import check_fits

    check_fits(
        distractor_spec.task, ConditionSpec.parse(distractor_condition), distractor_spec.counterbalanced
    )
    out = Path(cfg.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    # An earlier run's JSON would describe this run's figures if it stopped before writing its own.
    (out / "diagnostics.json").unlink(missing_ok=True)
    seeds = [opts.seed + i for i in range(opts.pairs)]
    logger.info(
        "diagnose %s (%s): %d matched pairs %s / %s on %s",
        loaded.label,
        loaded.hash,
        len(seeds),
        reference_condition,
        distractor_condition,
        reference_spec.task,
    )
    data = collect_matched(
        loaded, reference_spec, distractor_spec, seeds, opts.frame_stride, opts.batch_size, cfg.progress
    )

    phase, side = data["phase"], data["side"]
    layers = {
        layer: layer_metrics(data[f"{layer}_reference"], data[f"{layer}_distractor"], phase, side)
        for layer in LAYERS
    }
    notes = []
    state_gap = float(np.abs(data["state_reference"] - data["state_distractor"]).max()) if len(phase) else 0.0
    if state_gap > 1e-6:
        notes.append(
            f"matched robot states differ by up to {state_gap:.2e} (a competitor touched the robot): "
            "those frames differ by more than the competitors"
        )
    for name, i in zip(PHASES, (0, 1)):
        if not (phase == i).any():
            notes.append(f"no {name}-phase frame: its shift and the phase retention are undefined")
    if len(np.unique(side[phase == 1])) < 2:
        notes.append(
            f"the target receptacle stands on one side only ({', '.join(SIDES[s] for s in np.unique(side))}) "
            "in the place-phase frames: the container silhouette is undefined (Task 1's receptacle is fixed)"
        )
    if data["expert_success"].sum() < len(seeds):
        failed = [int(s) for s, ok in zip(seeds, data["expert_success"]) if not ok]
        notes.append(f"the scripted expert did not place in pairs with seeds {failed}; their frames are kept")
    placement, note = conditional_placement(
        cfg.sweep_dir, loaded.hash, reference_spec.task, distractor_condition
    )
    if note:
        notes.append(note)
    decoder = layers["decoder"]
    table2 = {
        "place_shift": decoder["shift"]["place"],
        "phase_retained": decoder["phase_retained"],
        "container_silhouette": decoder["container_silhouette"],
        "conditional_placement": placement["value"],
    }

    place = phase == 1
    figure_paths, embedding, note = tsne_figures(
        data["decoder_reference"][place],
        data["decoder_distractor"][place],
        side[place],
        out / "figures",
        opts.tsne_perplexity,
        opts.tsne_seed,
        f"{loaded.label} ({reference_spec.task})",
        (reference_condition, distractor_condition),
    )
    if note:
        notes.append(note)
    if embedding is not None:
        data["tsne_place_decoder"] = embedding.astype(np.float32)
    np.savez_compressed(out / "activations.npz", **data)

    result = {
        "kind": "diagnose",
        "policy_label": loaded.label,
        "checkpoint": loaded.path,
        "checkpoint_hash": loaded.hash,
        "policy_type": loaded.policy_type,
        "variant": loaded.variant,
        "training_seed": loaded.training_seed,
        "task": reference_spec.task,
        "reference_condition": reference_condition,
        "distractor_condition": distractor_condition,
        "counterbalanced": reference_spec.counterbalanced,
        "servo": reference_spec.servo,
        "observation_height": reference_spec.observation_height,
        "observation_width": reference_spec.observation_width,
        "pairs": len(seeds),
        "pair_seeds": seeds,
        "frame_stride": opts.frame_stride,
        "frames": int(len(phase)),
        "frames_per_phase": {name: int((phase == i).sum()) for i, name in enumerate(PHASES)},
        "frames_per_side": {name: int((side == i).sum()) for i, name in enumerate(SIDES)},
        "expert_success": int(data["expert_success"].sum()),
        "max_state_difference": state_gap,
        "mean_image_difference": float(np.mean(data["image_difference"])) if len(phase) else None,
        "container_side": f"sign of the target receptacle's {SIDE_AXIS}: left (< 0) / right (>= 0) in the top camera image",
        "layers": layers,
        "table2": table2,
        "table2_units": paper.TABLE2_UNITS,
        "conditional_placement": {**placement, "condition": distractor_condition, "sweep_dir": cfg.sweep_dir},
        "paper": {
            "source": "Table II: Task 2 decoder-state diagnostics",
            "columns": paper.TABLE2,
            "column": paper.TABLE2_COLUMN.get(loaded.label),
        },
        "figures": {name: str(path.relative_to(out)) for name, path in figure_paths.items()},
        "activations": "activations.npz",
        "notes": notes,
        "command": command_line("diagnose", cfg),
        "versions": versions(),
    }
    (out / "diagnostics.json").write_text(
        json.dumps(result, indent=2, allow_nan=False, default=_json_default)
    )
    print(format_diagnostics(result))
    print(f"wrote {out / 'diagnostics.json'}")
    return out


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON serializable")
