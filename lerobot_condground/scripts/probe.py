"""`condground probe`: the prompt-swap probe of a prompt-bearing checkpoint."""

from lerobot_condground.diagnosis.probe import ProbeConfig as Config, run_probe


def main(cfg: Config) -> None:
    run_probe(cfg)
