"""Where units of evaluation run: in this process, in spawned worker processes, or on a Ray cluster.

`execute(jobs, ...)` calls `on_done(job, rows)` in this process as each job finishes, whatever the
launcher, so the caller writes its part files and progress in one place.
"""

from __future__ import annotations

import logging
import os

from lerobot_condground.evaluation.units import run_unit

LAUNCHERS = ("local", "ray")


def init_worker(threads: int | None) -> None:
    """Per-process setup of a parallel worker: a fixed number of threads for torch and Mesa."""
    if threads:
        for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "LP_NUM_THREADS"):
            os.environ[var] = str(threads)
        import torch

        torch.set_num_threads(threads)
    os.environ.setdefault("MUJOCO_GL", "egl")


def execute(
    jobs: list[dict], launcher: str, workers: int, threads: int | None, ray_address: str | None, on_done
) -> None:
    """Runs jobs on the chosen launcher; on_done(job, rows) is called in this process as each finishes."""
    if launcher == "ray":
        _execute_ray(jobs, workers, threads, ray_address, on_done)
    elif workers == 1 and threads is None:
        # In this process, with its threads as they are; a thread count needs a fresh process, since
        # Mesa reads LP_NUM_THREADS only when it first loads.
        init_worker(None)
        for job in jobs:
            on_done(job, run_unit(job))
    else:
        import multiprocessing as mp
        from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

        # spawn: a fresh interpreter per worker, no forked EGL contexts or torch thread pools.
        with ProcessPoolExecutor(
            workers, mp_context=mp.get_context("spawn"), initializer=init_worker, initargs=(threads,)
        ) as pool:
            pending = {pool.submit(run_unit, job): job for job in jobs}
            try:
                while pending:
                    done, _ = wait(pending, return_when=FIRST_COMPLETED)
                    for future in done:
                        on_done(pending.pop(future), future.result())
            except BaseException:
                for future in pending:
                    future.cancel()
                raise


def _ray_unit(job: dict, threads: int | None) -> list[dict]:
    init_worker(threads)
    return run_unit(job)


def _execute_ray(jobs, workers, threads, ray_address, on_done) -> None:
    import ray

    env_vars = {
        k: os.environ[k]
        for k in ("MUJOCO_GL", "HF_HUB_OFFLINE", "HF_HOME", "HF_LEROBOT_HOME")
        if k in os.environ
    }
    started = not ray.is_initialized()
    if started:
        ray.init(
            address=ray_address,
            num_cpus=None if ray_address else workers,
            include_dashboard=False,
            runtime_env={"env_vars": env_vars},
            log_to_driver=False,
            logging_level=logging.WARNING,
        )
    try:
        task = ray.remote(num_cpus=threads or 1)(_ray_unit)
        pending = {task.remote(job, threads): job for job in jobs}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                on_done(pending.pop(ref), ray.get(ref))
    finally:
        if started:
            ray.shutdown()
