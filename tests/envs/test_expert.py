"""The scripted expert is the oracle: if it fails, the environment is wrong."""

import pytest

from lerobot_condground.core.conditions import PAPER_GRID, TASKS
from lerobot_condground.envs.expert import ScriptedExpert, expert_stages, run_expert_episode
from lerobot_condground.envs.pickplace_env import PickPlaceEnv


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


class _MissingExpert(ScriptedExpert):
    """The expert aiming `miss` m beside the cube: it closes on nothing, as failed policies do."""

    miss = 0.0

    def _target(self):
        pos, yaw = super()._target()
        return pos + [self.miss, 0.0, 0.0], yaw


class _ExpertDriver:
    """Another controller for the expert to take over from: the expert itself, or aiming beside the cube."""

    def __init__(self, miss):
        self.miss = miss

    def reset(self, env):
        self.expert, self.env, self.started = _MissingExpert(), env, False
        self.expert.miss = self.miss

    def __call__(self, obs):
        if not self.started:
            self.expert.reset(self.env)
            self.started = True
        return self.expert.act(obs)


@pytest.mark.parametrize(
    "takeover_step, miss, first_phase",
    [(0, 0.0, "approach"), (30, 0.0, "descend"), (45, 0.0, "lift"), (60, 0.0, "transport"),
     (75, 0.0, "place"), (45, 0.04, "recover"), (55, 0.04, "recover")],
)  # fmt: skip
def test_the_expert_takes_over_from_where_another_controller_left_the_scene_and_finishes(
    takeover_step, miss, first_phase
):
    """DAgger's labels: from any state a policy reaches (mid-carry, or closed beside the cube), the expert
    plans the phase the world asks for from the measured pose, and still places the cube."""
    env = PickPlaceEnv(task="PickPlaceFixedBin-v0", condition="clean", obs_type="agent_pos")
    expert, phases = ScriptedExpert(), []
    info = run_expert_episode(
        env, expert, 0, 300, on_step=lambda obs, a, p: phases.append(expert.phase),
        driver=_ExpertDriver(miss), takeover_step=takeover_step,
    )  # fmt: skip
    env.close()
    assert info["taken_over"] and info["is_success"], (phases[:1], phases[-1:], info["stage"])
    assert phases[0] == first_phase
    if miss:  # it opened, rose and came back for the cube
        assert phases.index("approach") > phases.index("recover")
