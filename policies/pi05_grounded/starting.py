"""A starting checkpoint for `lerobot-train --policy.path=DIR`: a pi05 checkpoint (`lerobot/pi05_base`)
retyped as `pi05_grounded`, with the processors of its variant.

`lerobot-train --policy.path` rebuilds the processors saved beside the weights, not the policy type's
factory: starting straight from `pi05_base` would train without the cue, instruction and label steps, and
with the hard-coded PaliGemma tokenizer. DIR holds `config.json` (type `pi05_grounded`, the dataset's
features), a link to the source's `model.safetensors` (nothing is copied) and processor files that list the
plugin's steps and the configured tokenizer. A tokenizer given as a local directory is copied into DIR
(`tokenizer/`) and named there by its absolute path, as the stock tokenizer step loads it from any working
folder; `pi05_start.json` records where it came from. Names and shapes of the weights are checked against the
configuration on the meta device (no memory), so a mismatch is an error now, not after loading.
"""

from __future__ import annotations

import copy
import json
import os
import shutil
import tempfile
from pathlib import Path

import draccus
import torch
from safetensors import SafetensorError, safe_open

from lerobot_condground.core.trust import check_name, pinned_folder

from .configuration_pi05_grounded import PI05GroundedConfig
from .modeling_pi05_grounded import WEIGHTS, PI05GroundedPolicy, weights_file
from .processor_pi05_grounded import make_pi05_grounded_pre_post_processors

SOURCE_TYPES = ("pi05", "pi05_grounded")
TOKENIZER_DIR = "tokenizer"
START_FILE = "pi05_start.json"


def source_config(source: str, overrides: list[str]) -> PI05GroundedConfig:
    """The source checkpoint's configuration as `pi05_grounded`, with `--key=value` overrides on top."""
    from huggingface_hub.constants import CONFIG_NAME

    config_file = Path(source) / CONFIG_NAME
    if not config_file.is_file():
        raise FileNotFoundError(f"--policy.path={source}: {config_file} is missing")
    raw = json.loads(config_file.read_text())
    kind = raw.pop("type", None)
    if kind not in SOURCE_TYPES:
        raise ValueError(
            f"--policy.path={source} is a {kind!r} checkpoint; allowed: {', '.join(SOURCE_TYPES)} "
            "(e.g. lerobot/pi05_base)"
        )
    with tempfile.NamedTemporaryFile("w", suffix=".json") as f:
        json.dump(raw, f)
        f.flush()
        config = draccus.parse(PI05GroundedConfig, f.name, args=overrides)
    # PreTrainedConfig picks a device available here; the checkpoint keeps the source's (or the flag's).
    if not any(arg.startswith("--device=") for arg in overrides):
        config.device = raw.get("device")
    if "tokenizer_name" in raw and not any(arg.startswith("--tokenizer_name=") for arg in overrides):
        # The source names what the new checkpoint's tokenizer step will load: a hub id or a path in its folder.
        check_name(config_file.parent, raw["tokenizer_name"], f"{config_file}, field 'tokenizer_name',")
    return config


def take_dataset_features(config: PI05GroundedConfig, dataset_features: dict) -> None:
    """The dataset's cameras, state and action replace the source's (pi05_base names other cameras)."""
    from lerobot.configs.types import FeatureType
    from lerobot.utils.feature_utils import dataset_to_policy_features

    features = dataset_to_policy_features(dataset_features)
    config.output_features = {k: f for k, f in features.items() if f.type is FeatureType.ACTION}
    config.input_features = {k: f for k, f in features.items() if k not in config.output_features}
    config.label_keys = None
    config.validate_features()


def check_weights(config: PI05GroundedConfig, weights: Path) -> None:
    """Raises unless every tensor of `weights` loads strictly into a policy of `config`."""
    try:
        with safe_open(str(weights), "pt", device="cpu") as f:
            state = {k: torch.empty(f.get_slice(k).get_shape(), device="meta") for k in f.keys()}  # noqa: SIM118
    except (SafetensorError, OSError) as err:
        # A damaged or crafted header (e.g. a length of 2^62 bytes) is the file's fault: name it.
        raise ValueError(f"{weights} is not a readable safetensors file ({err})") from None
    on_meta = copy.deepcopy(config)
    on_meta.device = "meta"
    with torch.device("meta"):
        policy = PI05GroundedPolicy(on_meta)
    problem = policy.weights_mismatch(policy.prepared_state(state))
    if problem:
        raise ValueError(f"{weights} does not fit pi05_grounded with this configuration: {problem}")


def write_starting_checkpoint(
    source: str, overrides: list[str], dataset_meta, output_dir: Path
) -> PI05GroundedConfig:
    if output_dir.exists() and any(output_dir.iterdir()):
        raise FileExistsError(f"--output_dir={output_dir} exists and is not empty; allowed: a new directory")
    try:
        source = str(pinned_folder(source))  # one snapshot of a hub id: the config and weights of one commit
    except FileNotFoundError as err:
        raise FileNotFoundError(
            f"--policy.path: {err}; give a local checkpoint directory, or download it first where the hub is reachable"
        ) from None
    config = source_config(source, overrides)
    take_dataset_features(config, dataset_meta.features)
    weights = weights_file(source)
    check_weights(config, weights)
    # Built before anything is written: an unreachable tokenizer fails here.
    pre, post = make_pi05_grounded_pre_post_processors(config, dataset_stats=dataset_meta.stats)
    # A relative tokenizer path would load only from the folder the command ran in, an absolute one outside
    # the checkpoint is refused by condground's commands: the checkpoint carries its own copy.
    local_tokenizer = Path(config.tokenizer_name).expanduser()
    local_tokenizer = local_tokenizer.resolve() if local_tokenizer.is_dir() else None
    if local_tokenizer is not None:
        config.tokenizer_name = str(output_dir.resolve() / TOKENIZER_DIR)
        for step in pre.steps:
            if getattr(step, "tokenizer_name", None) is not None:
                step.tokenizer_name = config.tokenizer_name
    # Written beside the output and renamed when whole: a failed run leaves no half checkpoint in
    # --output_dir to block the rerun (a killed one at most a hidden `.NAME.*` folder beside it).
    output_dir.parent.mkdir(parents=True, exist_ok=True)
    partial = Path(tempfile.mkdtemp(prefix=f".{output_dir.name}.", dir=output_dir.parent))
    try:
        config.save_pretrained(partial)
        (partial / WEIGHTS).symlink_to(weights.resolve())
        if local_tokenizer is not None:
            shutil.copytree(local_tokenizer, partial / TOKENIZER_DIR)
        start = {"source": source, "tokenizer_source": str(local_tokenizer or config.tokenizer_name)}
        (partial / START_FILE).write_text(json.dumps(start, indent=1))
        pre.save_pretrained(partial)
        post.save_pretrained(partial)
        os.replace(partial, output_dir)  # onto nothing, or onto the empty folder checked above
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    return config
