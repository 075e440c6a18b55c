"""`condground view`: one episode with its labels in rerun (a .rrd file, or a spawned viewer)."""

from lerobot_condground.diagnosis.view import ViewConfig as Config, run_view


def main(cfg: Config) -> None:
    run_view(cfg)
