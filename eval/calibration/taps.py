"""Per-tap offset and gain calibration (fixed-pattern correction) of raw taps.

Each tap of each pixel has its own offset (dark signal non-uniformity) and gain (photo
response non-uniformity). The offsets add a fixed complex offset to ``S``; the tap gains
do worse where stray light is strong: unequal gains turn part of the *unmodulated* light
``B`` into a false modulated signal, ``S_err = (2/K) sum_k (g_k - 1) B exp(i theta_k)``.
Stray light raises ``B`` on dark pixels by the scattered light of every bright one, so no
correction of ``S`` alone can remove that error: the taps must be balanced first.

Pixel-to-pixel gain differences matter too, because the scattered light reaches a pixel
before its gain does: a correction removes ``g * (h * S)`` with ``h * (g S)``, leaving
``(g - mean g) * (h * S)``, which is large where the stray light dominates.

Calibration needs two captures with the emitter off: a dark one (offsets) and a flat one
lit only by unmodulated light (ambient light on a surface filling the view): every tap of
a pixel then sees the same light, so ``(c_k - o_k) / mean_k(c_k - o_k)`` is the tap's
relative gain. The pixel's own gain is the flat image over its smooth illumination (a
2-D polynomial fitted to the log of the flat image): the illumination of a flat surface
varies smoothly over the sensor, the gains do not.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from tofhil.demod import phasor
from tofhil.errors import InputFileError, TofhilError
from tofhil.eval.calibration.side_files import load_tagged_npz

FORMAT = "tofhil.tap_calibration.v1"


@dataclass
class TapCalibration:
    """``c_k' = (c_k - offset_k) / gain_k`` per pixel, ``[F, K, H, W]`` arrays."""

    offset_dn: np.ndarray
    gain: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)

    def apply(self, taps: np.ndarray) -> np.ndarray:
        taps = np.asarray(taps, dtype=np.float64)
        if taps.shape != self.gain.shape:
            raise TofhilError(f"taps are {taps.shape}, the tap calibration {self.gain.shape}", field="flat",
                              expected="a tap calibration made with the same camera, frequencies and taps")
        return (taps - self.offset_dn) / self.gain

    @staticmethod
    def file_path(path: str | Path) -> Path:
        """The file :meth:`save` writes: ``path`` with ``.npz`` added when it lacks it."""
        p = Path(path)
        return p if p.suffix == ".npz" else p.with_name(p.name + ".npz")

    def save(self, path: str | Path, *, force: bool = False) -> Path:
        """Write the calibration (.npz); refuses to overwrite without ``force``. Returns the
        real path (``.npz`` added when missing)."""
        from tofhil.outputs import atomic_file, refuse_existing

        p = self.file_path(path)
        refuse_existing(p, force)
        if not (np.all(np.isfinite(self.offset_dn)) and np.all(np.isfinite(self.gain)) and np.all(self.gain > 0)):
            raise TofhilError("the calibration has non-finite offsets or gains", file=p, field="gain",
                              expected="finite offsets and positive gains")
        with atomic_file(p) as f:
            np.savez_compressed(f, offset_dn=self.offset_dn, gain=self.gain, info=json.dumps(self.info), format=FORMAT)
        return p

    @classmethod
    def load(cls, path: str | Path) -> "TapCalibration":
        p = Path(path)
        data = load_tagged_npz(p, FORMAT, "tofhil tap calibration", "a tap calibration (.npz) from tofhil calibrate-taps")
        for key in ("offset_dn", "gain"):
            if key not in data or np.asarray(data[key]).ndim != 4:
                raise InputFileError("missing or not [F, K, H, W]", file=p, field=key, expected="a 4-D array")
        if data["offset_dn"].shape != data["gain"].shape or np.any(data["gain"] <= 0):
            raise InputFileError("offset and gain differ in shape or a gain is <= 0", file=p, field="gain",
                                 expected="positive gains of the offsets' shape")
        return cls(np.asarray(data["offset_dn"], np.float64), np.asarray(data["gain"], np.float64),
                   json.loads(str(data.get("info", "{}"))))


