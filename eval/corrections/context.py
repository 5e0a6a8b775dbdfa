"""What a complex-domain correction knows about the signal it corrects, and what it says back.

A correction of ``S[F, H, W]`` needs more than the signal: the camera (a ghost mirrors
through its principal point), the acquisition settings (the twin renders for them), the
source pixels whose taps clipped (their light is not in ``S``: a correction that spreads
or removes light cannot know it) and how many frames the signal averages (its noise).
It says back which pixels it flagged (:data:`FLAGS`), one line per limit it met and the
figures it used. One :class:`CorrectionContext` per corrected signal, filled by the
caller (:func:`context_for_frame`, :func:`context_for_session`), read and annotated by
the method.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Iterable, Sequence

import numpy as np

from tofhil.demod import TapLimits
from tofhil.frames import RawFrame

#: Per-pixel flag bits of a corrected signal (``correction/flags`` of a corrected session).
FLAG_STRAY_LIGHT = 1   # the twin's stray light removed here is larger than the noise
FLAG_MULTIPATH = 2     # the twin's multipath (indirect light) removed here is larger than the noise
FLAG_UNTRUSTED = 4     # light from clipped source pixels, unknown to the correction, matters here
FLAG_RESTORED = 8      # a clipped source pixel whose light was taken from the twin's prediction
FLAGS = {FLAG_STRAY_LIGHT: "stray_light", FLAG_MULTIPATH: "multipath", FLAG_UNTRUSTED: "untrusted",
         FLAG_RESTORED: "restored_from_twin"}


@dataclass
class CorrectionContext:
    """The signal's camera and acquisition, its clipped pixels, and the correction's report."""

    camera: Any
    freq_hz: np.ndarray
    theta_rad: np.ndarray
    integration_time_s: float
    #: the session's recorded sensor configuration (a twin session), None for a device capture
    sensor_config: dict[str, Any] | None = None
    source: str = "<frames>"
    #: [H, W] pixels with a clipped or non-finite tap (in any frame averaged)
    saturated: np.ndarray | None = None
    #: frames averaged into the corrected signal (its noise is one frame's / sqrt(frames))
    frames: int = 1
    #: the mean signal ``[F, H, W]`` of other frames of the session, on which whatever the
    #: correction fits from the data (the twin's signal scale) is fitted, so that the signal
    #: corrected (and scored) is held out from the fit; None: fitted on the signal itself
    fit_signal: np.ndarray | None = None
    #: [H, W] pixels with a clipped or non-finite tap in the frames of ``fit_signal``
    fit_saturated: np.ndarray | None = None
    #: which frames fit and which are scored (:class:`tofhil.eval.metrics.split.FrameSplit`)
    split: Any = None
    flags: np.ndarray | None = None
    notes: list[str] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.camera.shape)

    def flag(self, mask: np.ndarray, bit: int) -> None:
        """Set ``bit`` on the pixels of ``mask`` (a bool ``[H, W]``)."""
        if self.flags is None:
            self.flags = np.zeros(self.shape, np.uint8)
        self.flags[np.asarray(mask, dtype=bool)] |= np.uint8(bit)

    def note(self, text: str) -> None:
        if text not in self.notes:
            self.notes.append(text)

    def flag_counts(self) -> dict[str, int]:
        """Pixels per flag name (0 for a flag not set)."""
        f = np.zeros(self.shape, np.uint8) if self.flags is None else self.flags
        return {name: int(np.count_nonzero(f & bit)) for bit, name in FLAGS.items()}

    def fitted_on(self) -> str:
        """Where a figure the correction fits from the data comes from, in words."""
        if self.fit_signal is None:
            return "the signal corrected itself (in-sample)"
        if self.split is not None:
            return "frames " + ", ".join(str(i) for i in self.split.fit) + " (held out from the frames scored)"
        return "other frames than those corrected (held out from them)"

    def summary(self) -> dict[str, Any]:
        """The report a corrected session and ``metrics.json`` carry (JSON-ready)."""
        return {"notes": list(self.notes), "flagged_pixels": self.flag_counts(), "frames": self.frames,
                **({"split": self.split.to_json()} if self.split is not None else {}),
                "saturated_source_pixels": 0 if self.saturated is None else int(np.count_nonzero(self.saturated)),
                **{k: v for k, v in self.info.items()}}


def saturated_pixels(frames: Iterable[RawFrame]) -> np.ndarray | None:
    """``[H, W]`` pixels with a clipped or non-finite tap in any of the frames: the clip
    levels the frames declare, else those detected in the data (``compare``'s rule,
    :class:`tofhil.eval.metrics.core.TapHealth`); None without frames."""
    from tofhil.eval.metrics.core import TapHealth

    frames = list(frames)
    if not frames:
        return None
    health = TapHealth.from_taps((f.taps for f in frames), declared=TapLimits.from_meta(frames[0].meta))
    return health.saturated | health.nonfinite


def context_for_frame(raw: RawFrame, *, sensor_config: dict[str, Any] | None = None,
                      source: str = "<frames>") -> CorrectionContext:
    """The context of one raw frame's signal."""
    return CorrectionContext(raw.camera, np.asarray(raw.freq_hz, float), np.asarray(raw.theta_rad, float),
                             float(raw.integration_time_s), sensor_config, source, saturated_pixels([raw]), 1)


def context_for_session(session: Any, n: int, frames: Sequence[int] | None = None) -> CorrectionContext:
    """The context of the mean of the first ``n`` frames of an open raw session, or of the
    frames numbered ``frames`` (then ``n`` is ignored)."""
    idx = list(range(max(1, min(n, session.n_frames)))) if frames is None else list(frames)
    first = session.raw_frame(idx[0])
    return CorrectionContext(session.camera, np.asarray(first.freq_hz, float), np.asarray(first.theta_rad, float),
                             float(first.integration_time_s), session.sensor_config, str(session.path),
                             saturated_pixels(session.raw_frame(i) for i in idx), len(idx))
