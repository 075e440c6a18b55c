"""Which LeRobot episode is being recorded, for a robot that must act at episode starts.

LeRobot gives robots no hook at the start of an episode: on hardware a person resets the scene during
the reset period. The ur3e needs one twice: its twin lays out a fresh scene for every recorded episode,
and its visual prompts are annotated on each episode's first frame. So it looks for LeRobot's episode
loops on the call stack; each call of such a loop has its own start time, which identifies the episode.
Outside these loops (own scripts) nothing happens by itself: call `UR3e.new_episode()`.
"""

from __future__ import annotations

import sys

# (module, function) -> (local holding the loop's start time, whether that call records)
EPISODE_LOOPS = {
    ("lerobot.scripts.lerobot_record", "record_loop"): (
        "start_episode_t",
        lambda loc: loc.get("dataset") is not None,
    ),
    ("lerobot.rollout.strategies.episodic", "_policy_loop"): ("start_t", lambda loc: True),
}


def recording_episode() -> float | None:
    """The start time of the LeRobot episode loop recording now (one value per episode), or None."""
    frame = sys._getframe(1)
    while frame is not None:
        entry = EPISODE_LOOPS.get((frame.f_globals.get("__name__"), frame.f_code.co_name))
        if entry is not None:
            local = frame.f_locals
            return local.get(entry[0]) if entry[1](local) else None
        frame = frame.f_back
    return None
