"""The scripts beside published results that compute something of their own: the training minutes that
docs/learning-curve/gpu/device_curve.py reads from `condground train`'s progress bars (resumed runs, tqdm
skipping steps at GPU rates)."""

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def device_curve():
    spec = importlib.util.spec_from_file_location(
        "device_curve", ROOT / "docs/learning-curve/gpu/device_curve.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def bar(done: int, total: int, seconds: int) -> str:
    """One tqdm line as `condground train` writes it."""
    return f"Training:  {100 * done // total}%| | {done}/{total} [{seconds // 60:02d}:{seconds % 60:02d}<00:10,  1.00step/s]"


def test_minutes_add_up_over_a_resumed_run(device_curve, tmp_path):
    # 6000 steps, 2 s a step until a kill at step 2500; resumed from the 2000 checkpoint at 1 s a step.
    first = [bar(k, 6000, 2 * k) for k in range(0, 2501)]
    second = [bar(k, 4000, k) for k in range(0, 4001)]
    log = tmp_path / "run.log"
    log.write_text("\r".join(first) + "\n# resumed\n" + "\r".join(second))
    assert device_curve.elapsed_minutes(log, 1000, 6000) == pytest.approx(2000 / 60)
    # the steps past 2000 of the killed run were lost: they do not count
    assert device_curve.elapsed_minutes(log, 3000, 6000) == pytest.approx((4000 + 1000) / 60)
    assert device_curve.elapsed_minutes(log, 6000, 6000) == pytest.approx((4000 + 4000) / 60)


def test_gpu_logs_skip_steps_and_a_step_not_reached_is_refused(device_curve, tmp_path):
    # At GPU rates tqdm writes every 7th step or so; a run never resumed needs no total.
    log = tmp_path / "run.log"
    log.write_text("\r".join(bar(k, 1500, k // 10) for k in [*range(0, 1200, 7), 1500]))
    assert device_curve.elapsed_minutes(log, 1000) == pytest.approx(
        (994 // 10) / 60
    )  # the last line at or before
    assert device_curve.elapsed_minutes(log, 1500) == pytest.approx(150 / 60)
    cut = tmp_path / "cut.log"
    cut.write_text("\r".join(bar(k, 1500, k) for k in range(0, 800)))  # still training
    with pytest.raises(SystemExit, match="no progress line at step 1000"):
        device_curve.elapsed_minutes(cut, 1000)
