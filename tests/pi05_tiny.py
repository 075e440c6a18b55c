"""A π0.5 small enough for CPU tests, built by LeRobot's own pi05 code, and an offline Gemma tokenizer.

LeRobot 0.6.1 builds only the 4.1 B-parameter configuration (gemma_2b + gemma_300m; its vocabulary and the
SigLIP projection width are hard-coded). While `tiny_pi05()` is active, three names of `modeling_pi05` build
the same classes with small widths, 2 layers and a 512-token vocabulary; every forward, attention and
loading path stays LeRobot's. Subprocesses (stock `lerobot-train`) get it through `pi05_site/sitecustomize.py`
when `CONDGROUND_TINY_PI05=1`.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from unittest import mock

from lerobot.policies.pi05 import modeling_pi05

VOCAB = 512
PATCH = 8
WIDTH = 64
# 8 query heads: pi05's layer code reshapes with 8 heads. Both experts need one depth and one head size.
GEMMA = {
    "gemma_2b": modeling_pi05.GemmaConfig(
        width=WIDTH, depth=2, mlp_dim=2 * WIDTH, num_heads=8, num_kv_heads=1, head_dim=8
    ),
    "gemma_300m": modeling_pi05.GemmaConfig(
        width=WIDTH // 2, depth=2, mlp_dim=WIDTH, num_heads=8, num_kv_heads=1, head_dim=8
    ),
}
_PaliGemma = modeling_pi05.PaliGemmaForConditionalGenerationWithPiGemma
_Expert = modeling_pi05.PiGemmaForCausalLM


class _TinyPaliGemma(_PaliGemma):
    def __init__(self, config):
        vision, text = config.vision_config, config.text_config
        vision.hidden_size, vision.intermediate_size = 32, 64
        vision.num_hidden_layers, vision.num_attention_heads = 2, 2
        vision.patch_size = PATCH
        vision.projection_dim = text.hidden_size
        text.num_image_tokens = (vision.image_size // PATCH) ** 2
        text.vocab_size = config.vocab_size = VOCAB
        config.image_token_index = VOCAB - 1
        super().__init__(config)


class _TinyExpert(_Expert):
    def __init__(self, config, **kwargs):
        config.vocab_size = VOCAB
        super().__init__(config, **kwargs)


def _patches():
    return (
        mock.patch.object(modeling_pi05, "get_gemma_config", lambda variant: GEMMA[variant]),
        mock.patch.object(modeling_pi05, "PaliGemmaForConditionalGenerationWithPiGemma", _TinyPaliGemma),
        mock.patch.object(modeling_pi05, "PiGemmaForCausalLM", _TinyExpert),
    )


@contextlib.contextmanager
def tiny_pi05():
    with contextlib.ExitStack() as stack:
        for patch in _patches():
            stack.enter_context(patch)
        yield


def activate() -> None:
    """For a whole process (sitecustomize)."""
    for patch in _patches():
        patch.start()


def save_tokenizer(directory: Path) -> Path:
    """A byte-fallback Gemma tokenizer (no sentencepiece files needed) that AutoTokenizer reloads offline."""
    from transformers import GemmaTokenizer

    vocab = {"<pad>": 0, "<eos>": 1, "<bos>": 2, "<unk>": 3, "<mask>": 4}
    vocab |= {f"<0x{b:02X}>": 5 + b for b in range(256)}
    for ch in ["▁"] + [chr(c) for c in range(33, 127)]:
        vocab.setdefault(ch, len(vocab))
    GemmaTokenizer(vocab=vocab, merges=[], add_bos_token=True).save_pretrained(directory)
    return directory
