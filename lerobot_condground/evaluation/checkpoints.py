"""Loads a policy checkpoint the way `lerobot-eval` does, for the diagnosis commands.

Any policy LeRobot can load works (ours or stock, a local `pretrained_model` directory or a hub id,
offline from the cache with HF_HUB_OFFLINE=1). The pseudo path `expert` stands for the scripted
expert, the oracle every table can show beside the policies.
"""

from __future__ import annotations

import atexit
import dataclasses
import functools
import hashlib
import json
import os
import re
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lerobot_condground.core.files import parse_json_object
from lerobot_condground.core.trust import (
    OPT_IN,
    check_policy_type,
    check_state_file,
    check_step,
    pinned_folder,
    within,
)

EXPERT = "expert"
CAMERA_PREFIX = "observation.images."


@dataclass
class LoadedPolicy:
    path: str
    label: str
    policy_type: str
    variant: str
    hash: str
    training_seed: int | None
    read: CheckpointRead | None = None  # None for the expert
    cameras: dict[str, tuple[int, int]] = field(default_factory=dict)  # name -> (height, width)
    vectors: dict[str, tuple[int, ...]] = field(default_factory=dict)  # state and action shapes
    needs_prompts: bool = False
    trust_remote_code: bool = False  # the user allowed processor steps outside LeRobot's registry
    policy: Any = None
    preprocessor: Any = None
    postprocessor: Any = None
    env_preprocessor: Any = None
    env_postprocessor: Any = None

    @property
    def local(self) -> str:
        """The folder LeRobot's loaders read: the private copy of what was checked."""
        return str(self.read.copy) if self.read else ""

    @property
    def is_expert(self) -> bool:
        return self.policy_type == EXPERT

    def identity(self) -> dict:
        """The results table's columns that say which checkpoint ran (see `results.py`)."""
        return {
            "policy_label": self.label,
            "policy_type": self.policy_type,
            "variant": self.variant,
            "checkpoint": self.path,
            "checkpoint_hash": self.hash,
            "training_seed": self.training_seed,
        }

    def describe(self) -> dict:
        return {
            "path": self.path,
            "hash": self.hash,
            "label": self.label,
            "policy_type": self.policy_type,
            "variant": self.variant,
            "training_seed": self.training_seed,
        }


def local_checkpoint(path: str) -> Path:
    """The folder a checkpoint's files are read from (trust.pinned_folder: a hub id's snapshot, once)."""
    try:
        return pinned_folder(path)
    except FileNotFoundError as err:
        raise FileNotFoundError(f"Policy path {err}; or use `{EXPERT}` for the scripted expert") from None


PROCESSOR_FILES = ("policy_preprocessor.json", "policy_postprocessor.json")
WEIGHTS = "model.safetensors"


@dataclass(frozen=True)
class CheckpointRead:
    """A checkpoint as read, every file once: what the trust checks judge, what the hash covers and what the
    loader builds. The loader reads `copy`, a private folder holding exactly the bytes read here (the weights
    copied as they were hashed), never the checkpoint's own folder, which may change after the checks."""

    source: str
    folder: Path  # where the files were read (a hub id's pinned snapshot)
    copy: Path
    config: dict
    # Every step of the processor pipelines: (file name, index in its file, step).
    steps: tuple[tuple[str, int, dict], ...]
    training_seed: int | None
    hash: str  # sha256 (16 hex digits) of config, weights, processor files and their state files


_COPIES: list[Path] = []


def _remove_copies(pid: int) -> None:
    if os.getpid() == pid:  # not in a forked child, whose parent may still load from them
        for copy in _COPIES:
            shutil.rmtree(copy, ignore_errors=True)


def private_copy() -> Path:
    """A folder of this process's own, removed when it exits."""
    if not _COPIES:
        atexit.register(_remove_copies, os.getpid())
    _COPIES.append(Path(tempfile.mkdtemp(prefix="condground-checkpoint-")))
    return _COPIES[-1]


