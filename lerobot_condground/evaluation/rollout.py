"""Closed-loop episodes of one policy (or the scripted expert) in a batch of our envs.

The envs of a batch step in lockstep and the policy sees them as one batch, as in `lerobot-eval`: the
observation goes through LeRobot's `preprocess_observation`, the env's processor, the policy's
pre-processor, `select_action` and the post-processors. An env that has finished keeps its last
observation in the batch (ACT's action queue is per batch) and is not stepped again.
Each episode ends in one outcome row (see `results.py` for the columns). The same loop runs the
pick-and-place tasks and InstrumentRouting-v0; only the outcome read off the env differs.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np
import torch

from lerobot_condground.core.conditions import ROUTING_TASK, ConditionSpec
from lerobot_condground.core.configs import EvalEnvConfig
from lerobot_condground.evaluation.checkpoints import LoadedPolicy

EXPERT_SIZE = (96, 128)


@dataclass(frozen=True)
class EnvSpec:
    task: str
    condition: str
    counterbalanced: bool = False
    observation_height: int = 240
    observation_width: int = 320
    wrist_camera: bool = False
    prompts: bool = True
    fps: int = 20
    episode_length: int = 300
    servo: str = "interpolated"
    camera_codec: str = "none"
    competitor_pool: str = "eval"
    # InstrumentRouting-v0 only: the env kwargs of the same names (see envs/routing_env.py).
    subgoal: str = "procedure"
    cue: bool | None = None
    instruction: str = "generic"

    @classmethod
    def for_checkpoint(
        cls, env: EvalEnvConfig, loaded: LoadedPolicy, condition: str, prompts: bool | None = None
    ):
        """The env that renders what the checkpoint reads: its cameras at its camera size unless the env
        config sets one, and the prompt crops when it reads them (or as `prompts` says)."""
        default = next(
            iter(loaded.cameras.values()), EXPERT_SIZE
        )  # the expert reads no pixels: render little
        return cls(
            task=env.task,
            condition=condition,
            counterbalanced=env.counterbalanced,
            observation_height=env.observation_height or default[0],
            observation_width=env.observation_width or default[1],
            wrist_camera="wrist" in loaded.cameras,
            prompts=loaded.needs_prompts if prompts is None else prompts,
            fps=env.fps,
            episode_length=env.episode_length,
            servo=env.servo,
            camera_codec=env.camera_codec,
            competitor_pool=env.competitor_pool,
        )

    def make(self):
        return self.lerobot_config().make_env(render_mode=None)

    def lerobot_config(self):
        from lerobot_condground.envs.configs import CondGroundEnvConfig

        fields = asdict(self)
        if self.task == ROUTING_TASK:  # no prompt crops there; the config refuses them
            fields["prompts"] = False
        return CondGroundEnvConfig(**fields)


class EnvPool:
    """Envs are costly to build (MuJoCo model, renderer): a worker keeps them per spec and reuses them."""

    def __init__(self):
        self._envs: dict[EnvSpec, list] = {}

    def get(self, spec: EnvSpec, n: int) -> list:
        envs = self._envs.setdefault(spec, [])
        while len(envs) < n:
            envs.append(spec.make())
        return envs[:n]


def policy_batch(loaded: LoadedPolicy, observations: list[dict], envs: list) -> dict:
    """Raw env observations of a batch -> the policy's input, through the same steps as lerobot-eval."""
    from lerobot.envs.utils import preprocess_observation

    stacked: dict = {}
    for key, value in observations[0].items():
        if isinstance(value, dict):
            stacked[key] = {cam: np.stack([o[key][cam] for o in observations]) for cam in value}
        else:
            stacked[key] = np.stack([o[key] for o in observations])
    batch = preprocess_observation(stacked)
    batch["task"] = [env.task_description for env in envs]
    batch = loaded.env_preprocessor(batch)
    return loaded.preprocessor(batch)


def actions_for(loaded: LoadedPolicy, batch: dict) -> np.ndarray:
    from lerobot.utils.constants import ACTION

    with torch.inference_mode():
        action = loaded.postprocessor(loaded.policy.select_action(batch))
    action = loaded.env_postprocessor({ACTION: action})[ACTION]
    return action.to("cpu").numpy()


class PolicyDriver:
    """A policy driving one env step by step through the same steps as `run_episodes`: the driver
    `envs.expert.run_expert_episode` hands over to the expert from (`condground record --takeover.*`)."""

    def __init__(self, loaded: LoadedPolicy):
        self.loaded = loaded
        self.hash = loaded.hash
        self.env = None

    def reset(self, env) -> None:
        self.env = env
        self.loaded.policy.reset()

    def __call__(self, obs: dict) -> np.ndarray:
        return actions_for(self.loaded, policy_batch(self.loaded, [obs], [self.env]))[0]


StepHook = Callable[[int, dict | None, list[dict], np.ndarray], None]


