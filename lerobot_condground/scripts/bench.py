"""`condground bench`: physics, rendering, env-step, recording, policy and sweep throughput here."""

from lerobot_condground.bench.throughput import BenchConfig as Config, run_bench


def main(cfg: Config) -> None:
    run_bench(cfg)
