"""Reading JSON files that this package or LeRobot wrote and a user may hand us damaged or hand-edited:
an error names the file, never only the parser's line and column. Where a command writes a new dataset
before it is whole."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path


def read_json_object(path: Path, what: str) -> dict:
    """The JSON object in `path`; `what` says in the error which file it was meant to be."""
    return parse_json_object(Path(path).read_bytes(), path, what)


def parse_json_object(text: bytes, path: Path, what: str) -> dict:
    """The JSON object in `text`, the bytes read from `path`."""
    try:
        data = json.loads(text)
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ValueError(
            f"{what} {path} is not valid JSON ({err}); it is damaged or was not written by LeRobot or condground"
        ) from None
    if not isinstance(data, dict):
        raise ValueError(f"{what} {path} holds a JSON {type(data).__name__}, not an object")
    return data


def partial_beside(out_root: Path) -> Path:
    """Where a command writes a new dataset before renaming it to `out_root` when whole: a failed or killed run
    leaves nothing at `out_root` that would block the rerun, and the rerun clears what it left here."""
    partial = out_root.with_name(f".{out_root.name}.partial")
    if partial.exists():
        logging.info("Removing %s, left by an earlier run that did not finish", partial)
        shutil.rmtree(partial)
    return partial
