"""`condground attention`: per-step cross-attention of one head over the camera, as a video with stills."""

from lerobot_condground.diagnosis.attention import AttentionConfig as Config, run_attention


def main(cfg: Config) -> None:
    run_attention(cfg)
