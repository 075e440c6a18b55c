"""`condground diagnose`: representation diagnostics on matched clean/distractor frames (Table II, Figure 2)."""

from lerobot_condground.diagnosis.diagnose import DiagnoseConfig as Config, run_diagnose


def main(cfg: Config) -> None:
    run_diagnose(cfg)
