"""`condground record`: scripted-expert demonstrations written to a LeRobotDataset (v3).

Per frame: camera frames, `observation.state`, `action`, the task string, and the label features of
`lerobot_condground.core.labels`: pick-and-place: phase, lossless segmentation, prompt crops;
InstrumentRouting-v0: the procedure step as phase, both cameras' segmentation, the destination side, and
the instruction of the subgoal in progress as the frame's task. Per episode, the provenance file
`meta/condground_record.json` keeps the seed and what each segmentation label is.

With `--drift.*` the arm is sent the expert's targets plus a smooth offset (DART); with `--takeover.*` a
trained policy drives each episode first and the expert finishes it from where the policy left the scene,
only the expert's frames recorded (DAgger). docs/recording.md says how both are made.

Only successful expert episodes are kept; a failed one is retried with the next seed and counted.
The dataset is closed after every `checkpoint_every` episodes, so a crash loses at most the episodes
since the last checkpoint (by default only the one in flight); rerunning resumes up to
`num_episodes` instead of overwriting.
"""

from __future__ import annotations

import fnmatch
import json
import logging
import os
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from lerobot_condground.core.conditions import ROUTING_TASK
from lerobot_condground.core.configs import (
    HELD_OUT_SEED_OFFSET,
    DatasetOutputConfig,
    check_at_least,
    check_seed,
)
from lerobot_condground.core.files import read_json_object
from lerobot_condground.core.labels import (
    OBS_DESTINATION,
    OBS_PHASE,
    OBS_PROMPT_OBJECT,
    OBS_PROMPT_RECEPTACLE,
    OBS_SEGMENTATION,
    OBS_SEGMENTATION_WRIST,
    PNG_FEATURE,
    encode_png,
)
from lerobot_condground.core.provenance import RECORD_FILE
from lerobot_condground.core.scheduling import kept_priority
from lerobot_condground.core.ur3e import MOTOR_NAMES, SERVO_BEFORE_THE_SETTING
from lerobot_condground.envs.configs import CondGroundEnvConfig

PROVENANCE_ENV_KEYS = (
    "task",
    "condition",
    "counterbalanced",
    "competitor_pool",
    "fps",
    "observation_height",
    "observation_width",
    "wrist_camera",
    "subgoal",
    "servo",
)
# What a provenance written before a setting existed recorded with.
PROVENANCE_ENV_BEFORE = {"servo": SERVO_BEFORE_THE_SETTING, "competitor_pool": "eval"}


@dataclass
class RecordDatasetConfig(DatasetOutputConfig):
    repo_id: str | None = "local/condground_pickplace"
    # Number of successful expert episodes the dataset should hold when done.
    num_episodes: int = 100
    # Encode camera frames as video (true) or store them as PNG images (false).
    video: bool = True
    # Write the label features act_modified and the diagnosis tools read (segmentation, phase, prompt
    # crops). Stock LeRobot policies other than ACT-as-`act_modified --policy.variant=standard` cannot
    # read string features: record with --dataset.labels=false for them.
    labels: bool = True
    # Close and reopen the dataset after this many episodes: a crash loses at most these.
    checkpoint_every: int = 1


@dataclass
class DriftConfig:
    # Recovery data (DART): rad of smooth random offset added to each arm joint's target the arm is sent,
    # while the frames keep the expert's target as the action (`envs.expert.JointDrift`). 0: clean
    # demonstrations. At 0.06 the tool moves 2.6-4 cm off the expert's path while the arm travels, and is
    # brought back before the gripper closes or opens (docs/recording.md).
    std: float = 0.0
    # Seconds over which the offset stays correlated: long enough for the arm to follow it off the path.
    time_constant: float = 0.5


@dataclass
class TakeoverConfig:
    # Recovery data from the states a policy reaches (DAgger by expert takeover, as in HG-DAgger): this
    # checkpoint drives each episode for a number of steps, then the scripted expert takes over from the
    # state it left and finishes the task (`envs.expert.ScriptedExpert.take_over`). Only the expert's frames
    # are recorded. None: the expert from the first step.
    policy_path: str | None = None
    # The policy's steps before the takeover, drawn uniformly per episode from the episode's seed.
    min_steps: int = 0
    max_steps: int = 150
    device: str = "cpu"
    # The checkpoint's processor files may name classes outside LeRobot's registry; they load only if true.
    trust_remote_code: bool = False


