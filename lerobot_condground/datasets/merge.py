"""`condground merge`: recordings merged into one LeRobotDataset with LeRobot's own merge, keeping how each
episode was made.

LeRobot's merge (`lerobot-edit-dataset --operation.type=merge`) copies every feature but not this package's
files in `meta/`; for a DAgger aggregate that loses which episodes are the expert's, which were taken over
from a policy (which checkpoint, at which step) and with which seeds. The merged dataset's
`meta/condground_record.json` lists each source (its recording settings, and its augmentation or prompt
labelling when it has them) and every episode in the merged order, with the index of its source.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from lerobot_condground.core.configs import DatasetOutputConfig, DatasetRefConfig
from lerobot_condground.core.files import partial_beside, read_json_object
from lerobot_condground.core.provenance import AUGMENT_FILE, PROMPTS_FILE, RECORD_FILE
from lerobot_condground.core.trust import within


@dataclass
class MergeConfig:
    # Local roots of the datasets to merge, in order, e.g. '[outputs/demos,outputs/takeover]': the merged
    # episodes keep this order. Recordings, not merges (LeRobot 0.6.1 cannot merge a merged dataset again).
    roots: list[str] = field(default_factory=list)
    # Must not exist yet.
    output: DatasetOutputConfig = field(default_factory=DatasetOutputConfig)

    def __post_init__(self):
        self.output.repo_id = self.output.repo_id or "local/condground_merged"


def _meta(root: Path, name: str, flag: str) -> dict | None:
    """One of the source's own JSON files, or None; never a file it links to outside its root."""
    if not (root / name).is_file():
        return None
    if not within(root, Path(name)):
        raise PermissionError(f"{flag}: {name} links outside the dataset's root; allowed: a file inside it")
    return read_json_object(root / name, f"{name} of {flag}")


def _source(root: Path, index: int) -> tuple[dict, list[dict]]:
    """What the merged provenance says of one source, and its episodes' records (one per episode)."""
    flag = f"--roots[{index}]={root}"
    if not (root / "meta" / "info.json").is_file():
        raise FileNotFoundError(
            f"{flag} holds no LeRobotDataset (no meta/info.json); allowed: the root of a local dataset, "
            "e.g. one written by `condground record`"
        )
    total = _meta(root, "meta/info.json", flag).get("total_episodes")
    if not isinstance(total, int) or total < 0:
        raise ValueError(f"{flag}: meta/info.json has total_episodes={total!r}; allowed: a count of episodes")
    entry: dict = {"root": str(root), "episodes": total}
    for key, name in (("augment", AUGMENT_FILE), ("prompts", PROMPTS_FILE)):
        if (found := _meta(root, name, flag)) is not None:
            entry[key] = found
    record = _meta(root, RECORD_FILE, flag)
    if record is None:
        entry["record"] = None  # a dataset recorded elsewhere: its episodes are listed without provenance
        return entry, [{} for _ in range(total)]
    if "sources" in record:
        raise ValueError(
            f"{flag} is itself a merge ({len(record['sources'])} sources); allowed: the original recordings "
            "(LeRobot 0.6.1 cannot merge a merged dataset again)"
        )
    episodes = record.get("episodes")
    if not isinstance(episodes, list) or not all(isinstance(e, dict) for e in episodes):
        raise ValueError(f"{flag}: its {RECORD_FILE} has no list of episode records; it is damaged")
    if len(episodes) != total:
        raise ValueError(
            f"{flag}: its {RECORD_FILE} lists {len(episodes)} episodes, its meta/info.json {total}; allowed: "
            "a dataset whose recording finished writing both"
        )
    entry["record"] = {key: value for key, value in record.items() if key != "episodes"}
    return entry, episodes


