"""`condground fit`: teacher-forced action errors of a checkpoint on a dataset, in physical units."""

from lerobot_condground.diagnosis.fit import FitConfig as Config, run_fit


def main(cfg: Config) -> None:
    run_fit(cfg)