# Far beyond any study here, well below what fills a disk unnoticed.
MAX_EPISODES = 100_000
# At 0.10 the expert already fails one episode in ten (docs/recording.md): beyond this, mostly failures.
MAX_DRIFT_STD = 0.15


@dataclass
class RecordConfig:
    env: CondGroundEnvConfig = field(default_factory=CondGroundEnvConfig)
    dataset: RecordDatasetConfig = field(default_factory=RecordDatasetConfig)
    drift: DriftConfig = field(default_factory=DriftConfig)
    takeover: TakeoverConfig = field(default_factory=TakeoverConfig)
    # Episode k of a fresh dataset is tried with seed + k (and later seeds after failures).
    seed: int = 0
    # Stop with an error when the expert fails this many episodes in a row.
    max_consecutive_failures: int = 20
    # Show a progress bar.
    progress: bool = True

    def __post_init__(self):
        check_at_least(self.dataset, "dataset.", num_episodes=1, checkpoint_every=1)
        check_at_least(self, "", max_consecutive_failures=1)
        check_seed("--seed", self.seed, self.dataset.num_episodes)
        if not 0.0 <= self.drift.std <= MAX_DRIFT_STD:
            raise ValueError(
                f"--drift.std={self.drift.std} is not allowed; allowed: 0 (none) to {MAX_DRIFT_STD} rad"
            )
        if not self.drift.time_constant > 0.0:
            raise ValueError(
                f"--drift.time_constant={self.drift.time_constant} is not allowed; allowed: seconds above 0"
            )
        if self.drift.std and self.env.task == ROUTING_TASK:
            raise ValueError(
                f"--drift.std={self.drift.std} is not allowed with --env.task={ROUTING_TASK}; allowed: 0 (its "
                "expert does not fade the drift before it grasps)"
            )
        if self.takeover.policy_path is not None:
            if self.env.task == ROUTING_TASK:
                raise ValueError(
                    f"--takeover.policy_path is not allowed with --env.task={ROUTING_TASK}; allowed: the "
                    "pick-and-place tasks (its expert cannot take over mid-procedure)"
                )
            if not 0 <= self.takeover.min_steps <= self.takeover.max_steps < self.env.episode_length:
                raise ValueError(
                    f"--takeover.min_steps={self.takeover.min_steps} and --takeover.max_steps="
                    f"{self.takeover.max_steps} are not allowed; allowed: 0 <= min_steps <= max_steps < "
                    f"--env.episode_length={self.env.episode_length}"
                )
        if self.env.camera_codec != "none":
            raise ValueError(
                f"--env.camera_codec={self.env.camera_codec!r} is not allowed when recording; allowed: none (the "
                "dataset's own video encoding is --dataset.video; a second codec pass would blur every frame twice)"
            )
        if self.dataset.num_episodes > MAX_EPISODES:
            raise ValueError(
                f"--dataset.num_episodes={self.dataset.num_episodes} is not allowed; allowed: 1 to {MAX_EPISODES} "
                "(at 96x128 about 0.5 MB and 4 s an episode on 2 cores: 50 GB and 5 days at the limit)"
            )
        if self.seed >= HELD_OUT_SEED_OFFSET:
            raise ValueError(
                f"--seed={self.seed} is not allowed: from seed {HELD_OUT_SEED_OFFSET} on `condground sweep` draws "
                f"its held-out layouts, which no training recording may hold; allowed: 0 to "
                f"{HELD_OUT_SEED_OFFSET - self.dataset.num_episodes}"
            )
        if self.seed + self.dataset.num_episodes > HELD_OUT_SEED_OFFSET:
            raise ValueError(
                f"--seed={self.seed} with --dataset.num_episodes={self.dataset.num_episodes} is not allowed: the "
                f"recording's layouts would reach seed {HELD_OUT_SEED_OFFSET}, where `condground sweep` draws its "
                f"held-out layouts; allowed: at most {HELD_OUT_SEED_OFFSET - self.seed} episodes from this seed"
            )


