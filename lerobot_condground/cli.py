"""`condground`: the plugin's own jobs, one module of `lerobot_condground.scripts` each.

Flags follow LeRobot's `--group.key=value` style and are parsed by draccus from the command's `Config`
(a module may bring its own `parse(args, prog)`). One error policy for every command: bad input (a
`ValueError`, a missing or already existing file, a flag draccus cannot decode) is one line on stderr,
naming the value and what is allowed, with exit code 2; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import logging
import re
import sys
from pathlib import Path

import draccus

from lerobot_condground.core.scheduling import normal_priority

# name -> (module under lerobot_condground.scripts, one line of help)
COMMANDS = {
    "record": ("record", "Record scripted-expert demonstrations into a LeRobotDataset (v3)."),
    "bench": (
        "bench",
        "Measure physics, rendering, env-step, recording and act_modified-vs-ACT throughput here.",
    ),
    "augment": (
        "augment",
        "Write a copy of a LeRobotDataset with synthetic distractors pasted in (copy-paste augmentation).",
    ),
    "merge": (
        "merge",
        "Merge recordings (e.g. demos and DAgger takeovers) with LeRobot's merge, keeping how each episode was made.",
    ),
    "train": (
        "train",
        "lerobot-train (same flags, same outputs) with decoded video frames held in memory: faster on a CPU.",
    ),
    "quickstart": (
        "quickstart",
        "Record demos, train a small act_modified (lerobot-train), evaluate it (lerobot-eval), print stages.",
    ),
    "reproduce": (
        "reproduce",
        "The paper's whole experiment (record, train 4 variants, sweep, diagnose, probe, report), resumable.",
    ),
    "pi05-start": (
        "pi05_start",
        "A pi05 checkpoint (lerobot/pi05_base) as a pi05_grounded starting point for lerobot-train --policy.path.",
    ),
    "pi05-bench": (
        "pi05_bench",
        "Training-step time and peak memory of the full-size pi05_grounded (regularizer, checkpointing), on a GPU.",
    ),
    "compare": (
        "compare",
        "Two training recipes side by side (N seeds, late checkpoints pooled, same held-out layouts), run-aware stats.",
    ),
    "sweep": (
        "sweep",
        "Evaluate checkpoints over conditions x seeds x rollouts (resumable, parallel) -> results.parquet.",
    ),
    "subgoals": (
        "subgoals",
        "InstrumentRouting-v0 per subgoal under cue / no_cue / explicit (sim, or the UR3e operator-scored).",
    ),
    "probe": (
        "probe",
        "Prompt-swap probe: how often a competitor's crop as prompt makes the policy select the competitor.",
    ),
    "diagnose": (
        "diagnose",
        "Representation diagnostics of an ACT-family checkpoint on matched clean/distractor frames.",
    ),
    "fit": (
        "fit",
        "How precisely a checkpoint reproduces demonstrations (teacher-forced), in rad and cm, per segment.",
    ),
    "failures": (
        "failures",
        "Why a checkpoint's rollouts fail: each failure's cause, grasp offsets at closing, pushes, stalls.",
    ),
    "attention": (
        "attention",
        "Per-step cross-attention of one head overlaid on the camera, as a video with stills.",
    ),
    "view": (
        "view",
        "Log one episode (a dataset's, with its segmentation, phase and prompts, or an attention run) to rerun.",
    ),
    "report": (
        "report",
        "Turn sweep, diagnose, probe and attention outputs into one HTML + Markdown report.",
    ),
    "prompts": (
        "prompts",
        "Add prompt crops, segmentation and phase (SAM 2 or color tracking) to a hardware dataset, as a copy.",
    ),
    "prompts-bench": (
        "prompts_bench",
        "Per-frame tracking latency of the prompt segmenters (color, SAM 2) on this machine.",
    ),
}
BAD_INPUT = (ValueError, FileNotFoundError, FileExistsError, PermissionError, draccus.utils.ParsingError)


def _usage() -> str:
    lines = ["usage: condground <command> [--group.key=value ...]", "", "commands:"]
    lines += [f"  {name:<13} {text}" for name, (_, text) in COMMANDS.items()]
    lines += ["", "`condground <command> --help` lists the flags of a command."]
    return "\n".join(lines)


def _message(err: BaseException) -> str:
    """draccus wraps a config's own ValueError ("Couldn't instantiate class ..."): the cause names the value.
    Its DecodingError ("`env.fps`: Couldn't parse 'abc' into an int") already does, unlike int()'s cause."""
    while (
        isinstance(err, draccus.utils.ParsingError)
        and not isinstance(err, draccus.utils.DecodingError)
        and isinstance(err.__cause__ or err.__context__, Exception)
    ):
        err = err.__cause__ or err.__context__
    return " ".join(str(err).split())


