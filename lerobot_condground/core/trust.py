"""The trust gate: what a checkpoint's processor files may make our commands load.

LeRobot rebuilds a checkpoint's pipelines from `policy_preprocessor.json` / `policy_postprocessor.json`:
it imports the class a step names and calls it with the file's arguments, and some registered steps then
load further code, models or tokenizers named in those arguments (LeRobot's tokenizer steps pass
`trust_remote_code=True` to transformers by default). A registered name is therefore not a safe step.
Every step registered by LeRobot 0.6.1 and by this plugin was reviewed; the decision is one of:

- DATA_STEPS: the step's arguments are numbers, flags, key names and tensors; any value is safe.
- LOADING_STEPS: the step loads what the listed fields name, through a loader that runs no shipped
  code unless a field asks for it. A name is a hub id, or a path inside the checkpoint's folder; a field
  that turns remote code on is refused.
- REFUSED_STEPS: the step loads a model or code in a way no value makes safe, or never belongs in a policy
  checkpoint.

Anything else (another plugin's step, a step a later LeRobot adds, a class path) was not reviewed and is
refused. `--policy.trust_remote_code=true` skips the gate for a checkpoint the user trusts. Whatever the
decision, every `state_file` must be a file inside the checkpoint's folder.
"""

from __future__ import annotations

import functools
import os
import re
from pathlib import Path

DATA_STEPS = frozenset(
    {
        # LeRobot's generic steps.
        "absolute_actions_processor", "relative_actions_processor", "device_processor", "normalizer_processor",
        "unnormalizer_processor", "rename_observations_processor", "to_batch_processor",
        "to_batch_processor_action", "to_batch_processor_observation", "to_batch_processor_complementary_data",
        "observation_processor", "numpy2torch_action_processor", "torch2numpy_action_processor",
        "policy_action_to_robot_action_processor", "robot_action_to_policy_action_processor",
        "map_delta_action_to_robot_action", "map_tensor_to_delta_action_dict", "libero_processor",
        "isaaclab_arena_processor",
        # LeRobot's policies' steps that only reshape, pad, clip or template.
        "pi05_prepare_state_tokenizer_processor_step", "pi0_fast_prepare_state_tokenizer_processor_step",
        "pi0_new_line_processor", "smolvla_new_line_processor", "eo1_conversation_template_processor",
        "evo1_action_processor", "evo1_pad_action_processor", "evo1_pad_state_processor",
        "fastwam_action_toggle_processor", "groot_action_unpack_unnormalize_v2", "groot_n1_7_action_decode_v1",
        "groot_n1_7_pack_inputs_v1", "molmoact2_action_frame_transform", "molmoact2_clamp_action",
        "molmoact2_clamp_normalized", "molmoact2_masked_normalizer", "molmoact2_masked_unnormalizer",
        "molmoact2_state_frame_transform", "vla_jepa_binarize_gripper", "vla_jepa_clip_actions",
        "vla_jepa_pre_snap_gripper", "wall_x_task_processor", "xvla_add_domain_id", "xvla_image_scale",
        "xvla_image_to_float", "xvla_imagenet_normalize", "xvla_rotation_6d_to_axis_angle",
        # This plugin's.
        "condground_copy_paste", "condground_decode_labels", "condground_instruction", "condground_rgb_cue",
    }
)  # fmt: skip

# Step -> (fields naming what it loads, fields that must be false: they switch remote code on when true,
# with their default when the file leaves them out).
LOADING_STEPS: dict[str, tuple[tuple[str, ...], dict[str, bool]]] = {
    # transformers' AutoTokenizer with its default: shipped code is refused by transformers itself.
    "tokenizer_processor": (("tokenizer_name",), {}),
    # AutoProcessor / AutoTokenizer with the step's own trust_remote_code, True unless the file says false.
    "action_tokenizer_processor": (
        ("action_tokenizer_name", "paligemma_tokenizer_name"),
        {"trust_remote_code": True},
    ),
    # Qwen2_5_VLProcessor by its own class: no auto_map, no shipped code.
    "eo1_qwen_processor": (("processor_name",), {}),
}