def dataset_features(env_cfg: CondGroundEnvConfig, video: bool, labels: bool = True) -> dict:
    h, w = env_cfg.observation_height, env_cfg.observation_width
    image = {
        "dtype": "video" if video else "image",
        "shape": (h, w, 3),
        "names": ["height", "width", "channels"],
    }
    features = {
        "observation.images.top": image,
        "observation.state": {"dtype": "float32", "shape": (7,), "names": list(MOTOR_NAMES)},
        "action": {"dtype": "float32", "shape": (7,), "names": list(MOTOR_NAMES)},
    }
    if labels:
        features[OBS_PHASE] = {"dtype": "int64", "shape": (1,), "names": ["phase"]}
        if env_cfg.task == ROUTING_TASK:
            features[OBS_DESTINATION] = {"dtype": "int64", "shape": (1,), "names": ["destination"]}
            pngs = (OBS_SEGMENTATION, *((OBS_SEGMENTATION_WRIST,) if env_cfg.wrist_camera else ()))
        else:
            pngs = (OBS_SEGMENTATION, OBS_PROMPT_OBJECT, OBS_PROMPT_RECEPTACLE)
        features |= {key: dict(PNG_FEATURE) for key in pngs}
    if env_cfg.wrist_camera:
        features["observation.images.wrist"] = dict(image)
    return features


def make_recording_env(env_cfg: CondGroundEnvConfig, labels: bool = True):
    """The task's env with what the recording writes turned on, and its scripted expert."""
    if env_cfg.task == ROUTING_TASK:
        from lerobot_condground.envs.routing_expert import RoutingExpert

        return env_cfg.make_env(segmentation=labels, destination=labels), RoutingExpert()
    from lerobot_condground.envs.expert import ScriptedExpert

    return env_cfg.make_env(segmentation=labels, prompts=labels), ScriptedExpert()


def episode_frames(obs: dict, action: np.ndarray, phase: int, task: str) -> dict:
    """One dataset frame; label features only when the env rendered them (`make_recording_env`)."""
    frame = {
        "observation.images.top": obs["pixels"]["top"],
        "observation.state": obs["agent_pos"].astype(np.float32),
        "action": action.astype(np.float32),
        "task": task,
    }
    if "segmentation" in obs:
        frame[OBS_PHASE] = np.array([phase], dtype=np.int64)
        for key, name in (
            (OBS_SEGMENTATION, "segmentation"),
            (OBS_SEGMENTATION_WRIST, "segmentation_wrist"),
            (OBS_PROMPT_OBJECT, "prompt_object"),
            (OBS_PROMPT_RECEPTACLE, "prompt_receptacle"),
        ):
            if name in obs:
                frame[key] = encode_png(obs[name])
    if "destination" in obs:
        frame[OBS_DESTINATION] = np.asarray(obs["destination"], dtype=np.int64).reshape(1)
    if "wrist" in obs["pixels"]:
        frame["observation.images.wrist"] = obs["pixels"]["wrist"]
    return frame


