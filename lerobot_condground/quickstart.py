"""`condground quickstart`: the whole foundation in a few minutes on a laptop.

Records a few expert episodes of each task into LeRobotDatasets, then runs the expert under `clean`
and `full_mixed` and prints a stage-metric table. Rerunning reuses the recorded datasets.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from lerobot_condground.conditions import TASKS


@dataclass
class QuickstartConfig:
    # Where datasets land: <output_dir>/datasets/<task>.
    output_dir: str = "outputs/quickstart"
    # Expert demonstrations recorded per task.
    episodes_per_task: int = 3
    # Expert rollouts per task and condition for the stage-metric table.
    expert_episodes: int = 20
    progress: bool = True


def run_quickstart(cfg: QuickstartConfig) -> list:
    from lerobot_condground.envs.configs import CondGroundEnvConfig
    from lerobot_condground.expert_rollouts import expert_stages
    from lerobot_condground.record import RecordConfig, RecordDatasetConfig, format_summary, record
    from lerobot_condground.stage_metrics import format_table, stage_metrics

    for task in TASKS:
        root = Path(cfg.output_dir) / "datasets" / task
        result = record(
            RecordConfig(
                env=CondGroundEnvConfig(task=task),
                dataset=RecordDatasetConfig(
                    repo_id=f"local/condground_{task.split('-')[0].lower()}", root=str(root),
                    num_episodes=cfg.episodes_per_task,
                ),
                progress=cfg.progress,
            )
        )
        print(f"[{task}] dataset {root}: {result['total_episodes']} episodes")
        print(format_summary(result))
    rows = []
    for task in TASKS:
        for condition in ("clean", "full_mixed"):
            stages = expert_stages(task, condition, cfg.expert_episodes, progress=cfg.progress)
            rows.append((task, condition, stage_metrics(stages)))
    print("\nScripted expert, stage metrics")
    print(format_table(rows))
    return rows
