"""How near this core's limit a training step at the CPU configuration runs, and what brings it nearer.

- The ceiling: the FLOPs of one training sample (forward and backward, `torch.utils.flop_counter`) and this
  core's measured peak (a matmul and a 3x3 convolution), fp32 and, where the CPU multiplies bf16 natively (AMX,
  AVX-512 BF16), bf16.
- Each option against the current path (`condground train`: the frame cache, fp32), `standard` and `full`
  each on its own loader, in alternating rounds: channels-last memory order, `torch.compile` (compile time
  reported apart), oneDNN's bf16 arithmetic for fp32 convolutions and matmuls and bf16 autocast (both where
  bf16 is native), and LeRobot's own path (no frame cache), against which `train_config_speedup` is taken.
- The kept path (`core.training.speed_flags`) at other batch sizes, in samples per second, in alternating rounds
  with the configuration's batch.
- One run on two threads against two runs on one thread each, in processes started together.
- A profile of the kept path's steps: seconds in the loader, the preprocessor, forward, backward and the
  optimizer, and by kind of operator.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import statistics
import time
from queue import Empty

import torch

from lerobot_condground.bench.training import (
    PHASES,
    Option,
    Trainer,
    alternating_rates,
    filled_cache,
    policy_config,
    ratio,
)
from lerobot_condground.core.training import native_bf16, speed_flags

VARIANTS = ("standard", "full")
# Operator kinds of the profile, by pieces of the aten name; the first that matches wins.
OP_KINDS = (
    ("convolution", ("conv",)),
    ("normalization", ("batch_norm", "layer_norm")),
    ("matmul", ("addmm", "mm", "bmm", "matmul", "linear", "scaled_dot_product")),
    ("optimizer", ("adam", "_foreach")),
)


def kept_option() -> Option:
    """What `core.training.speed_flags` turns on here, on `condground train`'s frame cache."""
    flags = set(speed_flags())
    return Option(channels_last="--policy.channels_last=true" in flags, amp="--policy.use_amp=true" in flags)


def named_options(with_compile: bool) -> dict[str, Option]:
    found = {"lerobot": Option(cache=False), "current": Option(), "channels_last": Option(channels_last=True)}
    if with_compile:
        found["compile"] = Option(compile=True)
    if native_bf16():
        found |= {
            "onednn_bf16": Option(onednn_bf16=True),
            "bf16": Option(amp=True),
            "bf16_channels_last": Option(amp=True, channels_last=True),
        }
    return found | {"kept": kept_option()}


def flops_per_sample(trainer: Trainer) -> float:
    """FLOPs of forward and backward per sample (the counter counts matmuls and convolutions, where a step's
    arithmetic is)."""
    from torch.utils.flop_counter import FlopCounterMode

    batch = trainer.preprocessor(trainer.next_batch())
    with FlopCounterMode(display=False) as counter:
        loss, _ = trainer.policy.forward(batch)
        loss.backward()
    trainer.optimizer.zero_grad()
    return counter.get_total_flops() / trainer.batch_size


def peak_gflops(dtype: torch.dtype, seconds: float) -> dict[str, float]:
    """Sustained GFLOP/s on torch's threads of a 1024x1024 matmul (MKL) and of a 3x3 convolution (oneDNN, the
    backbone's kind of layer), the best of three windows each: on AMD CPUs MKL's matmul runs well below the core's
    peak, which oneDNN's convolutions reach, so the ceiling is the larger of the two."""
    a, b = (torch.randn(1024, 1024, dtype=dtype) for _ in range(2))
    conv = torch.nn.Conv2d(256, 256, 3, padding=1, bias=False).to(dtype)
    x = torch.randn(16, 256, 32, 32, dtype=dtype)
    kernels = {
        "matmul": (lambda: a @ b, 2 * 1024**3),
        "conv3x3": (lambda: conv(x), 2 * 16 * 32 * 32 * 256 * 256 * 9),
    }
    found = {}
    with torch.no_grad():
        for name, (kernel, flops) in kernels.items():
            kernel()
            best = 0.0
            for _ in range(3):
                count, start = 0, time.perf_counter()
                while time.perf_counter() - start < seconds / 6:
                    kernel()
                    count += 1
                best = max(best, flops * count / (time.perf_counter() - start) / 1e9)
            found[name] = best
    return found


