"""Which frames of a session fit and which score: the held-out split of frames.

Whatever is fitted or chosen from a session's data (the twin's signal scale, a PSF or an
extended twin diagnosed on it, a weight tuned on it) is scored on frames it did not see:
their noise is independent of the fit's. The convention is the diagnosis's
(``tofhil.eval.diagnose.heldout.split_session``, ``depth_heldout``): even frames fit, odd
frames are held out. A PSF or an extended twin that ``tofhil diagnose`` fitted on a session
was fitted on its even frames, so scoring a correction on the odd frames keeps it held out
from that fit too. One frame cannot be split: the score is then in-sample, and says so.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class FrameSplit:
    """The frames a correction is fitted on and the frames its before and after are scored on."""

    fit: tuple[int, ...]
    scored: tuple[int, ...]

    @property
    def in_sample(self) -> bool:
        """Fitted and scored on the same frames (a session of one frame)."""
        return set(self.fit) == set(self.scored)

    def text(self) -> str:
        if self.in_sample:
            return (f"the session has {len(self.scored)} frame: the corrections are fitted and scored on the same "
                    "frame (in-sample; a gain may be optimistic)")
        return (f"fitted on frames {_frames(self.fit)} (the diagnosis's training frames), before and after scored "
                f"on frames {_frames(self.scored)}")

    def to_json(self) -> dict[str, Any]:
        return {"fit_frames": list(self.fit), "scored_frames": list(self.scored), "in_sample": self.in_sample,
                "split": "even frames fit, odd frames scored (the diagnosis's split)", "text": self.text()}


def frame_split(n: int) -> FrameSplit:
    """The split of ``n`` frames: even fit, odd scored; one frame both (in-sample)."""
    if n < 1:
        raise ValueError("need at least one frame")
    if n == 1:
        return FrameSplit((0,), (0,))
    return FrameSplit(tuple(range(0, n, 2)), tuple(range(1, n, 2)))


def _frames(idx: tuple[int, ...]) -> str:
    return ", ".join(str(i) for i in idx)
