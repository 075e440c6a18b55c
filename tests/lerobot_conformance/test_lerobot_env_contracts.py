"""What LeRobot v0.6.1's own env tests (tests/envs/test_envs.py) ask of an env, asked of ours: gymnasium's
checker under each of LeRobot's observation types (`state` is this env's `agent_pos`), and LeRobot's factory
from the registered `condground` config, whose frames reach a policy as float32 in [0, 1]."""

import gymnasium as gym
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from lerobot.envs.factory import make_env, make_env_config
from lerobot.envs.utils import close_envs, preprocess_observation

from lerobot_condground.core.configs import ConfigError


@pytest.mark.parametrize("obs_type", ["state", "pixels", "pixels_agent_pos"])
@pytest.mark.parametrize("task", ["PickPlaceFixedBin-v0", "InstrumentRouting-v0"])
def test_env(task, obs_type):
    env = gym.make(f"gym_condground/{task}", obs_type=obs_type, observation_height=96, observation_width=128)
    check_env(env.unwrapped, skip_render_check=True)
    observation, _ = env.reset(seed=0)
    assert ("pixels" in observation) == (obs_type != "state")
    assert ("agent_pos" in observation) == (obs_type != "pixels")
    env.close()


def test_factory():
    cfg = make_env_config("condground", observation_height=96, observation_width=128)
    envs = make_env(cfg, n_envs=1)
    env = envs[next(iter(envs))][next(iter(envs[next(iter(envs))]))]
    observation, _ = env.reset(seed=0)
    observation = preprocess_observation(observation)
    images = [value for key, value in observation.items() if "image" in key]
    assert images
    for image in images:
        assert image.dtype == torch.float32 and image.min() >= 0.0 and image.max() <= 1.0
    close_envs(envs)


def test_state_is_the_only_alias():
    with pytest.raises(ConfigError, match="Unknown obs_type 'states'; allowed: .*agent_pos, state"):
        make_env_config("condground", obs_type="states")