def profile_steps(trainer: Trainer, steps: int) -> dict:
    """Seconds per step by phase, and by operator kind (each operator's own time, not its children's)."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU], acc_events=True) as prof:
        for _ in range(steps):
            trainer.step()
    events = prof.key_averages()
    kinds = dict.fromkeys([kind for kind, _ in OP_KINDS] + ["other"], 0.0)
    for e in events:
        if e.key.startswith("aten::"):
            name = e.key.removeprefix("aten::")
            kind = next((k for k, parts in OP_KINDS if any(p in name for p in parts)), "other")
            kinds[kind] += e.self_cpu_time_total / 1e6 / steps
    return {
        "phases_s": {e.key: e.cpu_time_total / 1e6 / steps for e in events if e.key in PHASES},
        "operators_s": kinds,
    }


def _process_rate(repo_id, root, option, dim_model, batch_size, threads, steps, barrier, queue):
    """One training run in its own process: build, fill the frame cache, warm up, wait, time `steps` steps."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_condground.evaluation.checkpoints import register_plugins

    register_plugins()  # a fresh process: act_modified and its processor steps
    torch.set_num_threads(threads)
    cache = filled_cache(LeRobotDataset(repo_id, root=root))
    trainer = Trainer(policy_config("standard", option, dim_model), option, repo_id, root, batch_size, cache)
    trainer.step()
    barrier.wait()
    queue.put(trainer.samples_per_s(steps))


def thread_layouts(repo_id, root, option, dim_model, batch_size, steps) -> dict[str, float]:
    """Samples/s of all runs together: one run on two threads, and two runs on one thread each."""
    context = multiprocessing.get_context("spawn")
    rates = {}
    for name, processes, threads in (("1x2", 1, 2), ("2x1", 2, 1)):
        barrier, queue = context.Barrier(processes), context.Queue()
        args = (repo_id, root, option, dim_model, batch_size, threads, steps, barrier, queue)
        workers = [context.Process(target=_process_rate, args=args) for _ in range(processes)]
        for w in workers:
            w.start()
        found = []
        while len(found) < processes:
            if any(w.exitcode for w in workers):
                raise RuntimeError(f"a {name} training process failed (exit {[w.exitcode for w in workers]})")
            try:
                found.append(queue.get(timeout=5))
            except Empty:  # look at the processes again
                continue
        for w in workers:
            w.join()
        rates[name] = sum(found)
    return rates


def bench_options(repo_id: str, root: str, cfg, rounds: int, cache) -> dict:
    """The ceiling, every option against the current path, batch sizes, thread layouts, the profile."""
    options = named_options(cfg.compile)

    def trainer(variant: str, option: Option, batch_size: int = cfg.batch_size) -> Trainer:
        return Trainer(
            policy_config(variant, option, cfg.dim_model), option, repo_id, root, batch_size, cache
        )

    trainers = {f"{v}.{name}": trainer(v, o) for v in VARIANTS for name, o in options.items()}
    flops = {v: flops_per_sample(trainers[f"{v}.current"]) for v in VARIANTS}
    rates = alternating_rates(trainers, cfg.steps, rounds)
    compile_s = {name: t.compile_s for name, t in trainers.items() if t.option.compile}
    del trainers  # a model and its optimizer state each
    kept = options["kept"]
    peaks = {"fp32": peak_gflops(torch.float32, cfg.peak_seconds)}
    if native_bf16():
        peaks["bf16"] = peak_gflops(torch.bfloat16, cfg.peak_seconds)
    sizes = sorted({cfg.batch_size, *cfg.batch_list()})
    batches = alternating_rates({str(n): trainer("standard", kept, n) for n in sizes}, cfg.steps, rounds)
    profiled = trainer("standard", kept)
    profiled.step()
    result = {
        "train_flops_per_sample": flops,
        "train_peak_gflops": peaks,
        "train_option_samples_per_s": {name: statistics.median(r) for name, r in rates.items()},
        "train_option_speedup": {
            name: ratio(rates, name, f"{name.split('.')[0]}.current") for name in rates
        },
        "train_compile_s": compile_s,
        "train_kept_options": [f for f, on in dataclasses.asdict(kept).items() if on],
        # The kept path against LeRobot's plain fp32 path at the same configuration, in the same rounds.
        "train_config_speedup": ratio(rates, "standard.kept", "standard.lerobot"),
        # Achieved FLOP/s of the kept path over the measured peak of the precision it computes in.
        "train_flop_fraction": flops["standard"] * statistics.median(rates["standard.kept"]) / 1e9
        / max(peaks["bf16" if kept.amp else "fp32"].values()),
        # The kept path at each batch size (the learning rate is not scaled here: this is speed only), in
        # alternating rounds with the configuration's batch, and each against it.
        "train_batch_samples_per_s": {n: statistics.median(r) for n, r in batches.items()},
        "train_batch_speedup": {n: ratio(batches, n, str(cfg.batch_size)) for n in batches},
        "train_profile": profile_steps(profiled, cfg.steps),
    }  # fmt: skip
    if cfg.thread_layouts:
        layouts = thread_layouts(repo_id, root, kept, cfg.dim_model, cfg.batch_size, cfg.steps)
        result |= {
            "train_thread_layouts_samples_per_s": layouts,
            "train_2x1_over_1x2": layouts["2x1"] / layouts["1x2"],
        }
    return result