def _check_alike(roots: list[Path]) -> None:
    """fps and features must agree: named here by source and feature, where LeRobot's own check prints both
    feature tables whole."""
    infos = [read_json_object(root / "meta" / "info.json", "Dataset info") for root in roots]
    first = infos[0]
    for index, info in enumerate(infos[1:], start=1):
        flag = f"--roots[{index}]={roots[index]}"
        if info.get("fps") != first.get("fps"):
            raise ValueError(
                f"{flag} runs at {info.get('fps')} fps, --roots[0] at {first.get('fps')}; allowed: one fps"
            )
        ours, theirs = first.get("features") or {}, info.get("features") or {}
        only = sorted(set(ours) ^ set(theirs))
        differ = sorted(k for k in set(ours) & set(theirs) if ours[k].get("shape") != theirs[k].get("shape")
                        or ours[k].get("dtype") != theirs[k].get("dtype"))  # fmt: skip
        if only or differ:
            parts = [f"{k} only in {'--roots[0]' if k in ours else flag.split('=')[0]}" for k in only]
            parts += [f"{k} of another shape or type" for k in differ]
            raise ValueError(
                f"{flag} and --roots[0] have other features ({'; '.join(parts)}); allowed: recordings made alike "
                "(same cameras and sizes, labels on or off in all)"
            )


def merge_datasets(cfg: MergeConfig) -> dict:
    """Writes the merged dataset and its provenance; returns counts for the summary."""
    from lerobot.datasets.aggregate import aggregate_datasets
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    if len(cfg.roots) < 2:
        raise ValueError(f"--roots={cfg.roots} names {len(cfg.roots)} dataset(s); allowed: two or more roots")
    if cfg.output.video is not None:
        raise ValueError(
            f"--output.video={str(cfg.output.video).lower()}: a merge copies each source's frames as they are "
            "stored; allowed: leave it unset"
        )
    out_root = cfg.output.path()
    if out_root.exists():
        raise FileExistsError(
            f"--output.root={out_root} already exists; allowed: a path that does not exist yet "
            "(the merge is always written fresh)"
        )
    roots = [DatasetRefConfig(root=root).path() for root in cfg.roots]
    resolved = [root.resolve() for root in roots]
    for index, root in enumerate(resolved):
        if root in resolved[:index]:
            raise ValueError(
                f"--roots[{index}]={roots[index]} is --roots[{resolved.index(root)}] again: its episodes would be "
                "merged twice; allowed: each dataset once"
            )
        if (
            out_root.resolve() == root
            or out_root.resolve().is_relative_to(root)
            or root.is_relative_to(out_root.resolve())
        ):
            raise ValueError(
                f"--output.root={out_root} overlaps --roots[{index}]={roots[index]}; allowed: a path outside every "
                "source (a dataset's folder is its own)"
            )
    sources, episodes = [], []
    for index, root in enumerate(roots):
        entry, records = _source(root, index)
        sources.append(entry)
        episodes += [{**record, "source": index} for record in records]
    _check_alike(roots)
    partial = partial_beside(out_root)
    out_root.parent.mkdir(parents=True, exist_ok=True)
    try:
        # LeRobot checks that fps, robot type and features agree, and names what differs.
        aggregate_datasets(
            repo_ids=[f"local/{root.name}" for root in roots],
            aggr_repo_id=cfg.output.repo_id,
            roots=roots,
            aggr_root=partial,
        )
        merged = read_json_object(partial / "meta" / "info.json", "Merged dataset info")
        if merged["total_episodes"] != len(episodes):
            raise RuntimeError(
                f"LeRobot's merge wrote {merged['total_episodes']} episodes of {len(episodes)}"
            )
        provenance = {"sources": sources, "episodes": episodes}
        (partial / RECORD_FILE).write_text(json.dumps(provenance, indent=1, default=str))
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    partial.rename(out_root)
    if cfg.output.push_to_hub:
        LeRobotDataset(cfg.output.repo_id, root=out_root).push_to_hub(private=cfg.output.private)
    return {
        "root": str(out_root),
        "repo_id": cfg.output.repo_id,
        "episodes": len(episodes),
        "frames": merged["total_frames"],
        "per_source": [source["episodes"] for source in sources],
    }


def format_summary(result: dict) -> str:
    parts = " + ".join(str(n) for n in result["per_source"])
    return (
        f"merged {parts} = {result['episodes']} episodes, {result['frames']} frames -> {result['repo_id']} "
        f"at {result['root']} (how each episode was made: {Path(result['root']) / RECORD_FILE})"
    )
