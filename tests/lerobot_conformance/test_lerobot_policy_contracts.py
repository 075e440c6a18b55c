"""What LeRobot v0.6.1's own policy tests (tests/policies/test_policies.py, not shipped in the wheel) ask of a
policy, asked of ours: the class and config lookup, defaults that build, an exact save/load round trip and
`select_action` shapes, on the features of a plain LeRobot dataset (one 84x84 camera, 6-dof state and action)
and, for the variants that need them, of a `condground record` dataset. Backbone weights off: nothing
downloads here."""

import inspect

import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
from lerobot.policies.factory import get_policy_class, make_policy_config
from lerobot.utils.feature_utils import dataset_to_policy_features

PLAIN = {
    "observation.images.laptop": PolicyFeature(type=FeatureType.VISUAL, shape=(3, 84, 84)),
    "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(6,)),
    "action": PolicyFeature(type=FeatureType.ACTION, shape=(6,)),
}


def config_for(name: str, features: dict, **fields):
    cfg = make_policy_config(name, **fields)
    cfg.output_features = {k: f for k, f in features.items() if f.type is FeatureType.ACTION}
    cfg.input_features = {k: f for k, f in features.items() if k not in cfg.output_features}
    if hasattr(cfg, "pretrained_backbone_weights"):
        cfg.pretrained_backbone_weights = None
    return cfg


@pytest.mark.parametrize("name", ["act", "act_modified", "pi05_grounded"])
def test_get_policy_and_config_classes(name):
    policy_cls, cfg = get_policy_class(name), make_policy_config(name)
    assert policy_cls.name == name
    assert issubclass(cfg.__class__, inspect.signature(policy_cls.__init__).parameters["config"].annotation)


def test_defaults_build_on_a_plain_dataset_where_the_variant_needs_no_labels():
    policy_cls = get_policy_class("act_modified")
    policy_cls(config_for("act_modified", PLAIN, variant="standard"))
    # The default is the paper's method, which needs the labels `condground record` writes (copy-paste too:
    # the segmentation): one line says so and names the variant that builds.
    for variant, fields in (("full", {}), ("augmentation", {"variant": "augmentation"})):
        with pytest.raises(
            ValueError, match=rf"variant '{variant}' .* lacks\..*--policy\.variant=standard builds"
        ):
            policy_cls(config_for("act_modified", PLAIN, **fields))


def recorded_features(root) -> dict:
    return dataset_to_policy_features(LeRobotDatasetMetadata("local/test_full_mixed", root=root).features)


@pytest.mark.parametrize("variant", ["standard", "full"])
def test_save_and_load_round_trip_exactly(recorded_dataset, tmp_path, variant):
    features = PLAIN if variant == "standard" else recorded_features(recorded_dataset)
    policy_cls = get_policy_class("act_modified")
    policy = policy_cls(config_for("act_modified", features, variant=variant))
    policy.save_pretrained(tmp_path / variant)
    loaded = policy_cls.from_pretrained(tmp_path / variant, config=policy.config)
    torch.testing.assert_close(list(policy.parameters()), list(loaded.parameters()), rtol=0, atol=0)


def test_select_action_takes_any_frame_size_unless_the_attention_loss_fixes_the_grid(recorded_dataset):
    policy = get_policy_class("act_modified")(config_for("act_modified", PLAIN, variant="standard")).eval()
    for size in ((84, 84), (96, 128)):  # the trained size and another, as stock ACT takes
        policy.reset()
        batch = {"observation.state": torch.zeros(1, 6), "observation.images.laptop": torch.rand(1, 3, *size)}
        assert policy.select_action(batch).shape == (1, 6)
    features = recorded_features(recorded_dataset)
    full = get_policy_class("act_modified")(config_for("act_modified", features, variant="full")).eval()
    camera = next(k for k in full.config.image_features)
    h, w = full.config.image_features[camera].shape[-2:]
    batch = {key: torch.zeros(1, *feature.shape) for key, feature in full.config.input_features.items()} | {
        camera: torch.rand(1, 3, h + 16, w + 16)
    }
    with pytest.raises(
        ValueError, match=f"frames are {h + 16}x{w + 16}, .* trained on {h}x{w} \\(its attention loss"
    ):
        full.select_action(batch)
