"""`condground merge`: LeRobotDatasets merged into one, with the provenance of every episode."""

from lerobot_condground.datasets.merge import MergeConfig as Config, format_summary, merge_datasets


def main(cfg: Config) -> None:
    print(format_summary(merge_datasets(cfg)))
