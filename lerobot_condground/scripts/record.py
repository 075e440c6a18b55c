"""`condground record`: scripted-expert demonstrations -> a LeRobotDataset (v3), resumable."""

from lerobot_condground.datasets.record import RecordConfig as Config, format_summary, record


def main(cfg: Config) -> None:
    driver = None
    if cfg.takeover.policy_path is not None:
        from lerobot_condground.evaluation.checkpoints import load_policy, resolve_device
        from lerobot_condground.evaluation.rollout import PolicyDriver

        device = resolve_device(cfg.takeover.device)
        try:
            loaded = load_policy(
                cfg.takeover.policy_path,
                cfg.env,
                device=device,
                trust_remote_code=cfg.takeover.trust_remote_code,
            )
        except PermissionError as err:  # the loader's opt-in is named as this command spells it
            raise PermissionError(
                str(err).replace("--policy.trust_remote_code", "--takeover.trust_remote_code")
            ) from None
        driver = PolicyDriver(loaded)
    print(format_summary(record(cfg, driver)))
