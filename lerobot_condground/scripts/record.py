"""`condground record`: scripted-expert demonstrations -> a LeRobotDataset (v3), resumable."""

from lerobot_condground.datasets.record import RecordConfig as Config, format_summary, record


def main(cfg: Config) -> None:
    print(format_summary(record(cfg)))
