"""`condground probe`: does the prompt steer which entity the policy selects?

One target and one look-alike competitor of the probed role (default: a receptacle of the target's
color, the paper's cup-selection probe). Every layout runs twice with the same seed: once with the
target's crop as the prompt, once with the competitor's crop in its place. Selection is "placed in
the competitor receptacle" for the receptacle role and "grasped the competitor object" for the object
role. The paper reports 0-1 % competitor selection with the true prompt and 35-91 % swapped.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from lerobot_condground.core import paper
from lerobot_condground.core.conditions import MATCHES, check_task
from lerobot_condground.core.configs import EvalEnvConfig, PolicyRefConfig, check_seed, usable_cores
from lerobot_condground.core.provenance import command_line, versions
from lerobot_condground.evaluation.checkpoints import check_env_fits, describe_checkpoint, resolve_device
from lerobot_condground.evaluation.launchers import execute
from lerobot_condground.evaluation.results import write_table
from lerobot_condground.evaluation.rollout import EnvSpec
from lerobot_condground.evaluation.units import EPISODES_PER_SEED_LIMIT, Unit, make_jobs

ROLES = ("object", "receptacle")
SELECTED = {"object": "selected_competitor_object", "receptacle": "placed_in_competitor_receptacle"}


@dataclass
class ProbeSettings:
    role: str = "receptacle"  # whose prompt is swapped: object or receptacle
    match: str = "color"  # how the competitor looks like the target: color, shape or neither
    episodes: int = 50
    batch_size: int = 10
    seed_offset: int = 2_000_000


@dataclass
class ProbeConfig:
    policy: PolicyRefConfig = field(default_factory=PolicyRefConfig)
    env: EvalEnvConfig = field(default_factory=EvalEnvConfig)
    probe: ProbeSettings = field(default_factory=ProbeSettings)
    output_dir: str = "outputs/probe"
    workers: int | None = None
    progress: bool = True


def run_probe(cfg: ProbeConfig) -> Path:
    from lerobot_condground.evaluation.statistics import paired_difference, rate

    check_task(cfg.env.task)
    if cfg.probe.role not in ROLES:
        raise ValueError(f"Unknown --probe.role={cfg.probe.role!r}; allowed: {', '.join(ROLES)}")
    if cfg.probe.match not in MATCHES:
        raise ValueError(f"Unknown --probe.match={cfg.probe.match!r}; allowed: {', '.join(MATCHES)}")
    if cfg.probe.episodes < 1:
        raise ValueError(f"--probe.episodes={cfg.probe.episodes} must be at least 1")
    check_seed("--probe.seed_offset", cfg.probe.seed_offset, EPISODES_PER_SEED_LIMIT)
    # Its results.parquet would replace another command's (a subgoals run's operator-scored trials).
    foreign = [n for n in ("sweep.json", "subgoals.json") if (Path(cfg.output_dir) / n).exists()]
    if foreign:
        raise FileExistsError(
            f"--output_dir={cfg.output_dir} holds {foreign[0]}, another command's results; allowed: a new folder "
            "or one `condground probe` wrote"
        )
    if cfg.env.condition is not None:
        raise ValueError(
            f"--env.condition={cfg.env.condition!r} is not a probe flag; allowed: the probed competitor "
            "as --probe.role and --probe.match"
        )
    path = cfg.policy.single()
    loaded = describe_checkpoint(path, cfg.policy.label, trust_remote_code=cfg.policy.trust_remote_code)
    if not loaded.needs_prompts:
        raise ValueError(
            f"The prompt-swap probe needs a checkpoint that reads visual prompts (act_modified with "
            f"use_prompts, e.g. --policy.variant=full); {path!r} is {loaded.label!r} without prompts"
        )
    condition = f"{cfg.probe.role}_{cfg.probe.match}_1"
    check_env_fits(loaded, EnvSpec.for_checkpoint(cfg.env, loaded, condition).lerobot_config())
    units = [
        Unit(0, condition, 0, s, min(s + cfg.probe.batch_size, cfg.probe.episodes))
        for s in range(0, cfg.probe.episodes, cfg.probe.batch_size)
    ]
    jobs = []
    for prompt in ("target", "swapped"):
        for job in make_jobs(
            cfg.env, cfg.probe.seed_offset, resolve_device(cfg.policy.device), units, [loaded]
        ):
            job["identity"]["prompt"] = prompt
            job["swap"] = cfg.probe.role if prompt == "swapped" else None
            jobs.append(job)

    from tqdm import tqdm

    rows: list[dict] = []
    bar = tqdm(total=2 * cfg.probe.episodes, unit="ep", desc="probe", disable=not cfg.progress)

    def on_done(job, result):
        rows.extend(result)
        bar.update(len(result))

    workers = min(cfg.workers or usable_cores(), len(jobs))
    try:
        execute(jobs, "local", workers, 1 if workers > 1 else None, None, on_done)
    finally:
        bar.close()

    import pandas as pd

    frame = pd.DataFrame(rows).sort_values(["prompt", "episode"], ignore_index=True)
    column = SELECTED[cfg.probe.role]
    target = frame[frame.prompt == "target"].set_index("episode")[column]
    swapped = frame[frame.prompt == "swapped"].set_index("episode")[column].reindex(target.index)
    out = Path(cfg.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary = {
        "kind": "probe",
        "policy_label": loaded.label,
        "checkpoint": loaded.path,
        "checkpoint_hash": loaded.hash,
        "task": cfg.env.task,
        "role": cfg.probe.role,
        "match": cfg.probe.match,
        "condition": condition,
        "servo": cfg.env.servo,
        "selection": column,
        "episodes": cfg.probe.episodes,
        "target": rate(int(target.sum()), len(target)),
        "swapped": rate(int(swapped.sum()), len(swapped)),
        "difference": paired_difference(target.to_numpy(bool), swapped.to_numpy(bool)),
        "success": {
            p: rate(int(frame[frame.prompt == p].success.sum()), int((frame.prompt == p).sum()))
            for p in ("target", "swapped")
        },
        "paper": {arm: paper.probe_range(arm) for arm in paper.PROBE},
        "command": command_line("probe", cfg),
        "versions": versions(),
    }
    write_table(frame, out / "results.parquet", metadata=summary)
    (out / "probe.json").write_text(json.dumps(summary, indent=2))
    t, s = summary["target"], summary["swapped"]
    print(
        f"probe {loaded.label} ({condition}, {cfg.probe.episodes} layouts): competitor selected "
        f"{100 * t['rate']:.1f}% [{100 * t['low']:.1f}, {100 * t['high']:.1f}] with the target prompt, "
        f"{100 * s['rate']:.1f}% [{100 * s['low']:.1f}, {100 * s['high']:.1f}] swapped (paper: "
        + paper.probe_range("target")
        + " -> "
        + paper.probe_range("swapped")
        + ")"
    )
    return out / "probe.json"