def _open_dataset(cfg: RecordConfig, root: Path, features: dict, policy_hash: str | None = None):
    """Creates the dataset, or resumes an existing one after checking it was made the same way."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    provenance_path = root / RECORD_FILE
    if (root / "meta" / "info.json").exists():
        previous = (
            read_json_object(provenance_path, "Recording provenance") if provenance_path.exists() else {}
        )
        if "sources" in previous:
            raise ValueError(
                f"{root} holds a merge of {len(previous['sources'])} datasets (`condground merge`), which a "
                "recording cannot resume; allowed: record into a new --dataset.root and merge it with the others"
            )
        info = read_json_object(root / "meta" / "info.json", "Dataset info")
        # Provenance is written ahead of the data, so it never lists fewer episodes than were saved: fewer
        # means episodes added by something else (e.g. `lerobot-edit-dataset merge`), whose seeds a resumed
        # recording would neither know nor avoid, and its record would then misname every later episode.
        listed, total = len(previous.get("episodes", [])), info.get("total_episodes")
        if isinstance(total, int) and total > listed:
            how = f"its {RECORD_FILE} lists {listed}" if provenance_path.exists() else f"no {RECORD_FILE}"
            raise ValueError(
                f"{root} holds {total} episodes and {how}: episodes `condground record` did not record "
                "there, which a recording cannot resume; allowed: record into a new --dataset.root and "
                "combine the two with `condground merge`"
            )
        if provenance_path.exists():
            _discard_unsaved_episode(root)
            info = read_json_object(root / "meta" / "info.json", "Dataset info")
        if info.get("total_episodes") == 0 and provenance_path.exists():
            _remove_empty_recording(root)
            return _open_dataset(cfg, root, features, policy_hash)
        mismatches = []
        if info.get("fps") != cfg.env.fps:
            mismatches.append(f"fps {info.get('fps')} != {cfg.env.fps}")
        for key, ft in features.items():
            have = info["features"].get(key)
            if have is None or tuple(have["shape"]) != tuple(ft["shape"]) or have["dtype"] != ft["dtype"]:
                mismatches.append(f"feature {key}")
        from lerobot.utils.constants import DEFAULT_FEATURES

        mismatches += [
            f"feature {key}" for key in sorted(set(info["features"]) - set(features) - set(DEFAULT_FEATURES))
        ]
        recorded = {**PROVENANCE_ENV_BEFORE, **previous["env"]} if "env" in previous else {}
        for key in ("task", "condition", "counterbalanced", "competitor_pool", "subgoal", "servo"):
            if recorded.get(key, getattr(cfg.env, key)) != getattr(cfg.env, key):
                mismatches.append(f"env.{key} {recorded[key]!r} != {getattr(cfg.env, key)!r}")
        drift = previous.get("drift", {"std": 0.0, "time_constant": cfg.drift.time_constant})
        if drift["std"] != cfg.drift.std or (
            cfg.drift.std and drift["time_constant"] != cfg.drift.time_constant
        ):
            mismatches.append(f"drift {drift} != {asdict(cfg.drift)}")
        takeover = previous.get("takeover", {"policy_path": None})
        if takeover.get("policy_path") != cfg.takeover.policy_path or (
            cfg.takeover.policy_path
            and (takeover["min_steps"], takeover["max_steps"], takeover.get("policy_hash"))
            != (cfg.takeover.min_steps, cfg.takeover.max_steps, policy_hash)
        ):
            mismatches.append(f"takeover {takeover} != {asdict(cfg.takeover) | {'policy_hash': policy_hash}}")
        if mismatches:
            raise ValueError(
                f"{root} already holds a dataset recorded differently ({'; '.join(mismatches)}); "
                f"choose another --dataset.root or record with the same settings to resume it"
            )
        dataset = LeRobotDataset.resume(cfg.dataset.repo_id, root=root, streaming_encoding=False)
        # A hard kill leaves the frames of the episode in flight on disk, the last one maybe truncated;
        # LeRobot would encode them into the next episode's video along with its own.
        dataset.clear_episode_buffer(delete_images=True)
        return dataset, previous
    if root.is_dir():
        found = sorted(p.name for p in root.iterdir())
        if found:
            raise FileExistsError(
                f"--dataset.root={root} holds files but no dataset ({', '.join(found[:5])}); allowed: a new or "
                "empty folder, or a dataset recorded with the same settings to resume"
            )
        root.rmdir()  # LeRobot creates the folder itself and refuses an existing one, even empty
    # Not LeRobot's streaming encoder: when its queue is full (a busy CPU, our burst of add_frame calls)
    # it drops frames with only a warning, and the video ends up shorter than the episode.
    dataset = LeRobotDataset.create(
        cfg.dataset.repo_id,
        fps=cfg.env.fps,
        features=features,
        root=root,
        robot_type="ur3e_sim",
        use_videos=cfg.dataset.video,
        streaming_encoding=False,
    )
    return dataset, {}


# What LeRobot and the recorder write into a dataset before its first episode is saved, or while saving it.
EMPTY_RECORDING_FILES = (
    RECORD_FILE, "meta/info.json", "meta/stats.json", "meta/tasks.parquet", "meta/episodes/chunk-*/file-*.parquet",
    "data/chunk-*/file-*.parquet", "videos/*/chunk-*/file-*.mp4", "images/*/episode-*/frame-*.png",
    "tmp*/*.mp4",  # LeRobot encodes an episode's video in a temporary folder of the dataset, then moves it
)  # fmt: skip


# Of those, what an episode in flight may have written when the recording was killed.
IN_FLIGHT_FILES = (
    "meta/episodes/chunk-*/file-*.parquet", "data/chunk-*/file-*.parquet", "videos/*/chunk-*/file-*.mp4", "tmp*/*.mp4",
)  # fmt: skip


def _matches(relative: Path, patterns: tuple[str, ...]) -> bool:
    return any(
        len(relative.parts) == len(pattern.split("/"))
        and all(
            fnmatch.fnmatchcase(part, glob)
            for part, glob in zip(relative.parts, pattern.split("/"), strict=True)
        )
        for pattern in patterns
    )


def _remove_empty_recording(root: Path) -> None:
    """A recording of ours that saved no episode pins nothing: a failed or stopped first run must not refuse
    the corrected rerun. Removes it only when every file in the folder is one the recorder writes and
    nothing in it is a link; otherwise refuses and removes nothing."""
    entries = [
        Path(top) / name for top, dirs, files in os.walk(root) for name in (*dirs, *files)
    ]  # no links followed
    strangers = sorted(
        str(p.relative_to(root)) + (" (a link)" if p.is_symlink() else "")
        for p in entries
        if p.is_symlink() or (p.is_file() and not _matches(p.relative_to(root), EMPTY_RECORDING_FILES))
    )
    if strangers:
        raise FileExistsError(
            f"--dataset.root={root} holds an empty recording and files the recorder did not write "
            f"({', '.join(strangers[:5])}); nothing was removed: move them away or choose another --dataset.root"
        )
    for path in entries:
        if path.is_file():
            path.unlink()
    for path in sorted((p for p in entries if p.is_dir()), key=lambda p: len(p.parts), reverse=True):
        path.rmdir()
    root.rmdir()


def _discard_unsaved_episode(root: Path) -> None:
    """A hard kill while LeRobot saves an episode leaves it half-written: a data parquet without its footer
    (stock LeRobot then cannot open the dataset at all), a video or its temporary folder that no episode
    names, and `info.json` / `stats.json` that may already count it. The episodes index is written last, when
    the dataset is closed: what it names was saved. Removes the recorder's other files of the episode in
    flight and rebuilds the counts and statistics from the index, so the rerun resumes from the last closed
    episode. An index that does not match the files it names is refused, nothing removed."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    from lerobot.datasets.compute_stats import aggregate_stats
    from lerobot.datasets.io_utils import write_stats
    from lerobot.datasets.utils import DEFAULT_DATA_PATH, DEFAULT_EPISODES_PATH, DEFAULT_VIDEO_PATH

    index_files = sorted((root / "meta" / "episodes").glob("chunk-*/file-*.parquet"))
    rows: list[dict] = []
    for i, path in enumerate(index_files):
        try:
            rows += pq.read_table(path).to_pylist()
        except (OSError, pa.ArrowInvalid) as err:
            if i < len(index_files) - 1:
                raise ValueError(
                    f"{path} is not readable ({err}) and is not the last episodes index file: the dataset is "
                    "damaged beyond what a killed recording leaves; nothing was removed"
                ) from None
            # The kill came while the dataset was being closed: its last episode is not saved (removed below).
    if [row["episode_index"] for row in rows] != list(range(len(rows))):
        raise ValueError(
            f"{root}/meta/episodes does not list episodes 0..{len(rows) - 1} in order; nothing was removed"
        )
    info_path = root / "meta" / "info.json"
    info = read_json_object(info_path, "Dataset info")
    video_keys = [key for key, ft in info["features"].items() if ft.get("dtype") == "video"]
    saved = {
        DEFAULT_EPISODES_PATH.format(
            chunk_index=r["meta/episodes/chunk_index"], file_index=r["meta/episodes/file_index"]
        )
        for r in rows
    }
    saved |= {
        DEFAULT_DATA_PATH.format(chunk_index=r["data/chunk_index"], file_index=r["data/file_index"])
        for r in rows
    }
    saved |= {
        DEFAULT_VIDEO_PATH.format(
            video_key=key,
            chunk_index=r[f"videos/{key}/chunk_index"],
            file_index=r[f"videos/{key}/file_index"],
        )
        for r in rows
        for key in video_keys
    }
    missing = sorted(relative for relative in saved if not (root / relative).is_file())
    if missing:
        raise ValueError(
            f"{root} names files it does not hold ({', '.join(missing[:3])}); nothing was removed"
        )
    for top, _, files in os.walk(root):  # no links followed
        for path in (Path(top) / name for name in files):
            relative = path.relative_to(root)
            if (
                _matches(relative, IN_FLIGHT_FILES)
                and relative.as_posix() not in saved
                and not path.is_symlink()
            ):
                path.unlink()
                if relative.parts[0].startswith("tmp") and not any(path.parent.iterdir()):
                    path.parent.rmdir()
    frames = rows[-1]["dataset_to_index"] if rows else 0
    if (info["total_episodes"], info["total_frames"]) == (len(rows), frames) and _readable(
        root / "meta" / "stats.json"
    ):
        return
    info |= {"total_episodes": len(rows), "total_frames": frames, "splits": {"train": f"0:{len(rows)}"}}
    tmp = info_path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(info, indent=4))
    os.replace(tmp, info_path)
    if rows:
        write_stats(aggregate_stats([_episode_stats(row) for row in rows]), root)


