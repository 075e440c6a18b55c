"""`condground report`: sweep and diagnosis outputs -> one self-contained HTML report and a Markdown twin.

`inputs` reads and checks the output directories, `sections` decides what each section says (with
`formatting` for the numbers and `figures` for the plots), and `render` fills the Jinja2 templates.
"""

from __future__ import annotations

from pathlib import Path

from .config import ReportConfig, parse_report_args
from .inputs import Inputs, load_inputs
from .render import render_html, render_markdown, write_report
from .sections import Document, build_document

__all__ = [
    "Document",
    "Inputs",
    "ReportConfig",
    "build_document",
    "build_report",
    "load_inputs",
    "parse_report_args",
    "render_html",
    "render_markdown",
]


def build_report(cfg: ReportConfig) -> tuple[Path, Path]:
    """Writes cfg.output (HTML) and the Markdown version beside it (same name, .md, figures in NAME_files/).
    Returns (html_path, markdown_path). Raises ValueError for unusable inputs."""
    return write_report(build_document(load_inputs(list(cfg.input_dir)), cfg), Path(cfg.output))
