"""How low can eq. (1)'s attention terms go on a token grid? On dataset frames after a checkpoint's own
preprocessor (copy-paste included, as in training), the best any attention map over an h x w token grid
can reach puts all its weight on one token:

    min over A of (1 - <A, M_phi>) + <A, M_d>  =  min over tokens t of (1 - M_phi(t)) + M_d(t)

with the masks pooled onto the grid as the policy pools them. A floor above zero means the two terms pull
against each other: the relevant entity shares its tokens with distractors. Printed per grid, with the
share of frames whose best token still holds a distractor. Grids other than the policy's own are the
same frames pooled finer (8x10 is what a 240x320 frame gives at stride 32).

    python docs/measurements/attention_grid_check.py CHECKPOINT_DIR DATASET_ROOT [FRAMES]
"""

import sys

import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.factory import make_pre_post_processors

import lerobot_policy_condground  # noqa: F401  (registers our processor steps)
from lerobot_condground.core.grounding import pooled_mask
from lerobot_condground.core.labels import OBS_PHASE, OBS_SEGMENTATION, phase_masks
from lerobot_condground.evaluation.checkpoints import check_processor_steps

GRIDS = [(3, 4), (6, 8), (8, 10), (12, 16)]

torch.set_num_threads(1)
torch.manual_seed(0)
ckpt, root = sys.argv[1], sys.argv[2]
frames = int(sys.argv[3]) if len(sys.argv) > 3 else 512
check_processor_steps(ckpt, trust_remote_code=False)  # only registered processor steps load
cfg = PreTrainedConfig.from_pretrained(ckpt)
pre, _ = make_pre_post_processors(cfg, pretrained_path=ckpt)
ds = LeRobotDataset(
    "local/x", root=root, delta_timestamps={"action": [i / 20 for i in range(cfg.chunk_size)]}
)
idx = torch.randperm(len(ds))[:frames].tolist()
relevant, distractors = [], []
for i in range(0, len(idx), 32):
    # with gradients on and an action in the batch, the copy-paste step runs as in training
    batch = pre(torch.utils.data.default_collate([ds[j] for j in idx[i : i + 32]]))
    m_phi, m_d = phase_masks(batch[OBS_SEGMENTATION], batch[OBS_PHASE].reshape(-1).long())
    relevant.append(m_phi.cpu())
    distractors.append(m_d.cpu())
relevant, distractors = torch.cat(relevant), torch.cat(distractors)
has_both = relevant.flatten(1).any(1) & distractors.flatten(1).any(1)
print(f"{len(idx)} frames of {root}; {has_both.float().mean():.0%} hold the relevant entity and a distractor")
print(f"{'grid':>6} {'floor of the two terms (mean)':>30} {'frames whose best token holds a distractor':>44}")
for grid in GRIDS:
    m_phi, m_d = pooled_mask(relevant, grid), pooled_mask(distractors, grid)
    per_token = (1 - m_phi) + m_d
    floor, best = per_token.flatten(1).min(1)
    shared = m_d.flatten(1).gather(1, best[:, None]).squeeze(1) > 0
    print(f"{grid[0]:>2}x{grid[1]:<3} {floor.mean():>30.3f} {shared.float().mean():>44.0%}")
