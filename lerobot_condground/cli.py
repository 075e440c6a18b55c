"""`condground`: the plugin's own jobs. Flags follow LeRobot's `--group.key=value` style.

    condground record      expert demonstrations -> LeRobotDataset
    condground bench       simulation, recording and policy throughput
    condground augment     a LeRobotDataset with copy-paste distractors -> a new LeRobotDataset
    condground quickstart  record demos, train and evaluate a small act_modified, print stage tables
    condground sweep       evaluate checkpoints over a grid of conditions -> results.parquet
    condground probe       prompt-swap probe of a prompt-bearing checkpoint
    condground diagnose    representation diagnostics on matched clean/distractor frames (Table II, Figure 2)
    condground attention   per-step cross-attention overlay video of one episode
    condground report      one HTML (and Markdown) report from sweep and diagnosis outputs
    condground prompts     SAM 2 visual prompts + label maps for a hardware LeRobotDataset -> a new LeRobotDataset
    condground prompts-bench  per-frame tracking latency of the prompt segmenters
"""

from __future__ import annotations

import logging
import sys

import draccus

COMMANDS = {
    "record": "Record scripted-expert demonstrations into a LeRobotDataset (v3).",
    "bench": "Measure physics, rendering, env-step, recording and act_modified-vs-ACT throughput here.",
    "augment": "Write a copy of a LeRobotDataset with synthetic distractors pasted in (copy-paste augmentation).",
    "quickstart": "Record demos, train a small act_modified (lerobot-train), evaluate it (lerobot-eval), print stages.",
    "sweep": "Evaluate checkpoints over conditions x seeds x rollouts (resumable, parallel) -> results.parquet.",
    "probe": "Prompt-swap probe: how often a competitor's crop as prompt makes the policy select the competitor.",
    "diagnose": "Representation diagnostics of an ACT-family checkpoint on matched clean/distractor frames.",
    "attention": "Per-step cross-attention of one head overlaid on the camera, as a video with stills.",
    "report": "Turn sweep, diagnose, probe and attention outputs into one HTML + Markdown report.",
    "prompts": "Add prompt crops, segmentation and phase (SAM 2 or color tracking) to a hardware dataset, as a copy.",
    "prompts-bench": "Per-frame tracking latency of the prompt segmenters (color, SAM 2) on this machine.",
}


def _usage() -> str:
    lines = ["usage: condground <command> [--group.key=value ...]", "", "commands:"]
    lines += [f"  {name:<13} {text}" for name, text in COMMANDS.items()]
    lines += ["", "`condground <command> --help` lists the flags of a command."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0
    command, args = argv[0], argv[1:]
    if command not in COMMANDS:
        print(f"condground: unknown command {command!r}; allowed: {', '.join(COMMANDS)}\n\n{_usage()}", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if command == "record":
        from lerobot_condground.record import RecordConfig, format_summary, record

        cfg = draccus.parse(RecordConfig, args=args, prog="condground record")
        print(format_summary(record(cfg)))
    elif command == "bench":
        from lerobot_condground.bench import BenchConfig, run_bench

        args = ["--json=true" if a == "--json" else a for a in args]
        cfg = draccus.parse(BenchConfig, args=args, prog="condground bench")
        run_bench(cfg)
    elif command == "augment":
        from lerobot_condground.augment import AugmentConfig, augment_dataset, format_summary

        cfg = draccus.parse(AugmentConfig, args=args, prog="condground augment")
        try:
            print(format_summary(augment_dataset(cfg)))
        except (ValueError, FileNotFoundError, FileExistsError) as err:  # bad input: one line, no traceback
            print(f"condground augment: {err}", file=sys.stderr)
            return 2
    elif command == "quickstart":
        from lerobot_condground.quickstart import QuickstartConfig, run_quickstart

        cfg = draccus.parse(QuickstartConfig, args=args, prog="condground quickstart")
        run_quickstart(cfg)
    else:
        return _checked_command(command, args)
    return 0


def _checked_command(command: str, args: list[str]) -> int:
    """The diagnosis and prompt commands: bad input (grid, checkpoint, results directory, dataset, click)
    is one line, no traceback."""
    try:
        if command == "prompts":
            from lerobot_condground.prompts import PromptsConfig, format_summary, label_dataset

            print(format_summary(label_dataset(draccus.parse(PromptsConfig, args=args, prog="condground prompts"))))
        elif command == "prompts-bench":
            from lerobot_condground.prompts import PromptsBenchConfig, run_bench

            args = ["--json=true" if a == "--json" else a for a in args]
            run_bench(draccus.parse(PromptsBenchConfig, args=args, prog="condground prompts-bench"))
        elif command == "sweep":
            from lerobot_condground.sweep import SweepConfig, run_sweep

            run_sweep(draccus.parse(SweepConfig, args=args, prog="condground sweep"))
        elif command == "probe":
            from lerobot_condground.probe import ProbeConfig, run_probe

            run_probe(draccus.parse(ProbeConfig, args=args, prog="condground probe"))
        elif command == "diagnose":
            from lerobot_condground.diagnose import DiagnoseConfig, run_diagnose

            run_diagnose(draccus.parse(DiagnoseConfig, args=args, prog="condground diagnose"))
        elif command == "attention":
            from lerobot_condground.attention_view import AttentionConfig, run_attention

            run_attention(draccus.parse(AttentionConfig, args=args, prog="condground attention"))
        elif command == "report":
            from lerobot_condground.report import build_report, parse_report_args

            html, markdown = build_report(parse_report_args(args))
            print(f"report: {html} and {markdown}")
    except (ValueError, FileNotFoundError, FileExistsError) as err:
        print(f"condground {command}: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
