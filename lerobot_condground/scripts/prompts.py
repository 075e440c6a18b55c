"""`condground prompts`: prompt crops, segmentation and phase for a hardware LeRobotDataset -> a labelled copy."""

from lerobot_condground.labelling.prompts import PromptsConfig as Config, format_summary, label_dataset


def main(cfg: Config) -> None:
    print(format_summary(label_dataset(cfg)))
