"""`condground augment`: a LeRobotDataset with copy-paste distractors pasted in -> a new LeRobotDataset."""

from lerobot_condground.datasets.augment import AugmentConfig as Config, augment_dataset, format_summary


def main(cfg: Config) -> None:
    print(format_summary(augment_dataset(cfg)))
