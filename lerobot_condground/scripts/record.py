"""`condground record`: scripted-expert demonstrations -> a LeRobotDataset (v3), resumable."""

from lerobot_condground.datasets.record import RecordConfig as Config, format_summary, record


def main(cfg: Config) -> None:
    driver = None
    if cfg.takeover.policy_path is not None:
        from lerobot_condground.evaluation.checkpoints import load_policy, resolve_device
        from lerobot_condground.evaluation.rollout import PolicyDriver

        device = resolve_device(cfg.takeover.device)
        driver = PolicyDriver(load_policy(cfg.takeover.policy_path, cfg.env, device=device))
    print(format_summary(record(cfg, driver)))
