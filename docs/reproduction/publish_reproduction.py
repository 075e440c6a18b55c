"""Copies the small outputs of a `condground reproduce` run's finished stages into a folder kept in git
(results tables, JSON, report, figures; never checkpoints, datasets or logs).

    python docs/reproduction/publish_reproduction.py outputs/reproduce docs/reproduction/cpu

A stage counts once its marker `stages/<stage>.json` exists; rerunning adds the stages finished since.
Training stages contribute their `train_config.json`, recordings their `meta/info.json` and provenance.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

SMALL = {".parquet", ".json", ".html", ".md", ".png", ".csv"}
MAX_BYTES = 2_000_000
SKIP_DIRS = {"parts", "checkpoints", "data", "videos", "images"}


def stage_files(run: Path, stage: str) -> list[Path]:
    here = run / stage
    kind = stage.split("/")[0]
    if kind == "train":
        config = here / "checkpoints" / "last" / "pretrained_model" / "train_config.json"
        return [config] if config.is_file() else []
    if kind == "datasets":
        return [
            p for p in (here / "meta" / "info.json", here / "meta" / "condground_record.json") if p.is_file()
        ]
    return [
        p
        for p in here.rglob("*")
        if p.is_file()
        and p.suffix in SMALL
        and p.stat().st_size <= MAX_BYTES
        and not SKIP_DIRS & set(p.relative_to(here).parts[:-1])
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="the --output_dir of condground reproduce")
    parser.add_argument("dest", type=Path, help="where the small outputs go")
    args = parser.parse_args()
    if not (args.run / "reproduce.json").is_file():
        raise SystemExit(f"{args.run} holds no reproduce.json: not a condground reproduce directory")
    args.dest.mkdir(parents=True, exist_ok=True)
    shutil.copy2(args.run / "reproduce.json", args.dest / "reproduce.json")
    copied = 0
    for marker in sorted((args.run / "stages").glob("*.json")):
        stage = marker.stem.replace("__", "/")
        for src in [marker, *stage_files(args.run, stage)]:
            dst = args.dest / src.relative_to(args.run)
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dst)
            copied += 1
        print(f"published {stage}")
    print(f"{copied} files in {args.dest}")


if __name__ == "__main__":
    main()
