"""`condground pi05-bench`: seconds per training step and peak memory of the full-size `pi05_grounded` with the
regularizer and gradient checkpointing on and off, and `select_action` latency (made for a GPU machine)."""

from lerobot_condground.bench.pi05 import Pi05BenchConfig as Config, bench_pi05


def main(cfg: Config) -> None:
    for key, value in bench_pi05(cfg).items():
        print(f"{key}: {value:.4g}" if isinstance(value, float) else f"{key}: {value}", flush=True)
