"""`condground subgoals`: InstrumentRouting-v0 per subgoal under cue / no_cue / explicit, with real LeRobot
checkpoints in real MuJoCo, and on the UR3e's hardware path against the loopback fake controller with an
operator typing into the command's stdin."""

import json
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import binomtest

from helpers import make_checkpoint, run_cli
from lerobot_condground.cli import main
from lerobot_condground.core.routing import DESTINATION, SUBGOALS
from lerobot_condground.evaluation.results import read_metadata, read_table, write_table
from lerobot_condground.evaluation.subgoals import check_same_run
from ur_fake import free_loopback_host, start_fake_controller

HEIGHT, WIDTH = 64, 80
ROUTING = ("--env.task=InstrumentRouting-v0",)


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory) -> dict[str, Path]:
    """Stock ACT with random weights on the routing env's cameras (top, wrist) at 64x80: `plain`, and `cue`
    whose saved preprocessor draws the RGB cue (the condground_rgb_cue step, as a prompt-trained one's does)."""
    from lerobot.processor import NormalizerProcessorStep, PolicyProcessorPipeline

    from lerobot_condground.processors.rgb_cue import RgbCueStep

    root = tmp_path_factory.mktemp("routing_act")
    plain = make_checkpoint(
        root / "plain", policy_type="act", height=HEIGHT, width=WIDTH, cameras=("top", "wrist")
    )
    cue = Path(shutil.copytree(plain, root / "cue"))
    pre = PolicyProcessorPipeline.from_pretrained(cue, config_filename="policy_preprocessor.json")
    normalizer = next(i for i, step in enumerate(pre.steps) if isinstance(step, NormalizerProcessorStep))
    pre.steps.insert(normalizer, RgbCueStep())
    for stale in cue.glob("policy_preprocessor_step_*"):  # state files are named by step index
        stale.unlink()
    pre.save_pretrained(cue)
    return {"plain": plain, "cue": cue}