def read_checkpoint(source: str) -> CheckpointRead:
    """Reads a checkpoint once: config, processor files, their state files (never from outside the folder),
    the training seed, and the weights, copied into a private folder while hashed and then checked whole.

    A changed normalization or processor step is a different checkpoint: the hash covers every file that
    decides behaviour, in the order config, weights, processor files, state files (sorted)."""
    folder = local_checkpoint(source)
    if not (folder / "config.json").is_file():
        raise FileNotFoundError(
            f"Policy path {source!r} is neither a checkpoint directory with config.json nor a cached hub id "
            f"(or `{EXPERT}` for the scripted expert)"
        )
    copy = private_copy()

    def take(name: str) -> bytes:
        if not within(folder, Path(name)):
            raise PermissionError(
                f"{folder / name} links outside the checkpoint's folder {folder}; allowed: a file inside it"
            )
        data = (folder / name).read_bytes()
        (copy / name).parent.mkdir(parents=True, exist_ok=True)
        (copy / name).write_bytes(data)
        return data

    digest = hashlib.sha256()

    def hashed(name: str, data: bytes) -> None:
        digest.update(name.encode() + b"\0" + data)

    config = take("config.json")
    parsed = parse_json_object(config, folder / "config.json", "Policy config")
    hashed("config.json", config)
    copy_weights(folder, copy, digest)
    steps, state_files = [], set()
    for name in PROCESSOR_FILES:
        if not (folder / name).is_file():
            continue
        data = take(name)
        listed = parse_json_object(data, folder / name, "Processor file").get("steps")
        if not isinstance(listed, list) or not all(isinstance(step, dict) for step in listed):
            raise ValueError(
                f"Processor file {folder / name} has no list of steps; the checkpoint is damaged"
            )
        hashed(name, data)
        for index, step in enumerate(listed):
            check_state_file(folder / name, index, step)
            if isinstance(step.get("state_file"), str):
                state_files.add(step["state_file"])
        steps += [(name, index, step) for index, step in enumerate(listed)]
    for name in sorted(state_files):
        if not (folder / name).is_file():
            raise FileNotFoundError(f"Checkpoint {source!r} has no {name}, which its processor files name")
        hashed(name, take(name))
    seed = None
    if (folder / "train_config.json").is_file():
        train = parse_json_object(take("train_config.json"), folder / "train_config.json", "Training config")
        seed = train.get("seed")
    return CheckpointRead(source, folder, copy, parsed, tuple(steps), seed, digest.hexdigest()[:16])


def copy_weights(folder: Path, copy: Path, digest) -> None:
    """The weights into the private folder, hashed as they stream; a truncated download or copy is refused
    here, not inside a worker."""
    from safetensors import SafetensorError, safe_open

    file = folder / WEIGHTS
    if not file.is_file():
        raise FileNotFoundError(f"Checkpoint {str(folder)!r} has no {WEIGHTS}")
    if not within(folder, Path(WEIGHTS)):
        raise PermissionError(
            f"{file} links outside the checkpoint's folder {folder}; allowed: a file inside it"
        )
    digest.update(WEIGHTS.encode() + b"\0")
    with open(file, "rb") as source, open(copy / WEIGHTS, "wb") as target:
        for block in iter(lambda: source.read(1 << 20), b""):
            digest.update(block)
            target.write(block)
    try:
        with safe_open(copy / WEIGHTS, "pt") as weights:
            weights.keys()
    except SafetensorError as err:
        raise ValueError(f"Weights file {file} is damaged or incomplete ({err})") from None


def check_processor_steps(read: CheckpointRead, trust_remote_code: bool) -> None:
    """Refuses a checkpoint whose pipelines would load code (trust.py); state files were kept inside its folder
    as it was read.

    LeRobot's loader imports whatever dotted path a step's "class" names and calls it with the file's
    arguments, and some registered steps load further code their arguments name: only steps reviewed as
    safe, with safe arguments, load unless the user opts in.
    """
    if trust_remote_code:
        return
    from lerobot.processor.pipeline import ProcessorStepRegistry

    register_plugins()
    registered = set(ProcessorStepRegistry.list())
    by_class = {
        f"{cls.__module__}.{cls.__name__}": name
        for name, cls in ((name, ProcessorStepRegistry.get(name)) for name in registered)
    }
    for file_name, index, step in read.steps:
        file = read.folder / file_name
        name = step.get("registry_name") if "registry_name" in step else by_class.get(step.get("class"))
        if not isinstance(name, str) or name not in registered:
            named = (
                f"registry name {step['registry_name']!r}"
                if "registry_name" in step
                else f"class {step.get('class')!r}"
            )
            raise PermissionError(
                f"Processor file {file}, step {index} names {named}, which is not a registered LeRobot processor "
                f"step: loading it would import and run code the checkpoint names. Install the plugin that "
                f"registers it, or {OPT_IN}"
            )
        check_step(file, index, step, name)


