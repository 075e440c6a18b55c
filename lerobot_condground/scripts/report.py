"""`condground report`: sweep, diagnose, probe and attention outputs -> one HTML and Markdown report."""

from lerobot_condground.diagnosis.report import (
    ReportConfig as Config,
    build_report,
)


def main(cfg: Config) -> None:
    html, markdown = build_report(cfg)
    print(f"report: {html} and {markdown}")
