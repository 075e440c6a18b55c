"""Does a checkpoint act differently in eval mode than in training? The L1 of its action chunks on 128
dataset frames with batch norm on its running statistics (inference) and on batch statistics (training),
dropout off and no gradients (so no copy-paste) in both.

    python docs/measurements/batchnorm_gap_check.py CHECKPOINT_DIR DATASET_ROOT
"""

import sys

import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.factory import get_policy_class, make_pre_post_processors

import lerobot_policy_condground  # noqa: F401  (registers act_modified)
from lerobot_condground.evaluation.checkpoints import check_processor_steps

torch.set_num_threads(1)
torch.manual_seed(0)
ckpt, root = sys.argv[1], sys.argv[2]
check_processor_steps(ckpt, trust_remote_code=False)  # only registered processor steps load
cfg = PreTrainedConfig.from_pretrained(ckpt)
policy = get_policy_class(cfg.type).from_pretrained(ckpt, config=cfg)
pre, _ = make_pre_post_processors(cfg, pretrained_path=ckpt)
fps = 20
ds = LeRobotDataset(
    "local/x", root=root, delta_timestamps={"action": [i / fps for i in range(cfg.chunk_size)]}
)
idx = torch.randperm(len(ds))[:128].tolist()


def run(bn_train):
    policy.eval()
    if bn_train:
        for m in policy.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.train()
    losses = []
    with torch.no_grad():
        for i in range(0, 128, 16):
            batch = torch.utils.data.default_collate([ds[j] for j in idx[i : i + 16]])
            batch = pre(batch)
            loss, out = policy.forward(batch)
            losses.append(out["l1_loss"])
    return sum(losses) / len(losses)


state = {k: v.clone() for k, v in policy.state_dict().items()}  # training mode moves the running statistics
print(f"batch norm on running statistics (inference): L1 {run(False):.4f}")
policy.load_state_dict(state)
print(f"batch norm on batch statistics (training):    L1 {run(True):.4f}")