HIL_STEPS = (
    "add_teleop_action_as_complementary_data", "add_teleop_action_as_info", "gripper_penalty_processor",
    "gym_hil_adapter_processor", "image_crop_resize_processor", "intervention_action_processor",
    "time_limit_processor",
)  # fmt: skip
REFUSED_STEPS = {
    "groot_n1_7_vlm_encode_v1": "loads its model_name's tokenizer and processors with trust_remote_code=True",
    "molmoact2_pack_inputs": "loads a processor and an action tokenizer from its checkpoint_path",
    "reward_classifier_processor": "loads a whole reward model from its pretrained_path",
    **dict.fromkeys(
        HIL_STEPS, "is an environment-side human-in-the-loop step, never part of a policy checkpoint"
    ),
}

# Policy types whose construction from a checkpoint's config.json loads nothing the config names beyond
# torchvision's own weights (reviewed in LeRobot 0.6.1 and this plugin). Others load models, tokenizers or
# remote code by a name in the config as they are built (pi0_fast's action tokenizer, gaussian_actor's vision
# encoder and wall_x's tokenizer with trust_remote_code=True; groot's base model; smolvla's VLM).
REVIEWED_POLICY_TYPES = frozenset(
    {"act", "act_modified", "diffusion", "vqbet", "tdmpc", "pi0", "pi05", "pi05_grounded"}
)


def check_policy_type(config_file: Path, policy_type: str) -> None:
    if policy_type not in REVIEWED_POLICY_TYPES:
        raise PermissionError(
            f"Policy config {config_file} names policy type {policy_type!r}, which is not reviewed as safe to build "
            f"from an untrusted checkpoint (building it may load code or models its config names; reviewed: "
            f"{', '.join(sorted(REVIEWED_POLICY_TYPES))}); {OPT_IN}"
        )


HUB_ID = re.compile(r"[A-Za-z0-9][\w.-]*/[\w.-]+")
OPT_IN = "pass --policy.trust_remote_code=true if you trust this checkpoint's author"


@functools.cache
def pinned_folder(source: str) -> Path:
    """A checkpoint's folder: a local directory, or a hub id's snapshot at one commit, resolved once per
    process so that the files checked are the files loaded (a push between two downloads would otherwise
    load unchecked files). Hand this folder, not the id, to worker processes."""
    local = Path(source)
    if local.is_dir():
        return local
    from huggingface_hub import snapshot_download

    try:
        snapshot = Path(snapshot_download(source))
    except Exception as err:  # invalid id, not cached while offline, no such repo, network
        raise FileNotFoundError(
            f"{source!r} is not a checkpoint directory and cannot be fetched as a hub id "
            f"({type(err).__name__}: {str(err).splitlines()[0]})"
        ) from None
    # huggingface_hub links a snapshot's files to its repo's blobs; a cache edited to link elsewhere is refused.
    for path in snapshot.rglob("*"):
        if not within(snapshot, path.relative_to(snapshot)):
            raise PermissionError(
                f"{path} (in the hub cache's snapshot of {source!r}) links outside the repo's blobs "
                f"to {path.resolve()}; the cache was edited: remove {snapshot.parent.parent} and download again"
            )
    return snapshot


def _hub_snapshot(root: Path) -> bool:
    """A snapshot in huggingface_hub's cache: its files link to the repo's blobs two levels up, by design."""
    return root.parent.name == "snapshots" and root.parent.parent.name.startswith("models--")


def within(root: Path, path: Path) -> bool:
    """`path` (relative to `root`, or absolute) names something inside `root`, also once links are followed."""
    base = Path(os.path.normpath(root.absolute()))
    target = Path(os.path.normpath(base / path))
    if not target.is_relative_to(base):
        return False
    resolved = target.resolve()
    # A hub snapshot's files link into its repo's blobs; nothing may link anywhere else.
    if _hub_snapshot(base):
        return resolved.is_relative_to(base.resolve()) or resolved.is_relative_to(
            (base.parent.parent / "blobs").resolve()
        )
    return resolved.is_relative_to(base.resolve())


def inside(root: Path, value: str) -> bool:
    return not Path(value).is_absolute() and within(root, Path(value))


def check_name(root: Path, value, where: str) -> None:
    """A hub id (loaded by a loader that runs no shipped code), or a path inside the checkpoint's folder."""
    if not isinstance(value, str) or not value:
        raise PermissionError(f"{where} is {value!r}; allowed: a hub id or a path inside {root}")
    local = Path(value).expanduser()
    looks_local = (
        local.exists() or value.startswith(("/", ".", "~")) or "\\" in value or not HUB_ID.fullmatch(value)
    )
    if looks_local and not within(root, local.absolute()):
        raise PermissionError(
            f"{where} is {value!r}, a path outside the checkpoint's folder {root}; allowed: a hub id or a path "
            f"inside it (copy what it names into the checkpoint), or {OPT_IN}"
        )