def subgoals_cli(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return run_cli(
        "condground", "subgoals", *ROUTING, "--progress=false", "--policy.device=cpu", *args, check=check
    )


def cell_text(k: int, n: int) -> str:
    ci = binomtest(k, n).proportion_ci(method="wilson")
    return f"{k}/{n} {k / n:.0%} [{ci.low:.0%}, {ci.high:.0%}]"


def test_three_conditions_in_one_directory_give_paired_rows_and_a_wilson_table(tmp_path, checkpoints):
    out = tmp_path / "study"
    subgoals_cli("--policy.path=expert", "--condition=explicit", "--trials=1", f"--output_dir={out}")
    act = (f"--policy.path={checkpoints['cue']}", "--trials=2", "--subgoals=place,route", "--max_steps=3")
    subgoals_cli(*act, "--condition=cue", f"--output_dir={out}")
    last = subgoals_cli(*act, "--condition=no_cue", f"--output_dir={out}")

    rows = read_table(out / "results.parquet")
    assert len(rows) == 5 + 2 * 2 * 2
    assert set(rows.scored_by) == {"env"} and set(rows.task) == {"InstrumentRouting-v0"}
    expert = rows[rows.condition == "explicit"]
    assert list(expert.subgoal) == list(SUBGOALS)  # the oracle reaches every subgoal from its own start
    assert expert.success.all() and (expert.steps < 300).all() and not expert.truncated.any()
    assert set(expert.condition_spec) == {json.dumps({"cue": None, "instruction": "explicit"})}
    policy = rows[rows.condition != "explicit"]
    assert (policy.steps == 3).all() and policy.truncated.all() and not policy.success.any()
    assert sorted(zip(policy.condition, policy.subgoal, policy.episode)) == sorted(
        (c, s, e) for c in ("cue", "no_cue") for s in ("route", "place") for e in (0, 1)
    )
    specs = {c: json.loads(policy[policy.condition == c].condition_spec.iloc[0]) for c in ("cue", "no_cue")}
    assert specs == {
        "cue": {"cue": True, "instruction": "generic"},
        "no_cue": {"cue": False, "instruction": "generic"},
    }
    # Paired: trial t of a subgoal has one layout whatever the condition or checkpoint; subgoals differ.
    per_trial = rows.groupby(["subgoal", "episode"])
    assert (per_trial.layout_seed.nunique() == 1).all() and (per_trial.destination.nunique() == 1).all()
    assert rows.drop_duplicates(["subgoal", "episode"]).layout_seed.is_unique

    # The table, recomputed from the rows with scipy's Wilson interval.
    cells = json.loads((out / "subgoals_table.json").read_text())["cells"]
    pools = {"routing": ("route", "place"), "overall": SUBGOALS}
    expected = {}
    for condition, group in rows.groupby("condition"):
        for name in (*SUBGOALS, *pools):
            members = group[group.subgoal.isin(pools.get(name, (name,)))]
            if len(members):
                expected[(condition, name)] = (int(members.success.sum()), len(members))
    assert {(c["condition"], c["subgoal"]): (c["k"], c["n"]) for c in cells} == expected
    for c in cells:
        ci = binomtest(c["k"], c["n"]).proportion_ci(method="wilson")
        assert (c["low"], c["high"]) == pytest.approx((ci.low, ci.high), abs=1e-12)
        assert c["rate"] == c["k"] / c["n"]
    printed = last.stdout
    assert "| subgoal | cue | no_cue | explicit |" in printed
    assert f"| overall | {cell_text(0, 4)} | {cell_text(0, 4)} | {cell_text(5, 5)} |" in printed
    assert f"| pick | — | — | {cell_text(1, 1)} |" in printed and "| route (routing) |" in printed
    table = "\n".join(line for line in printed.splitlines() if line.startswith("|"))
    assert table.count("\n") == 1 + 7 and table in (out / "subgoals_table.md").read_text()

    # A rerun resumes (nothing left to do); other settings for a condition already run are refused.
    again = subgoals_cli(*act, "--condition=no_cue", f"--output_dir={out}")
    assert "4 trials; 4 already done" in again.stdout and len(read_table(out / "results.parquet")) == len(
        rows
    )
    refused = subgoals_cli(*act, "--condition=no_cue", "--seed=7", f"--output_dir={out}", check=False)
    assert refused.returncode == 2 and "differences: seed: 1000000 -> 7" in refused.stderr
    # Settings no trial was scored under pin nothing (a run that failed before its first trial).
    manifest = json.loads((out / "subgoals.json").read_text())
    other = {**manifest["runs"]["no_cue"], "seed": 7}
    kept = check_same_run(out, "sim", "no_cue", other, rows[rows.condition != "no_cue"])
    assert "no_cue" not in kept["runs"] and set(kept["runs"]) == {"cue", "explicit"}
    # A row the manifest never asked for (a subgoal the cue run did not run) is an error, never counted.
    hostile = rows.copy()
    hostile.loc[hostile.index[hostile.condition == "cue"][0], "subgoal"] = "pick"
    original = (out / "results.parquet").read_bytes()
    write_table(hostile, out / "results.parquet", metadata=read_metadata(out / "results.parquet"))
    outside = subgoals_cli(*act, "--condition=cue", f"--output_dir={out}", check=False)
    assert outside.returncode == 2 and f"{out / 'results.parquet'}: row " in outside.stderr
    assert "(condition='cue', subgoal='pick', episode=" in outside.stderr
    from lerobot_condground.diagnosis.report import ReportConfig, build_report

    with pytest.raises(ValueError, match="subgoal='pick'.*is not part of the run subgoals.json describes"):
        build_report(ReportConfig(input_dir=[str(out)], output=str(tmp_path / "hostile.html")))
    (out / "results.parquet").write_bytes(original)

    _, markdown = build_report(ReportConfig(input_dir=[str(out)], output=str(tmp_path / "report.html")))
    text = markdown.read_text()
    assert "| subgoal | this report: cue | this report: no_cue | this report: explicit | paper: cue |" in text
    assert (
        "| overall | 0.0% [0.0, 49.0] (0/4) | 0.0% [0.0, 49.0] (0/4) | 100.0% [56.6, 100.0] (5/5) | 25/25 | 20/25 | 25/25 |"
        in text
    )


def test_the_cue_highlights_the_destination_and_no_cue_shows_the_same_frame_unmarked(checkpoints):
    """What the policy sees: the same scene, with the destination's pixels recoloured under `cue` only."""
    from lerobot_condground.core.configs import PolicyRefConfig
    from lerobot_condground.evaluation.checkpoints import describe_checkpoint, load_policy
    from lerobot_condground.evaluation.rollout import run_episodes
    from lerobot_condground.evaluation.subgoals import SubgoalsConfig, env_settings, sim_spec

    seen = {}
    for condition in ("cue", "no_cue"):
        cfg = SubgoalsConfig(
            policy=PolicyRefConfig(path=str(checkpoints["cue"])), condition=condition, max_steps=1
        )
        described = describe_checkpoint(cfg.policy.path)
        spec = sim_spec(cfg, described, env_settings(condition, described))
        loaded = load_policy(described.path, spec.lerobot_config(), "cpu")
        env = spec.make()

        def keep(step, batch, observations, active, condition=condition):
            seen[condition] = (batch["observation.images.top"][0], observations[0]["segmentation"])

        run_episodes(loaded, [env], [123], max_steps=1, on_step=keep)
        env.close()
    cued, labels = seen["cue"]
    plain, blank = seen["no_cue"]
    destination = labels == DESTINATION
    assert destination.sum() > 20 and not blank.any()
    changed = (cued - plain).abs().sum(0).numpy() > 1e-6
    assert (changed == destination).all()


@pytest.mark.parametrize(
    "args, message",
    [
        (["--condition=maybe"], "--condition='maybe' is not allowed; allowed: cue, no_cue, explicit"),
        (["--subgoals=pick,grasp"], "--subgoals='pick,grasp' is not allowed; allowed: pick, inspect, route, place, home"),
        (["--trials=0"], "--trials=0 is not allowed; allowed: an integer >= 1"),
        (["--env.task=PickPlaceRandomBin-v0"], "--env.task='PickPlaceRandomBin-v0' is not allowed; allowed: InstrumentRouting-v0"),
        (["--env.competitor_pool=augmentation"], "--env.competitor_pool do not apply to InstrumentRouting-v0"),
        (
            ["--env.observation_height=96", "--env.observation_width=128"],
            "reads cameras top 64x80, wrist 64x80, but InstrumentRouting-v0 (rendering both at one size) gives top "
            "96x128, wrist 96x128; set that size with --env.observation_height/--env.observation_width",
        ),
        (["--policy.path=FRONT"], "reads cameras front 64x80, but InstrumentRouting-v0 (rendering both at one size) gives top 64x80, wrist 64x80"),
        (["--policy.path=PROMPTED"], "reads prompt crops (act_modified with use_prompts), which InstrumentRouting-v0 does not give"),
        (["--policy.path=PLAIN", "--condition=cue"], "has no enabled condground_rgb_cue step; evaluate it with --condition=explicit"),
        (["--robot.type=ur3e", "--robot.host=127.0.0.1", "--condition=cue"], "--condition=cue cannot run on the real arm"),
        (["--robot.type=ur3e", "--robot.backend=sim"], "--robot.backend=sim drives the pick-and-place twin"),
        (
            ["--robot.type=ur3e", "--robot.host=127.0.0.1"],
            "reads cameras top 64x80, wrist 64x80, but the ur3e robot gives none; give the robot those cameras at "
            "those sizes with --robot.cameras=",
        ),
    ],
)  # fmt: skip
def test_bad_input_is_one_clear_error_before_any_work(args, message, checkpoints, tmp_path, capsys):
    if "--policy.path=FRONT" in args:
        front = make_checkpoint(
            tmp_path / "front", policy_type="act", height=HEIGHT, width=WIDTH, cameras=("front",)
        )
        args = [f"--policy.path={front}", "--condition=explicit"]
    if "--policy.path=PROMPTED" in args:
        prompted = make_checkpoint(
            tmp_path / "prompted", height=HEIGHT, width=WIDTH, cameras=("top", "wrist")
        )
        args = [f"--policy.path={prompted}", "--condition=explicit"]
    args = [a.replace("PLAIN", str(checkpoints["plain"])) for a in args]
    defaults = [
        f"--policy.path={checkpoints['cue']}",
        *ROUTING,
        "--condition=no_cue",
        f"--output_dir={tmp_path / 'out'}",
    ]
    assert main(["subgoals", *defaults, *args]) == 2
    lines = [
        line for line in capsys.readouterr().err.splitlines() if line.startswith("condground subgoals: ")
    ]
    assert len(lines) == 1 and message in lines[0], lines
    assert not (tmp_path / "out").exists()


# The command as an operator starts it, with one camera type for this test: a frame without hardware.
OPERATOR_SCRIPT = textwrap.dedent("""
    import sys
    from dataclasses import dataclass

    import numpy as np
    from lerobot.cameras import Camera, CameraConfig


    @CameraConfig.register_subclass("still")
    @dataclass(kw_only=True)
    class StillCameraConfig(CameraConfig):
        pass


    class StillCamera(Camera):
        def __init__(self, config):
            super().__init__(config)
            self.connected = False

        @property
        def is_connected(self):
            return self.connected

        @staticmethod
        def find_cameras():
            return []

        def connect(self, warmup=True):
            self.connected = True

        def read(self, color_mode=None):
            return np.full((self.height, self.width, 3), 128, np.uint8)

        def async_read(self, timeout_ms=200):
            return self.read()

        def disconnect(self):
            self.connected = False


    if __name__ == "__main__":  # the robot's worker process is spawned, which imports this module again
        from lerobot_condground.cli import main

        sys.exit(main(sys.argv[1:]))
""")


def default_sigint() -> None:
    """Ctrl-C as a terminal gives it. A shell starts background jobs (`make test &`) with SIGINT ignored,
    their children inherit that, and Python then installs no KeyboardInterrupt: the operator's Ctrl-C
    would do nothing."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_operator_scored_trials_on_the_arm_through_the_fake_controller(tmp_path, checkpoints):
    """Two trials (pick, route) of the cue checkpoint with its cue hidden: the arm goes to each subgoal's
    simulated start pose, the operator presses Enter, Ctrl-C ends the first trial (not the command), an
    answer that is neither y nor n is asked again, and the scores land in the table. Ctrl-C at the second
    trial's score prompt ends the command with the first trial kept; the same command then runs only the
    second."""
    from lerobot_condground.evaluation.operator_trials import start_states
    from lerobot_condground.evaluation.units import layout_seed

    script = tmp_path / "operator.py"
    script.write_text(OPERATOR_SCRIPT)
    out = tmp_path / "arm"
    still = f"{{type: still, width: {WIDTH}, height: {HEIGHT}, fps: 20}}"
    q0 = [0.1, -1.6, 1.5, -1.4, -1.57, 0.3]
    starts = {
        s: start_states(s, [layout_seed(1_000_000, SUBGOALS.index(s), 0)])[0] for s in ("pick", "route")
    }
    command = [
        sys.executable, str(script), "subgoals", *ROUTING, f"--policy.path={checkpoints['cue']}",
        "--condition=no_cue", "--trials=1", "--subgoals=route,pick", "--max_steps=30", "--policy.device=cpu",
        f"--output_dir={out}", "--robot.type=ur3e", "--robot.connect_timeout_s=60",
        f"--robot.cameras={{top: {still}, wrist: {still}}}",
    ]  # fmt: skip
    poses = {}

    def operate(fake, last_answer: str) -> str:
        """Plays the operator; `last_answer` is typed at the route trial's score prompt (or Ctrl-C)."""
        proc = subprocess.Popen(
            [*command, f"--robot.host={fake.host}"], preexec_fn=default_sigint,
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1,
        )  # fmt: skip
        transcript = []
        watchdog = threading.Timer(300, proc.kill)  # a command stuck at a prompt fails the test, not CI
        watchdog.start()
        try:
            for line in proc.stdout:
                transcript.append(line)
                if line.startswith("Set up:"):  # the arm waits at the start pose for the operator
                    subgoal = "pick" if "lies on the table" in line else "route"
                    poses[subgoal] = np.array(fake.state()["actual_q"])
                    proc.stdin.write("\n")
                elif "Running the policy" in line and "pick up the instrument" in line:
                    proc.send_signal(signal.SIGINT)
                elif line.startswith("Stopped by Ctrl-C after"):
                    proc.stdin.write("maybe\ny\n")
                elif line.startswith("Step limit reached"):
                    if last_answer == "ctrl-c":  # at a prompt, Ctrl-C ends the session, not only the trial
                        proc.send_signal(signal.SIGINT)
                    else:
                        proc.stdin.write(last_answer)
                proc.stdin.flush()
            proc.wait(timeout=60)
        finally:
            watchdog.cancel()
            proc.kill()
        text = "".join(transcript)
        assert proc.returncode == 0, text[-3000:] + proc.stderr.read()[-3000:]
        return text

    with start_fake_controller(
        free_loopback_host(), servers=("rtde", "dashboard", "gripper", "script"), actual_q=q0
    ) as fake:
        stopped = operate(fake, "ctrl-c")
        assert "Stopped by Ctrl-C before Trial 2/2 (route #1" in stopped, stopped[-3000:]
        assert list(read_table(out / "results.parquet").subgoal) == ["pick"]
        text = operate(fake, "n\n")  # the same command scores only what is left
    assert "2 trials; 1 already done" in text and "pick up the instrument" not in text
    for subgoal, start in starts.items():
        np.testing.assert_allclose(poses[subgoal], start.q, atol=0.02)
    assert f"belongs in the {starts['route'].destination} container" in text
    assert "Enter closes the gripper" in stopped and "Please answer y or n." in stopped
    rows = read_table(out / "results.parquet").set_index("subgoal")
    assert list(rows.index) == ["pick", "route"]
    assert rows.loc["pick", "success"] and not rows.loc["route", "success"]
    assert rows.loc["pick", "steps"] < 30 and not rows.loc["pick", "truncated"]  # Ctrl-C ended it
    assert rows.loc["route", "steps"] == 30 and rows.loc["route", "truncated"]
    assert set(rows.scored_by) == {"operator"} and rows.stage.isna().all() and rows.placed_in.isna().all()
    assert rows.loc["route", "destination"] == starts["route"].destination
    assert f"| overall | {cell_text(1, 2)} |" in text


def test_ctrl_c_at_a_prompt_is_never_lost_whichever_thread_takes_the_signal():
    """Python runs a signal's handler only between bytecodes of the main thread. A SIGINT that arrives while
    the main thread is in C code on its way into read() (`input` writing the prompt, as a scripted operator
    answers the line before it), or that a helper thread takes (policy, camera and tqdm threads run beside
    the prompt), leaves `input` from a pipe blocked with the KeyboardInterrupt pending until a line comes.
    Here the signal goes to a helper thread while the operator types nothing: the prompt must end at once."""
    script = textwrap.dedent(
        """
        import signal, threading, time
        from lerobot_condground.evaluation.operator_trials import ask

        def interrupt():
            time.sleep(1.0)
            signal.pthread_kill(threading.get_ident(), signal.SIGINT)  # to this thread, not the main one

        threading.Thread(target=interrupt, daemon=True).start()
        ask("Did it succeed? [y/n] ", {"y": True, "n": False})
        """
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", script],
        preexec_fn=default_sigint,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )  # stdin stays open and empty: the operator never answers
    started = time.monotonic()
    try:
        proc.wait(timeout=30)  # not communicate(): it would close stdin, and end of input ends the prompt too
    except subprocess.TimeoutExpired:
        pytest.fail("Ctrl-C at the prompt was lost: the command still waited for input 30 s later")
    finally:
        proc.kill()
    err = proc.stderr.read()
    assert b"KeyboardInterrupt" in err and time.monotonic() - started < 30, err[-2000:]
