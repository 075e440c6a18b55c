"""The `condground report` command line."""

from __future__ import annotations

from dataclasses import dataclass, field

import draccus

from lerobot_condground.core.configs import comma_items


@dataclass
class ReportConfig:
    # Output directories of `condground sweep`, `diagnose`, `probe`, `attention` and `subgoals`, in any mix.
    # Repeat the flag or separate directories with commas.
    input_dir: list[str] = field(default_factory=list)
    # The HTML file; the Markdown version and its figure folder (FILE_files/) go beside it.
    output: str = "outputs/report/report.html"
    title: str = "Conditional visual grounding: diagnosis report"


def parse_report_args(argv: list[str]) -> ReportConfig:
    """draccus reads a list flag only as one YAML list (`--input_dir=[A,B]`); this also accepts the
    flag repeated (`--input_dir=A --input_dir=B`, `--input_dir A`) and comma-separated values."""
    dirs: list[str] = []
    rest: list[str] = []
    title = None
    i = 0
    while i < len(argv):
        arg = argv[i]
        if arg.startswith("--title="):  # taken as written: draccus would read "A: B" as a YAML mapping
            title = arg.partition("=")[2]
            i += 1
            continue
        if arg.startswith("--input_dir="):
            value = arg.partition("=")[2]
        elif arg == "--input_dir" and i + 1 < len(argv):
            i += 1
            value = argv[i]
        else:
            rest.append(arg)
            i += 1
            continue
        i += 1
        value = value.strip()
        if value.startswith("[") and value.endswith("]"):
            value = value[1:-1]
        dirs += [v.strip("'\"") for v in comma_items(value, "--input_dir")]
    cfg = draccus.parse(ReportConfig, args=rest, prog="condground report")
    cfg.input_dir = [*cfg.input_dir, *dirs]
    if title is not None:
        cfg.title = title
    return cfg