def check_step(file: Path, index: int, step: dict, name: str) -> None:
    """Raises PermissionError naming the file, the step and the field if `step` may not load untrusted."""
    where = f"Processor file {file}, step {index} ({name})"
    if name in DATA_STEPS:
        return
    if name in REFUSED_STEPS:
        raise PermissionError(f"{where} is refused: it {REFUSED_STEPS[name]}; {OPT_IN}")
    if name not in LOADING_STEPS:
        raise PermissionError(
            f"{where} is not a step reviewed as safe to load from an untrusted checkpoint (its arguments may "
            f"make it load code); {OPT_IN}"
        )
    names, must_be_false = LOADING_STEPS[name]
    config = step.get("config") or {}
    if not isinstance(config, dict):
        raise PermissionError(f"{where} has a config that is not an object: {config!r}")
    for field, default in must_be_false.items():
        if config.get(field, default) is not False:
            raise PermissionError(
                f"{where} sets {field}={config.get(field, default)!r} (the default when left out): it would "
                f"run code shipped with the model it loads; allowed: false, or {OPT_IN}"
            )
    for field in names:
        if config.get(field) is not None:
            check_name(file.parent, config[field], f"{where}, field {field!r},")


def check_state_file(file: Path, index: int, step: dict) -> None:
    state_file = step.get("state_file")
    if state_file is not None and not (isinstance(state_file, str) and inside(file.parent, state_file)):
        raise PermissionError(
            f"Processor file {file}, step {index}: state_file {state_file!r} is not a file inside the checkpoint's folder "
            f"{file.parent}; allowed: a relative path to a file in that folder (no '..', no link out of it)"
        )


def check_dataset_paths(root: Path) -> None:
    """Raises PermissionError unless every file path template in the dataset's meta/info.json (`data_path`,
    `video_path`, ...), filled in for each of its video features, names a file inside `root`.

    LeRobot joins the templates to the root as written: an absolute template, `..`, or a feature name with
    a slash would move a recording's writes, or augment's reads, anywhere on the disk."""
    import string

    from lerobot_condground.core.files import read_json_object

    info_file = root / "meta" / "info.json"
    if not info_file.is_file():
        return
    if not within(root, Path("meta/info.json")):
        raise PermissionError(
            f"{info_file} links outside the dataset's root {root}; allowed: a file inside it"
        )
    info = read_json_object(info_file, "Dataset info")
    features = info.get("features") if isinstance(info.get("features"), dict) else {}
    video_keys = [k for k, ft in features.items() if isinstance(ft, dict) and ft.get("dtype") == "video"]
    for field, template in info.items():
        if not field.endswith("_path") or template is None:
            continue
        if not isinstance(template, str):
            raise PermissionError(f"{info_file}: {field} is {template!r}; allowed: a relative path template")
        fields = [(name, spec) for _, name, spec, _ in string.Formatter().parse(template) if name]
        names = {name for name, _ in fields}
        # Chunk and file indices come from meta/episodes: formatted as integers, a string there cannot name
        # a path (LeRobot's own templates all read `{chunk_index:03d}`).
        loose = [name for name, spec in fields if name != "video_key" and not (spec or "").endswith("d")]
        if loose:
            raise PermissionError(
                f"{info_file}: {field} {template!r} formats {loose[0]!r} without an integer format; allowed: "
                f"{{{loose[0]}:03d}} as LeRobot writes it"
            )
        for key in video_keys if "video_key" in names else [None]:
            try:
                path = template.format(**dict.fromkeys(names - {"video_key"}, 0), video_key=key)
            except (ValueError, IndexError, KeyError, AttributeError) as err:
                raise PermissionError(
                    f"{info_file}: {field} {template!r} is not a path template ({err})"
                ) from None
            if not inside(root, path):
                raise PermissionError(
                    f"{info_file}: {field} {template!r} names {path!r}, outside the dataset's root {root}"
                    + (f" (for feature {key!r})" if key else "")
                    + "; allowed: a relative path template whose files stay inside the root"
                )
