"""The `condground` LeRobot env type: `lerobot-eval --env.type=condground --env.task=... --env.condition=...`."""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION, OBS_IMAGES, OBS_STATE

from lerobot_condground.core.conditions import ROUTING_TASK, ConditionSpec, check_env_task
from lerobot_condground.core.configs import ConfigError
from lerobot_condground.core.labels import OBS_PROMPT_OBJECT, OBS_PROMPT_RECEPTACLE
from lerobot_condground.core.routing import INSTRUCTION_FORMS, parse_episodes

from . import GYM_NAMESPACE


@EnvConfig.register_subclass("condground")
@dataclass
class CondGroundEnvConfig(EnvConfig):
    """Pick-and-place with look-alike competitors, or instrument routing.

    task: PickPlaceFixedBin-v0 (fixed receptacle), PickPlaceRandomBin-v0 (both randomized), or
        InstrumentRouting-v0 (the VLA case study's state-conditioned routing; always clean).
    condition: a name (clean, object_color_2, receptacle_shape_1, full_mixed, ...) or fields
        (object_color=2,receptacle_shape=1).
    counterbalanced: permute target and competitor colors and shapes across episodes.
    competitor_pool: eval (competitors from the evaluation assets, as every evaluation scene) or augmentation
        (from the augmentation assets, matching the target as the copy-paste step's pastes do: for recording
        demonstrations among rendered competitors no evaluation scene holds).
    subgoal (InstrumentRouting-v0): procedure, a subgoal (pick, inspect, route, place, home), or several
        separated by commas, one drawn per episode.
    cue (InstrumentRouting-v0): true sends the destination masks the `condground_rgb_cue` step draws,
        false sends empty ones (the cue hidden); unset sends none.
    instruction (InstrumentRouting-v0): the task strings' form, generic or explicit.
    camera_codec: none (frames as rendered) or video (each frame through LeRobot's default video encoder and
        back, as a recorded dataset stores it).
    servo: interpolated (each joint target reached over one control period at no more than the UR3e's
        rated joint speeds, as the arm's servoj stream and the twin do) or direct (the target set at once;
        the behaviour of runs made before this setting existed).
    """

    task: str | None = "PickPlaceRandomBin-v0"
    condition: str = "clean"
    counterbalanced: bool = False
    competitor_pool: str = "eval"
    fps: int = 20
    episode_length: int = 300
    obs_type: str = "pixels_agent_pos"
    observation_height: int = 240
    observation_width: int = 320
    # Render the wrist camera too; by default on for InstrumentRouting-v0, off for pick-and-place.
    wrist_camera: bool | None = None
    # Send the positionless prompt crops of the target object and receptacle with every observation
    # (`observation.prompt.object` / `.receptacle`, as in recorded datasets); prompt policies need them.
    # Pick-and-place only; on by default there.
    prompts: bool | None = None
    subgoal: str = "procedure"
    cue: bool | None = None
    instruction: str = "generic"
    servo: str = "interpolated"
    # Camera frames as rendered (none), or through the video codec a LeRobotDataset stores them with (video):
    # evaluation frames then look as the training frames did, small saturated objects blurred and desaturated.
    camera_codec: str = "none"
    render_mode: str = "rgb_array"
    features: dict[str, PolicyFeature] = field(
        default_factory=lambda: {ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(7,))}
    )
    features_map: dict[str, str] = field(
        default_factory=lambda: {
            ACTION: ACTION,
            "agent_pos": OBS_STATE,
            "pixels/top": f"{OBS_IMAGES}.top",
            "pixels/wrist": f"{OBS_IMAGES}.wrist",
        }
    )

    def __post_init__(self):
        # Bad names and sizes fail here, when the command line is parsed, before any work starts; under the
        # stock scripts as one line (ConfigError), not inside draccus's traceback.
        try:
            self._validate()
        except ValueError as err:
            raise ConfigError(str(err)) from None

    def _validate(self):
        from lerobot_condground.core.codec import check_camera_codec
        from lerobot_condground.core.ur3e import check_servo

        from .arm_env import check_fps, check_obs_type, check_resolution
        from .layout import check_competitor_pool

        check_env_task(self.task)
        ConditionSpec.parse(self.condition)
        check_competitor_pool(self.competitor_pool, "--env.competitor_pool")
        routing = self.task == ROUTING_TASK
        if routing:
            parse_episodes(self.subgoal)
            for flag, value, allowed in (
                ("condition", self.condition, "clean"),
                ("counterbalanced", self.counterbalanced, False),
                ("competitor_pool", self.competitor_pool, "eval"),
                ("prompts", self.prompts, None),
            ):
                if value != allowed and not (flag == "prompts" and value is False):
                    raise ValueError(
                        f"--env.{flag}={value!r} does not apply to {ROUTING_TASK} (no look-alike competitors); "
                        f"leave it at its default"
                    )
            if self.instruction not in INSTRUCTION_FORMS:
                raise ValueError(
                    f"--env.instruction={self.instruction!r} is not allowed; allowed: {', '.join(INSTRUCTION_FORMS)}"
                )
        else:
            for flag, value, default in (
                ("subgoal", self.subgoal, "procedure"),
                ("cue", self.cue, None),
                ("instruction", self.instruction, "generic"),
            ):
                if value != default:
                    raise ValueError(
                        f"--env.{flag}={value!r} applies to {ROUTING_TASK} only; task is {self.task}"
                    )
        if self.wrist_camera is None:
            self.wrist_camera = routing
        if self.prompts is None:
            self.prompts = not routing
        check_resolution(self.observation_height, self.observation_width)
        check_servo(self.servo, "--env.servo")
        check_camera_codec(
            self.camera_codec, "--env.camera_codec", self.observation_height, self.observation_width
        )
        check_fps(self.fps)
        self.obs_type = check_obs_type(self.obs_type)
        if self.episode_length < 1:
            raise ValueError(f"episode_length={self.episode_length} must be a positive number of steps")
        image = PolicyFeature(
            type=FeatureType.VISUAL, shape=(self.observation_height, self.observation_width, 3)
        )
        if self.obs_type != "agent_pos":
            self.features["pixels/top"] = image
            if self.wrist_camera:
                self.features["pixels/wrist"] = image
        if self.obs_type != "pixels":
            self.features["agent_pos"] = PolicyFeature(type=FeatureType.STATE, shape=(7,))

    def get_env_processors(self):
        # LeRobot passes extra env observations through as `observation.<key>`; give the prompt crops
        # the names they have in recorded datasets.
        from lerobot.processor import PolicyProcessorPipeline, RenameObservationsProcessorStep

        rename = {
            "observation.prompt_object": OBS_PROMPT_OBJECT,
            "observation.prompt_receptacle": OBS_PROMPT_RECEPTACLE,
        }
        return PolicyProcessorPipeline(
            steps=[RenameObservationsProcessorStep(rename_map=rename)]
        ), PolicyProcessorPipeline(steps=[])

    @property
    def package_name(self) -> str:
        return "lerobot_condground.envs"

    @property
    def gym_id(self) -> str:
        return f"{GYM_NAMESPACE}/{self.task}"

    def make_env(self, **extra):
        """The task's env itself, without gymnasium's wrappers (for code that steps it directly: recording,
        the sweep); `extra` turns on what such a caller needs beyond these settings (labels, no rendering)."""
        kwargs = {k: v for k, v in self.gym_kwargs.items() if k != "max_episode_steps"} | extra
        if self.task == ROUTING_TASK:
            from .routing_env import InstrumentRoutingEnv

            return InstrumentRoutingEnv(**kwargs)
        from .pickplace_env import PickPlaceEnv

        return PickPlaceEnv(task=self.task, **kwargs)

    @property
    def gym_kwargs(self) -> dict:
        if self.task == ROUTING_TASK:
            return {
                "subgoal": self.subgoal,
                "obs_type": self.obs_type,
                "observation_height": self.observation_height,
                "observation_width": self.observation_width,
                "wrist_camera": self.wrist_camera,
                "cue": self.cue,
                "instruction": self.instruction,
                "render_mode": self.render_mode,
                "fps": self.fps,
                "servo": self.servo,
                "camera_codec": self.camera_codec,
                "max_episode_steps": self.episode_length,
            }
        return {
            "condition": self.condition,
            "counterbalanced": self.counterbalanced,
            "competitor_pool": self.competitor_pool,
            "obs_type": self.obs_type,
            "observation_height": self.observation_height,
            "observation_width": self.observation_width,
            "wrist_camera": self.wrist_camera,
            "prompts": self.prompts,
            "render_mode": self.render_mode,
            "fps": self.fps,
            "servo": self.servo,
            "camera_codec": self.camera_codec,
            "max_episode_steps": self.episode_length,
        }