# YAML 1.1, which draccus reads each value with, takes `1:2` for the base-60 number 62: a range such as
# --fit.episodes=1:2 would silently name another episode. No flag of ours is meant in base 60.
_SEXAGESIMAL = re.compile(r"[-+]?[0-9][0-9_]*(:[0-5]?[0-9])+(\.[0-9_]*)?")


def _literal(arg: str) -> str:
    """`--key=value` with a value YAML would read as a base-60 number, quoted so that it stays text."""
    key, sep, value = arg.partition("=")
    return f"{key}={value!r}" if sep and key.startswith("--") and _SEXAGESIMAL.fullmatch(value) else arg


def _flagged(message: str, args: list[str]) -> str:
    """A nested config's own check names its field ("prob=2.0 is not allowed"): prefixed with the flag's group
    ("--copy_paste.prob=2.0 ...") when exactly one flag given sets a field of that name."""
    field = re.match(r"(\w+)=", message)
    flags = {arg.partition("=")[0] for arg in args if arg.startswith("--") and "." in arg.partition("=")[0]}
    groups = {flag.rpartition(".")[0] for flag in flags if field and flag.rpartition(".")[2] == field[1]}
    return f"{groups.pop()}.{message}" if len(groups) == 1 else message


def _parse(script, args: list[str], prog: str):
    """The command's config. argparse answers an unknown flag with the whole usage (every flag) and exits:
    only its last line, the error, is kept, with where to find the flags."""
    captured = io.StringIO()
    args = [_literal(arg) for arg in args]
    try:
        with contextlib.redirect_stderr(captured):
            parse = getattr(script, "parse", None)
            return parse(args) if parse else draccus.parse(script.Config, args=args, prog=prog)
    except draccus.utils.ParsingError as err:
        if isinstance(err, draccus.utils.DecodingError):
            raise
        raise ValueError(_flagged(_message(err), args)) from err
    except SystemExit as stop:
        if stop.code != 2:
            raise
        last = captured.getvalue().strip().splitlines()[-1:] or ["bad arguments"]
        raise ValueError(
            f"{last[0].removeprefix(f'{prog}: error: ')}; `{prog} --help` lists the flags"
        ) from None
    finally:
        sys.stderr.write(captured.getvalue() if "usage:" not in captured.getvalue() else "")


def _check_outputs(cfg) -> None:
    """An output folder that is an existing file: one line naming the flag, for every command, before any work
    (mkdir would say only "File exists", and some commands would first load a checkpoint or build envs)."""
    from lerobot_condground.core.configs import DatasetOutputConfig

    folders = {"--output_dir": getattr(cfg, "output_dir", None)}
    for name, group in vars(cfg).items() if hasattr(cfg, "__dataclass_fields__") else ():
        if isinstance(group, DatasetOutputConfig):
            folders[f"--{name}.root"] = group.root
    for flag, folder in folders.items():
        if isinstance(folder, str | Path) and Path(folder).exists() and not Path(folder).is_dir():
            raise ValueError(
                f"{flag}={str(folder)!r} is an existing file; allowed: a folder (a new one, or one this command wrote)"
            )


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0
    command, args = argv[0], argv[1:]
    if command not in COMMANDS:
        print(
            f"condground: unknown command {command!r}; allowed: {', '.join(COMMANDS)} "
            "(`condground --help` says what each does)",
            file=sys.stderr,
        )
        return 2
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    # A command started by a thread an AV1 encoder left at real-time priority would starve its machine.
    normal_priority()
    import lerobot_condground.registration  # noqa: F401  (our env, policy and processor names, as in LeRobot's scripts)

    script = importlib.import_module(f"lerobot_condground.scripts.{COMMANDS[command][0]}")
    prog = f"condground {command}"
    try:
        cfg = _parse(script, args, prog)
        _check_outputs(cfg)
        script.main(cfg)
    except BAD_INPUT as err:
        print(f"{prog}: {_message(err)}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
