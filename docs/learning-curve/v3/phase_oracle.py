"""Does the phase head's choice of prompt cost a prompted `act_modified` checkpoint its success? Runs each
checkpoint on the sweep's held-out clean layouts (seeds 1 000 000 on) twice: with the prompt its phase head picks
(as `condground sweep` does) and with the simulator's phase (1 while the target is held between both fingers or
off the table, else 0), and counts, per episode, the policy calls that fed the receptacle's prompt while the
target lay on the table (the wrong prompt the simulator's phase never feeds).

    python docs/learning-curve/v3/phase_oracle.py --layouts=50 --csv=phase_oracle.csv CHECKPOINT_DIR [...]
"""

import argparse
from pathlib import Path

import pandas as pd
import torch

import lerobot_policy_condground  # noqa: F401  (registers act_modified and the env)
from lerobot_condground.core.training import CPU_FRAME_SIZE
from lerobot_condground.envs.configs import CondGroundEnvConfig
from lerobot_condground.evaluation.checkpoints import load_policy
from lerobot_condground.evaluation.rollout import run_episodes

SEED_OFFSET = 1_000_000
OFF_TABLE_M = 0.01  # the target's bottom above the table: lifted, or on its way into the bin

parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
parser.add_argument("checkpoints", nargs="+")
parser.add_argument("--task", default="PickPlaceFixedBin-v0")
parser.add_argument("--layouts", type=int, default=50)
parser.add_argument("--csv", type=Path, help="per-episode rows: checkpoint, phase_source, layout_seed, ...")
args = parser.parse_args()
torch.set_num_threads(1)
height, width = CPU_FRAME_SIZE
env_cfg = CondGroundEnvConfig(
    task=args.task, condition="clean", observation_height=height, observation_width=width
)


def simulator_phase(env) -> int:
    sim = env.unwrapped
    held = sim.tracker.held == 1
    return int(held or sim.tracker.bottom_height(sim.data, 1) > OFF_TABLE_M)


rows = []
for checkpoint in args.checkpoints:
    loaded = load_policy(checkpoint, env_cfg)
    model = loaded.policy.acting_model
    if not getattr(model.config, "use_prompts", False):
        raise SystemExit(f"{checkpoint} feeds no prompt: there is no phase choice to replace")
    predicted_phase = model._prompt_phase
    for source in ("phase_head", "simulator"):
        for seed in range(SEED_OFFSET, SEED_OFFSET + args.layouts):
            env = env_cfg.make_env()
            calls = {"n": 0, "wrong": 0}

            def choose(batch, logits, env=env, calls=calls, source=source, predicted_phase=predicted_phase):
                truth = simulator_phase(env)
                phase = predicted_phase(batch, logits) if source == "phase_head" else torch.tensor([truth])
                calls["n"] += 1
                calls["wrong"] += int(phase.item() == 1 and truth == 0)
                return phase

            model._prompt_phase = choose
            outcome = run_episodes(loaded, [env], [seed], env_cfg.episode_length)[0]
            rows.append(
                {"checkpoint": checkpoint, "phase_source": source, "layout_seed": seed,
                 "success": outcome["success"], "pick": outcome["pick"], "policy_calls": calls["n"],
                 "receptacle_prompt_on_table": calls["wrong"]}
            )  # fmt: skip
            env.close()
    model._prompt_phase = predicted_phase
table = pd.DataFrame(rows)
summary = table.groupby(["checkpoint", "phase_source"]).agg(
    success=("success", "mean"), pick=("pick", "mean"), layouts=("success", "size"),
    receptacle_prompt_on_table=("receptacle_prompt_on_table", "sum"), policy_calls=("policy_calls", "sum"),
)  # fmt: skip
print(summary.to_string())
if args.csv:
    table.to_csv(args.csv, index=False)