def smooth_illumination(image: np.ndarray, degree: int = 4) -> np.ndarray:
    """Least-squares 2-D polynomial of ``log(image)`` (``[H, W]``, positive), exponentiated."""
    h, w = image.shape
    v, u = np.mgrid[0:h, 0:w]
    x, y = (u - (w - 1) / 2) / (w / 2), (v - (h - 1) / 2) / (h / 2)
    cols = [x ** i * y ** j for i in range(degree + 1) for j in range(degree + 1 - i)]
    a = np.stack([c.ravel() for c in cols], axis=1)
    coef, *_ = np.linalg.lstsq(a, np.log(image).ravel(), rcond=None)
    return np.exp(a @ coef).reshape(h, w)


def calibrate_taps(flat: np.ndarray, theta_rad: np.ndarray, dark: np.ndarray | None = None, *,
                   max_modulation: float = 0.02, pixel_gain: bool = True, degree: int = 4) -> TapCalibration:
    """Tap offsets from a dark capture and relative tap gains from a flat unmodulated one.

    ``flat`` and ``dark`` are mean taps ``[F, K, H, W]`` (average many frames first). The
    flat capture must carry no modulated light: where ``|S| > max_modulation * B`` the
    emitter was evidently on, and that is an error.
    """
    flat = np.asarray(flat, dtype=np.float64)
    off = np.zeros_like(flat) if dark is None else np.asarray(dark, dtype=np.float64)
    for name, taps in (("flat", flat), ("dark", off)):
        bad = int((~np.isfinite(taps)).sum())
        if bad:
            raise TofhilError(f"{bad} of {taps.size} mean taps are not finite (NaN or inf)", field=name,
                              expected="a capture with finite taps on every pixel")
    if off.shape != flat.shape:
        raise TofhilError(f"dark taps {off.shape} and flat taps {flat.shape} differ", field="dark",
                          expected="captures with the same camera, frequencies and taps")
    lit = flat - off
    b = lit.mean(axis=-3, keepdims=True)
    if np.any(b <= 0):
        raise TofhilError(f"{int((b <= 0).sum())} pixels get no light in the flat capture", field="flat",
                          expected="every pixel lit (ambient light on a surface filling the view)")
    mod = np.abs(phasor(lit, theta_rad)) / b[..., 0, :, :]
    if np.median(mod) > max_modulation:
        raise TofhilError(f"the flat capture is modulated (median |S|/B = {np.median(mod):.3f})", field="flat",
                          expected="a capture with the emitter off, lit by unmodulated light only")
    gain = lit / b  # relative tap gains, mean 1 per pixel
    pix = np.ones_like(b)
    if pixel_gain:
        for f in range(b.shape[0]):
            pix[f, 0] = b[f, 0] / smooth_illumination(b[f, 0], degree)
    return TapCalibration(off, gain * pix, {"tap_gain_spread": float(np.median(gain.std(axis=-3))),
                                            "pixel_gain_spread": float(pix.std()), "dark": dark is not None,
                                            "pixel_gain": pixel_gain})


def mean_taps(path: str | Path, progress: Callable[[Any, int, str], Any] | None = None
              ) -> tuple[np.ndarray, Any, np.ndarray]:
    """Mean raw taps ``[F, K, H, W]`` of a session (calibration captures are averaged in the
    taps, before demodulation), its camera and tap phases."""
    from tofhil.session import open_session

    p = Path(path)
    wrap = progress or (lambda it, n, desc: it)
    with open_session(p) as s:
        if not s.has_raw or s.n_frames == 0:
            raise TofhilError("needs raw taps (at least one frame)", file=p, field="raw/taps")
        from tofhil.eval.corrections.averaging import mean_taps_of

        return mean_taps_of(wrap(s.raw_frames(), s.n_frames, f"reading {p.name}")), s.camera, s.theta_rad
