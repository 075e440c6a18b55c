"""`condground prompts-bench`: per-frame tracking latency of the prompt segmenters on this machine."""

from lerobot_condground.bench.prompts import PromptsBenchConfig as Config, run_bench


def main(cfg: Config) -> None:
    run_bench(cfg)