def checkpoint_hash(path: str) -> str:
    return read_checkpoint(path).hash


@functools.cache
def register_plugins() -> None:
    """A checkpoint names its policy type and processor steps by registry name: LeRobot imports the installed
    plugins (this one included) first, as its own scripts do."""
    from lerobot.utils.import_utils import register_third_party_plugins

    register_third_party_plugins()


def describe_checkpoint(
    path: str, label: str | None = None, index: int = 0, trust_remote_code: bool = False
) -> LoadedPolicy:
    """What a checkpoint is, without building it: type, variant, cameras, hash, training seed. Checks that
    building it would run only installed code (see check_processor_steps)."""
    register_plugins()
    if path == EXPERT:
        return LoadedPolicy(
            path=EXPERT,
            label=label or EXPERT,
            policy_type=EXPERT,
            variant="",
            hash=EXPERT,
            training_seed=index,
        )
    read = read_checkpoint(path)
    config_file, config = read.folder / "config.json", read.config
    policy_type = config.get("type", "")
    from lerobot.configs.policies import PreTrainedConfig

    known = sorted(PreTrainedConfig.get_known_choices())
    if policy_type not in known:
        raise ValueError(
            f"Policy config {config_file} names policy type {policy_type!r}, which no installed package "
            f"registers; known: {', '.join(known)}"
        )
    if not trust_remote_code:
        check_policy_type(config_file, policy_type)
    check_config_fields(config_file, config, policy_type, known)
    check_processor_steps(read, trust_remote_code)
    variant = config.get("variant", "") if policy_type == "act_modified" else ""
    cameras = {
        key[len(CAMERA_PREFIX) :]: tuple(feature["shape"][-2:])
        for key, feature in config.get("input_features", {}).items()
        if key.startswith(CAMERA_PREFIX) and feature.get("type") == "VISUAL"
    }
    vectors = {
        key: tuple(feature["shape"])
        for group in ("input_features", "output_features")
        for key, feature in config.get(group, {}).items()
        if key in ("observation.state", "action")
    }
    return LoadedPolicy(
        path=path,
        label=label or (f"{policy_type}/{variant}" if variant else policy_type),
        policy_type=policy_type,
        variant=variant,
        hash=read.hash,
        read=read,
        training_seed=read.training_seed if read.training_seed is not None else index,
        cameras=cameras,
        vectors=vectors,
        needs_prompts=bool(config.get("use_prompts")),
        trust_remote_code=trust_remote_code,
    )


def check_config_fields(config_file: Path, config: dict, policy_type: str, known: list[str]) -> None:
    """Every field of config.json must be one its type's config has: a `type` edited to another policy would
    otherwise fail in draccus with every foreign field listed and no file named."""
    from dataclasses import fields

    from lerobot.configs.policies import PreTrainedConfig

    def names(kind: str) -> set[str]:
        return {f.name for f in fields(PreTrainedConfig.get_choice_class(kind))}

    given = set(config) - {"type"}
    unknown = sorted(given - names(policy_type))
    if unknown:
        fits = [kind for kind in known if kind != policy_type and given <= names(kind)]
        raise ValueError(
            f"Policy config {config_file} names type {policy_type!r}, which has no field "
            f"{', '.join(unknown[:3])}{', ...' if len(unknown) > 3 else ''} ({len(unknown)} of its fields); "
            + (
                f"its fields are those of {' or '.join(fits)}"
                if fits
                else "allowed: the config its training wrote"
            )
        )