def run_episodes(
    loaded: LoadedPolicy,
    envs: list,
    seeds: list[int],
    max_steps: int,
    swap: str | None = None,
    on_step: StepHook | None = None,
) -> list[dict]:
    """One episode per env with the given reset seeds; returns one outcome dict per episode.

    swap: None, or the prompt role ("object" / "receptacle") whose crop is replaced by the first
    competitor of that role (the prompt-swap probe). on_step(step, policy_batch or None for the expert,
    raw observations, active mask) is called before every action.
    """
    if len(envs) != len(seeds):
        raise ValueError(f"{len(envs)} envs for {len(seeds)} seeds")
    from lerobot_condground.envs.expert import ScriptedExpert
    from lerobot_condground.envs.routing_expert import RoutingExpert

    observations, infos = [], []
    for env, seed in zip(envs, seeds):
        obs, info = env.reset(seed=int(seed))
        if swap is not None:
            competitor = next(
                (e.label for e in env.layout.entities if e.asset.role == swap and not e.is_target), None
            )
            if competitor is None:
                raise ValueError(
                    f"The prompt swap needs a {swap} competitor; condition {env.condition.name!r} has none"
                )
            obs[f"prompt_{swap}"] = env.swap_prompt(swap, competitor)
        observations.append(obs)
        infos.append(info)
    routing = [env.task == ROUTING_TASK for env in envs]
    experts = [RoutingExpert() if r else ScriptedExpert() for r in routing] if loaded.is_expert else None
    if experts:
        for expert, env in zip(experts, envs):
            expert.reset(env)
    else:
        loaded.policy.reset()

    active = np.ones(len(envs), dtype=bool)
    steps = np.zeros(len(envs), dtype=int)
    unstable = np.zeros(len(envs), dtype=bool)
    step = 0
    while active.any() and step < max_steps:
        batch = None if experts else policy_batch(loaded, observations, envs)
        if on_step is not None:
            on_step(step, batch, observations, active.copy())
        actions = np.stack([e.act() for e in experts]) if experts else actions_for(loaded, batch)
        for i in np.flatnonzero(active):
            obs, _, terminated, trunc, info = envs[i].step(actions[i])
            observations[i], infos[i] = obs, info
            steps[i] += 1
            if terminated or trunc:
                active[i] = False
                unstable[i] = bool(info.get("physics_unstable"))
        step += 1
    truncated = active  # still running at the step limit
    return [
        (routing_outcome if r else outcome)(env, info, int(n), bool(t), bool(u))
        for env, info, n, t, u, r in zip(envs, infos, steps, truncated, unstable, routing)
    ]


def outcome(env, info: dict, steps: int, truncated: bool, unstable: bool) -> dict:
    """The per-episode outcome columns, read off the env's final info and state."""
    layout = env.layout
    competitor = int(info["grasped_competitor"])
    target = env.entity_pose(1)[0]
    grasped = env.entity_pose(competitor)[0] if competitor else np.full(3, np.nan)
    receptacle = layout.target_receptacle
    return {
        "condition_spec": json.dumps(asdict(ConditionSpec.parse(env.condition))),
        "stage": int(info["stage"]),
        "success": bool(info["place"]),
        "pick": bool(info["pick"]),
        "lift": bool(info["lift"]),
        "place": bool(info["place"]),
        "grasped_first": int(info["grasped_first"]),
        "grasped_first_match": str(info["grasped_first_match"]),
        "grasped_competitor": competitor,
        "grasped_competitor_match": layout.entities[competitor - 1].match if competitor else "none",
        "selected_competitor_object": competitor > 0,
        "target_location": str(info["target_location"]),
        "competitor_location": str(info["competitor_location"]),
        "placed_in_competitor_receptacle": "competitor_receptacle"
        in (info["target_location"], info["competitor_location"]),
        "target_x": float(target[0]),
        "target_y": float(target[1]),
        "target_z": float(target[2]),
        "competitor_x": float(grasped[0]),
        "competitor_y": float(grasped[1]),
        "competitor_z": float(grasped[2]),
        "receptacle_x": float(receptacle.xy[0]),
        "receptacle_y": float(receptacle.xy[1]),
        "steps": steps,
        "truncated": truncated,
        "physics_unstable": unstable,
    }


def routing_outcome(env, info: dict, steps: int, truncated: bool, unstable: bool) -> dict:
    """InstrumentRouting-v0's outcome columns: the subgoal's success and where the instrument went. The
    pick-and-place stage flags and competitor columns stay null: the subgoals are not those stages, and
    the task has no competitors (the other container is the wrong destination, not a look-alike)."""
    layout = env.layout
    instrument = env.instrument_pose()[0]
    destination = layout.containers[layout.destination]
    return {
        "stage": int(info["stage"]),
        "success": bool(info["is_success"]),
        "placed_in_competitor_receptacle": info["placed_in"] == layout.other,
        "target_x": float(instrument[0]),
        "target_y": float(instrument[1]),
        "target_z": float(instrument[2]),
        "receptacle_x": float(destination[0]),
        "receptacle_y": float(destination[1]),
        "steps": steps,
        "truncated": truncated,
        "physics_unstable": unstable,
        "subgoal": str(info["subgoal"]),
        "destination": str(info["destination"]),
        "route_choice": str(info["route_choice"]),
        "placed_in": str(info["placed_in"]),
        "scored_by": "env",
    }