def _readable(path: Path) -> bool:
    try:
        json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    return True


def _episode_stats(row: dict) -> dict[str, dict[str, np.ndarray]]:
    stats: dict[str, dict[str, np.ndarray]] = {}
    for key, value in row.items():
        if key.startswith("stats/"):
            feature, stat = key.removeprefix("stats/").rsplit("/", 1)
            stats.setdefault(feature, {})[stat] = np.asarray(value, dtype=np.float64)
    return stats


def _write_provenance(root: Path, cfg: RecordConfig, state: dict, policy_hash: str | None) -> None:
    from lerobot_condground import __version__

    env = {key: getattr(cfg.env, key) for key in PROVENANCE_ENV_KEYS}
    payload = {"env": env, "drift": asdict(cfg.drift), "seed": cfg.seed, "version": __version__}
    if cfg.takeover.policy_path:
        payload["takeover"] = asdict(cfg.takeover) | {"policy_hash": policy_hash}
    payload |= state
    tmp = root / (RECORD_FILE + ".tmp")
    tmp.write_text(json.dumps(payload, indent=1, default=str))
    os.replace(tmp, root / RECORD_FILE)


def record(cfg: RecordConfig, driver=None) -> dict:
    """Records until the dataset holds `num_episodes` expert episodes. Returns counts for the report.

    driver: with --takeover.policy_path, the policy that drives each episode up to the takeover (`reset(env)`,
    `driver(obs) -> action`, `hash`: its checkpoint's), built by the command layer."""
    if (driver is None) != (cfg.takeover.policy_path is None):
        raise ValueError("record() takes a driver exactly when --takeover.policy_path is set")
    import datasets
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from tqdm import tqdm

    from lerobot_condground.envs.expert import JointDrift, run_expert_episode

    # SVT-AV1 (LeRobot's video encoder) prints a 20-line banner to stderr for every encoded episode; at
    # level 1 (errors) it stays quiet. Read by the library at each encoder start; a user's value wins.
    os.environ.setdefault("SVT_LOG", "1")
    # The recording shows its own progress: no codec line per saved episode (nor `datasets` bar, below).
    logging.getLogger("lerobot.configs.video").setLevel(logging.WARNING)
    features = dataset_features(cfg.env, cfg.dataset.video, cfg.dataset.labels)
    # Validates the condition and its layout before anything is written.
    env, expert = make_recording_env(cfg.env, cfg.dataset.labels)
    root = cfg.dataset.path()
    policy_hash = driver.hash if driver is not None else None
    dataset, previous = _open_dataset(cfg, root, features, policy_hash)
    have = dataset.meta.total_episodes
    state = {
        "next_seed": previous.get("next_seed", cfg.seed),
        # Provenance is written ahead of the data; after a hard kill it may name one unsaved episode.
        "episodes": previous.get("episodes", [])[:have],
        "failed_seeds": previous.get("failed_seeds", []),
    }
    if driver is not None:
        # Episodes the policy finished (or broke) before the takeover: nothing to record.
        state["ended_before_takeover_seeds"] = previous.get("ended_before_takeover_seeds", [])
    if have:
        logging.info("Resuming %s: %d episodes already recorded", root, have)
    # Counts of this run only: what the closing line reports.
    run_stages: Counter = Counter()
    attempts = successes = consecutive_failures = ended_before_takeover = 0
    bar = tqdm(
        total=cfg.dataset.num_episodes,
        initial=have,
        desc=f"record {cfg.env.task} {cfg.env.subgoal if cfg.env.task == ROUTING_TASK else cfg.env.condition}",
        unit="ep",
        disable=not cfg.progress,
    )
    try:
        while have < cfg.dataset.num_episodes:
            seed = state["next_seed"]
            if seed >= HELD_OUT_SEED_OFFSET:
                # Failed episodes were retried with later seeds until the next one is a held-out layout.
                raise ValueError(
                    f"the next episode's seed {seed} is a held-out layout of `condground sweep` (retries of "
                    f"{len(state['failed_seeds'])} failed episodes pushed the seeds up); what was recorded is kept: "
                    f"record the rest into another --dataset.root from a lower --seed and merge the two"
                )
            state["next_seed"] += 1
            frames: list[dict] = []
            drift = (
                JointDrift(cfg.drift.std, cfg.drift.time_constant, cfg.env.fps, seed)
                if cfg.drift.std
                else None
            )
            takeover_step = 0
            if driver is not None:
                rng = np.random.default_rng([seed, 1])
                takeover_step = int(rng.integers(cfg.takeover.min_steps, cfg.takeover.max_steps + 1))
            info = run_expert_episode(
                env,
                expert,
                seed,
                cfg.env.episode_length,
                on_step=lambda obs, action, phase: frames.append(  # noqa: B023  (called within this iteration)
                    episode_frames(obs, action, phase, env.task_description)
                ),
                drift=drift,
                driver=driver,
                takeover_step=takeover_step,
            )
            if driver is not None and not info["taken_over"]:
                state["ended_before_takeover_seeds"].append(seed)
                ended_before_takeover += 1
                continue
            attempts += 1
            run_stages[int(info["stage"])] += 1
            if not info["is_success"]:
                state["failed_seeds"].append(seed)
                consecutive_failures += 1
                if consecutive_failures >= cfg.max_consecutive_failures:
                    raise ValueError(
                        f"The expert failed {consecutive_failures} episodes in a row (last seed {seed}) with "
                        f"--env.episode_length={cfg.env.episode_length}: too short for the task, or the "
                        f"environment is broken for task={cfg.env.task} condition={cfg.env.condition}"
                    )
                continue
            consecutive_failures = 0
            successes += 1
            state["episodes"].append(
                {"seed": seed, "task": env.task_description, "entities": env.entity_table()}
                | ({"subgoal": env.episode} if cfg.env.task == ROUTING_TASK else {})
                | ({"drift_largest_rad": round(drift.largest, 4)} if drift else {})
                | ({"takeover_step": takeover_step} if driver is not None else {})
            )
            # Before the data, so a resumed run never reuses a seed.
            _write_provenance(root, cfg, state, policy_hash)
            for frame in frames:
                dataset.add_frame(frame)
            # LeRobot re-enables `datasets` bars after every dataset load (SuppressProgressBars).
            datasets.disable_progress_bars()
            with kept_priority():  # the encoder would leave this thread at real-time priority
                dataset.save_episode()
            have += 1
            bar.update(1)
            if have % cfg.dataset.checkpoint_every == 0 and have < cfg.dataset.num_episodes:
                with kept_priority():
                    dataset.finalize()
                dataset = LeRobotDataset.resume(cfg.dataset.repo_id, root=root, streaming_encoding=False)
    finally:
        bar.close()
        # Whatever happened, what was saved is closed and readable.
        with kept_priority():
            dataset.finalize()
        _write_provenance(root, cfg, state, policy_hash)
        env.close()
    if cfg.dataset.push_to_hub:
        LeRobotDataset(cfg.dataset.repo_id, root=root).push_to_hub(private=cfg.dataset.private)
    return {
        "attempts": attempts,
        "successes": successes,
        "stages": dict(run_stages),
        "task": cfg.env.task,
        "root": str(root),
        "total_episodes": have,
    } | ({"ended_before_takeover": ended_before_takeover} if driver is not None else {})


def format_summary(result: dict) -> str:
    line = f"expert success: {result['successes']}/{result['attempts']}"
    if "ended_before_takeover" in result:
        ended = result["ended_before_takeover"]
        line += f" after the takeover ({ended} episode{'' if ended == 1 else 's'} ended before it)"
    if not result["attempts"]:
        line += f" (the dataset already holds {result['total_episodes']} episodes)"
    if result.get("task") == ROUTING_TASK:
        counts = ", ".join(f"{n}={c}" for n, c in sorted(result["stages"].items()))
        return f"{line}\nsubgoals reached in order (count=episodes): {counts}"
    from lerobot_condground.envs.stages import STAGES

    stage_counts = ", ".join(f"{name}={result['stages'].get(i, 0)}" for i, name in enumerate(STAGES))
    return f"{line}\nstages reached: {stage_counts}"