def check_env_fits(loaded: LoadedPolicy, env_cfg) -> None:
    """The checkpoint's cameras and sizes must be ones the env renders; one error naming what differs."""
    if loaded.is_expert:
        return
    from lerobot.envs.utils import env_to_policy_features

    env_features = env_to_policy_features(env_cfg)
    problems = []
    for name, size in loaded.cameras.items():
        feature = env_features.get(CAMERA_PREFIX + name)
        if feature is None:
            problems.append(f"camera {name!r} (env cameras: top, and wrist with --env.wrist_camera=true)")
        else:
            shape = tuple(feature.shape)
            rendered = shape[1:] if shape[0] == 3 else shape[:2]  # CHW or HWC
            if rendered != tuple(size):
                problems.append(
                    f"camera {name!r} at {size[0]}x{size[1]} (env renders {rendered[0]}x{rendered[1]})"
                )
    if not loaded.cameras:
        problems.append("no camera input at all")
    for key, shape in loaded.vectors.items():
        feature = env_features.get(key)
        if feature is None or tuple(feature.shape) != tuple(shape):
            problems.append(
                f"{key} of shape {tuple(shape)} (env: {tuple(feature.shape) if feature else 'none'})"
            )
    if problems:
        raise ValueError(
            f"Checkpoint {loaded.path!r} does not fit the env {env_cfg.task}: it expects "
            + "; ".join(problems)
        )


def resolve_device(device: str | None) -> str:
    """--policy.device as LeRobot resolves it: checked when given, else (or `auto`) the best one on this machine."""
    from lerobot.utils.device_utils import auto_select_torch_device, get_safe_torch_device

    if device in (None, "", "auto"):
        return str(auto_select_torch_device())
    try:
        return str(get_safe_torch_device(device))
    except RuntimeError as err:  # torch's own words for a string that names no device type
        raise ValueError(
            f"--policy.device={device!r} is not a device; allowed: auto, cpu, cuda, cuda:N, mps, xpu"
        ) from err


def load_policy(
    checkpoint: str | LoadedPolicy,
    env_cfg,
    device: str = "cpu",
    label: str | None = None,
    index: int = 0,
    trust_remote_code: bool = False,
) -> LoadedPolicy:
    """Builds the policy and its processors with LeRobot's own factories, as `lerobot-eval` does, from a
    checkpoint described here (a path) or already (what `describe_checkpoint` judged is what loads)."""
    if isinstance(checkpoint, LoadedPolicy):
        register_plugins()  # in a worker process, as describe_checkpoint does
        loaded = dataclasses.replace(checkpoint)
    else:
        loaded = describe_checkpoint(checkpoint, label, index, trust_remote_code)
    if loaded.is_expert:
        return loaded
    check_env_fits(loaded, env_cfg)
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.envs.factory import make_env_pre_post_processors
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    cfg = PreTrainedConfig.from_pretrained(loaded.local)
    cfg.pretrained_path = Path(loaded.local)
    cfg.device = device
    policy = make_policy(cfg=cfg, env_cfg=env_cfg)
    policy.eval()
    loaded.policy = policy
    try:
        loaded.preprocessor, loaded.postprocessor = make_pre_post_processors(
            policy_cfg=cfg,
            pretrained_path=loaded.local,
            preprocessor_overrides={"device_processor": {"device": device}},
        )
    except (ValueError, TypeError, KeyError) as err:
        # LeRobot names the step and its config but not the file: the files holding that step are named.
        named = ["".join(m) for m in re.findall(r"'([\w.]+)'|\(([\w.]+)\)", str(err))][:1]
        files = sorted(
            {name for name, _, step in loaded.read.steps if named and named[0] in json.dumps(step)}
        ) or list(PROCESSOR_FILES)
        raise ValueError(
            f"{' or '.join(str(loaded.read.folder / f) for f in files)} does not build: {' '.join(str(err).split())}"
        ) from None
    loaded.env_preprocessor, loaded.env_postprocessor = make_env_pre_post_processors(
        env_cfg=env_cfg, policy_cfg=cfg
    )
    return loaded
