"""`condground report`: sweep, diagnose, probe and attention outputs -> one HTML and Markdown report."""

from lerobot_condground.diagnosis.report import ReportConfig as Config, build_report, parse_report_args


def parse(args: list[str]) -> Config:
    """`--input_dir` repeated or comma-separated, besides draccus' one YAML list."""
    return parse_report_args(args)


def main(cfg: Config) -> None:
    html, markdown = build_report(cfg)
    print(f"report: {html} and {markdown}")
