"""Shared test helpers: console scripts in subprocesses, JSON files, small checkpoints."""

import json
import os
import subprocess
import sys
from pathlib import Path

BIN = Path(sys.executable).parent


def run_cli(
    *args: str, cwd: Path | None = None, timeout: float = 600, check: bool = True
) -> subprocess.CompletedProcess:
    """Runs an installed console script (condground, lerobot-eval, ...) in a subprocess."""
    env = {**os.environ, "MUJOCO_GL": "egl", "HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled"}
    proc = subprocess.run(
        [str(BIN / args[0]), *args[1:]], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
    )
    if check and proc.returncode != 0:
        raise AssertionError(
            f"{' '.join(args)} failed ({proc.returncode}):\n{proc.stdout[-4000:]}\n{proc.stderr[-6000:]}"
        )
    return proc


def read_json(path: Path) -> dict:
    return json.loads(Path(path).read_text())


def make_checkpoint(
    path: Path,
    variant: str = "full",
    height: int = 96,
    width: int = 128,
    seed: int = 0,
    policy_type: str = "act_modified",
    cameras: tuple[str, ...] = ("top",),
    phase_predictor: bool | None = None,
) -> Path:
    """A small act_modified (or, with policy_type="act", stock ACT) checkpoint with random weights, saved
    the way lerobot-train saves one (config, weights, processors): what the diagnosis commands load.
    It has not learned anything. Stock ACT reads `cameras` (the routing env renders top and wrist);
    `phase_predictor` overrides the variant's (True: the paper's `full`, whose predictor picks the prompt)."""
    import torch
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.factory import make_pre_post_processors

    from lerobot_condground.core.labels import (
        OBS_PHASE,
        OBS_PROMPT_OBJECT,
        OBS_PROMPT_RECEPTACLE,
        OBS_SEGMENTATION,
    )
    from lerobot_condground.policies.act_modified.configuration_act_modified import ACTModifiedConfig
    from lerobot_condground.policies.act_modified.modeling_act_modified import ACTModifiedPolicy

    torch.manual_seed(seed)
    images = {
        f"observation.images.{c}": PolicyFeature(FeatureType.VISUAL, (3, height, width)) for c in cameras
    }
    features = {
        **images,
        "observation.state": PolicyFeature(FeatureType.STATE, (7,)),
        OBS_SEGMENTATION: PolicyFeature(FeatureType.STATE, (height, width)),
        OBS_PHASE: PolicyFeature(FeatureType.STATE, (1,)),
        OBS_PROMPT_OBJECT: PolicyFeature(FeatureType.STATE, (64, 64, 3)),
        OBS_PROMPT_RECEPTACLE: PolicyFeature(FeatureType.STATE, (64, 64, 3)),
    }
    small = dict(
        output_features={"action": PolicyFeature(FeatureType.ACTION, (7,))},
        dim_model=32,
        n_heads=4,
        dim_feedforward=64,
        n_encoder_layers=1,
        n_vae_encoder_layers=1,
        chunk_size=10,
        n_action_steps=10,
        pretrained_backbone_weights=None,
        device="cpu",
    )
    if policy_type == "act":
        from lerobot.policies.act.configuration_act import ACTConfig
        from lerobot.policies.act.modeling_act import ACTPolicy

        cameras_and_state = {k: features[k] for k in (*images, "observation.state")}
        policy = ACTPolicy(ACTConfig(input_features=cameras_and_state, **small))
    else:
        cfg = ACTModifiedConfig(
            variant=variant, use_phase_predictor=phase_predictor, input_features=features, **small
        )
        policy = ACTModifiedPolicy(cfg)
    stats = {
        **{k: {"mean": torch.full((3, 1, 1), 0.45), "std": torch.full((3, 1, 1), 0.25)} for k in images},
        "observation.state": {"mean": torch.zeros(7), "std": torch.ones(7)},
        "action": {
            "mean": torch.tensor([0.0, -1.2, 1.3, -1.6, -1.57, 0.0, 0.3]),
            "std": torch.full((7,), 0.3),
        },
    }
    preprocessor, postprocessor = make_pre_post_processors(policy.config, dataset_stats=stats)
    path.mkdir(parents=True, exist_ok=True)
    for part in (policy, preprocessor, postprocessor):
        part.save_pretrained(path)
    (path / "train_config.json").write_text(json.dumps({"seed": seed}))
    return path


def garbage_checkpoints(source: Path, root: Path) -> dict[Path, str]:
    """Copies of a checkpoint damaged as a bad copy or a hand edit leaves them, with the line each must give."""
    import shutil

    cases = {}
    for name, edit, message in (
        ("model.safetensors", lambda b: b[: len(b) // 2], "model.safetensors is damaged or incomplete"),
        ("config.json", lambda b: b"{not json", "config.json is not valid JSON"),
        (
            "policy_preprocessor.json",
            lambda b: b'{"steps": 3}',
            "policy_preprocessor.json has no list of steps",
        ),
    ):
        ckpt = root / f"garbage_{name.split('.')[0]}"
        shutil.copytree(source, ckpt)
        (ckpt / name).write_bytes(edit((ckpt / name).read_bytes()))
        cases[ckpt] = message
    return cases
