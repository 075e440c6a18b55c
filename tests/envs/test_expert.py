"""The scripted expert is the oracle: if it fails, the environment is wrong."""

import pytest

from lerobot_condground.core.conditions import PAPER_GRID, TASKS
from lerobot_condground.envs.expert import expert_stages


@pytest.mark.parametrize("task", TASKS)
@pytest.mark.parametrize(
    "condition, counterbalanced", [("clean", False), ("full_mixed", False), ("full_mixed", True)]
)
def test_expert_succeeds(task, condition, counterbalanced):
    stages = expert_stages(task, condition, 15, counterbalanced=counterbalanced, seed=1000, progress=False)
    assert stages == [3] * 15


@pytest.mark.slow
@pytest.mark.parametrize("task", TASKS)
@pytest.mark.parametrize("counterbalanced", [False, True])
@pytest.mark.parametrize("condition", PAPER_GRID)
def test_expert_succeeds_in_99_percent_over_200_episodes(task, condition, counterbalanced):
    stages = expert_stages(task, condition, 200, counterbalanced=counterbalanced, progress=False)
    assert sum(s == 3 for s in stages) >= 198, stages
