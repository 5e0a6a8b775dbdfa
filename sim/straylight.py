"""Stray light: lens scattering as a convolution of the complex image on the sensor.

Model (Mure-Dubois and Huegli 2007): ``S_meas = (delta + h) * S`` for every modulation
frequency and harmonic (and for the unmodulated light as well: the lens scatters all of it).
``h`` moves a fraction ``W`` of each pixel's light elsewhere:

    h = sum_i w_i G_i  +  veil  +  ghost  +  measured  -  W delta     (conserve = true)

with ``W = sum_i w_i + w_veil + w_ghost + w_measured`` (the *fraction of light scattered*).
Each scattering component is normalised to unit sum over the infinite plane, so a weight is
exactly the fraction of a pixel's light the component moves; light scattered beyond the
sensor edge is lost, as in a real camera. With ``conserve = false`` the scattered light is
added on top (``S + sum_i w_i G_i * S + ...``), Mure-Dubois and Huegli's additive form.

Components:
- Gaussians: weight, ``sigma_x``, ``sigma_y`` in pixels, integrated over each pixel's area
  (erf differences), so small sigmas are exact.
- Veil: a weight spread uniformly over the whole sensor (every pixel receives
  ``w_veil * sum(S) / (H W)``).
- Ghosts: a reflection between lens surfaces images the scene mirrored through a centre
  ``c`` (each ghost's own, default the principal point): light at pixel ``p`` leaks to
  ``2c - p`` (sub-pixel), blurred by a Gaussian.
- Measured PSF: the image of a point source (any size; its peak pixel is the direct light).

Convolutions are linear, never circular: images are zero-padded for the FFT so that no
wrap-around reaches the retained pixels. The shift-invariant part uses a kernel of shape
``[2H-1, 2W-1]`` (every shift between two sensor pixels) centred at ``(H-1, W-1)``. The
operators are public (``psf_kernel``, ``ghost_kernel``, ``convolve``, ``correlate``,
``StrayLightOperator`` with ``apply``/``scatter``/``adjoint``/``invert``) so corrections
(``eval/corrections``) are built on them. ``StrayLightPSF`` is the one PSF type: simulated
(the ``stray_light`` effect's parameters, ``from_params``/``to_params``), diagnosed,
calibrated, saved and loaded (``save``/``load``, JSON) and corrected with.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import scipy.fft as sfft
from scipy.special import erf

from tofhil import C_M_PER_S
from tofhil.camera import CameraModel
from tofhil.content_cache import LRUCache, content_digest
from tofhil.errors import InputFileError, TofhilError, require_input_file
from tofhil.schema import Schema


@dataclass(frozen=True)
class GaussianLobe:
    """A scattering lobe: ``weight`` of the light spread by a Gaussian (sigmas in pixels).
    ``field_weight`` makes it shift-variant: a source at normalised field radius ``rho`` (0 at
    the principal point, 1 at the sensor's corner) spreads ``weight + field_weight rho^2``;
    ``field_weight4`` adds the second order, ``+ field_weight4 rho^4`` (a lobe whose *width*
    changes across the field is a signed combination of widths whose weights vary with
    ``rho^2`` -- a Taylor series in ``rho^2`` that first order truncates too early when the
    width triples from axis to corner)."""

    weight: float
    sigma_x_px: float
    sigma_y_px: float
    field_weight: float = 0.0
    field_weight4: float = 0.0


@dataclass(frozen=True)
class Ghost:
    """A lens ghost: ``weight`` of the light imaged mirrored through ``center_px`` (``(x, y)``
    in pixels; None = the camera's principal point), blurred by a Gaussian ``sigma_px``.

    ``magnification`` generalises the mirror (-1): light at ``p`` lands at ``c + m (p - c)``
    (a traced lens ghost, sim/optics.py; a filter's ghost is near +1); a source pixel then
    covers ``|m|`` pixels, added to the blur as a box's variance. ``extra_path_m``: the ghost
    travels this much more optical path than the direct light (its phasor is delayed by it)."""

    weight: float
    sigma_px: float = 0.0
    center_px: tuple[float, float] | None = None
    magnification: float = -1.0
    extra_path_m: float = 0.0

    @property
    def is_mirror(self) -> bool:
        """The plain ghost (mirror through the centre, no delay): a convolution of the flipped image."""
        return self.magnification == -1.0 and self.extra_path_m == 0.0


@dataclass(frozen=True)
class RadialProfile:
    """A free-form scattering lobe (heavy tails, any shape in r): the fraction of a pixel's
    light that lands on ONE other pixel at distance ``r`` is ``k(r)``, piecewise linear in
    ``log r`` between the knots ``radii_px`` (``values`` per pixel at each knot; constant
    inside the first knot, zero beyond the last). ``aspect`` stretches it along y
    (``r = hypot(dx, dy / aspect)``). ``field_values`` (same knots) make it shift-variant:
    a source at normalised field radius ``rho`` (0 at the principal point, 1 at the sensor's
    corner) scatters by ``k(r) + rho^2 k_f(r)``."""

    radii_px: tuple[float, ...]
    values: tuple[float, ...]
    field_values: tuple[float, ...] = ()
    aspect: float = 1.0

    @property
    def weight(self) -> float:
        """Fraction of a pixel's light the on-axis profile moves (over the infinite plane)."""
        return float(np.dot(self.values, radial_hat_sums(self.radii_px, self.aspect)))

    @property
    def field_weight(self) -> float:
        """Extra fraction moved by a source at the sensor's corner (rho = 1)."""
        if not self.field_values:
            return 0.0
        return float(np.dot(self.field_values, radial_hat_sums(self.radii_px, self.aspect)))


@dataclass(frozen=True)
class StrayLightPSF:
    """The one stray-light model of tofhil: the scatter kernel ``h`` and the direct part.

    ``S_meas = keep * S + h * S`` with ``h`` = shift-invariant lobes (``gaussians``, the
    ``veil``, a ``measured`` point-source image) + ``ghosts`` (not shift-invariant: mirrored
    through their centre). ``keep`` is ``direct`` when given (a calibration fits it), else
    ``1 - total_weight`` when ``conserve`` (light moved), else 1 (light added). New lobe
    forms (power-law tails, free radial profiles) are further shift-invariant terms of
    :func:`psf_kernel`; ghosts with fitted centre or scale are further :class:`Ghost` fields.
    Simulated (the ``stray_light`` effect), diagnosed, calibrated and corrected with alike.
    """

    gaussians: tuple[GaussianLobe, ...] = ()
    veil: float = 0.0
    ghosts: tuple[Ghost, ...] = ()
    #: A free-form radial lobe (heavy tails; optionally field-dependent).
    radial: RadialProfile | None = None
    #: Measured point-source image (normalised on use) and its centre pixel ``(x, y)``.
    measured: np.ndarray | None = field(default=None, compare=False)
    measured_center_px: tuple[int, int] | None = None
    measured_scale: float = 1.0
    conserve: bool = True
    #: Fraction of a pixel's light that stays on it; None = by ``conserve``.
    direct: float | None = None
    #: What a calibration or diagnosis found (basis, weights, residual, source); not physics.
    info: dict[str, Any] = field(default_factory=dict, compare=False)

    @property
    def measured_fraction(self) -> float:
        """Fraction of light the measured PSF scatters away from its peak pixel (x scale)."""
        if self.measured is None:
            return 0.0
        p, (cx, cy) = _measured_normalised(self.measured, self.measured_center_px)
        return self.measured_scale * float(1.0 - p[cy, cx])

    @property
    def ghost_weight(self) -> float:
        return sum(g.weight for g in self.ghosts)

    @property
    def total_weight(self) -> float:
        """``W``: the fraction of each pixel's light that is scattered (over the infinite plane)."""
        return (sum(g.weight for g in self.gaussians) + self.veil + self.ghost_weight + self.measured_fraction
                + (self.radial.weight if self.radial is not None else 0.0))

    @property
    def keep(self) -> float:
        """The direct part: the factor on ``S`` itself."""
        if self.direct is not None:
            return float(self.direct)
        return 1.0 - self.total_weight if self.conserve else 1.0

    @property
    def is_identity(self) -> bool:
        return self.total_weight == 0.0 and self.keep == 1.0

    @classmethod
    def from_params(cls, params: Mapping[str, Any], *, source: str | Path = "<effects>",
                    prefix: str = "effects.stray_light", base_dir: Path | None = None) -> "StrayLightPSF":
        """From the `stray_light` effect's parameters (docs/effects.md): ``weight``,
        ``sigma_px`` (``sigma_y_px``), ``gaussians: [[w, sx, sy], ...]``, ``veil``,
        ``ghost_weight``, ``ghost_sigma_px``, ``ghost_center_px``, ``ghosts: [[w, sigma(, cx,
        cy)], ...]``, ``psf_file``, ``psf_center_px``, ``psf_scale``, ``conserve``, ``direct``."""
        return _psf_from_params(params, source=source, prefix=prefix, base_dir=base_dir)

    def to_params(self, measured_file: str | None = None) -> dict[str, Any]:
        """The `stray_light` effect's parameters of this PSF (inverse of :meth:`from_params`).

        A measured image is referred to by ``measured_file`` (written by the caller)."""
        d: dict[str, Any] = {"weight": 0.0}  # every lobe is in `gaussians`
        if self.gaussians:
            d["gaussians"] = [[g.weight, g.sigma_x_px, g.sigma_y_px]
                              + ([g.field_weight] if g.field_weight or g.field_weight4 else [])
                              + ([g.field_weight4] if g.field_weight4 else [])
                              for g in self.gaussians]
        if self.veil:
            d["veil"] = self.veil
        if len(self.ghosts) == 1 and self.ghosts[0].is_mirror:
            g = self.ghosts[0]
            d["ghost_weight"], d["ghost_sigma_px"] = g.weight, g.sigma_px
            if g.center_px is not None:
                d["ghost_center_px"] = list(g.center_px)
        elif self.ghosts:
            d["ghosts"] = [[g.weight, g.sigma_px] + ([] if g.center_px is None else list(g.center_px))
                           if g.is_mirror else _ghost_mapping(g) for g in self.ghosts]
        if self.radial is not None:
            d["radial"] = {"radii_px": list(self.radial.radii_px), "values": list(self.radial.values)}
            if self.radial.field_values:
                d["radial"]["field_values"] = list(self.radial.field_values)
            if self.radial.aspect != 1.0:
                d["radial"]["aspect"] = self.radial.aspect
        if self.measured is not None:
            if measured_file is None:
                raise ValueError("a PSF with a measured image needs the image's file name")
            d["psf_file"] = measured_file
            d["psf_scale"] = self.measured_scale
            if self.measured_center_px is not None:
                d["psf_center_px"] = list(self.measured_center_px)
        d["conserve"] = self.conserve
        if self.direct is not None:
            d["direct"] = self.direct
        return d

    def save(self, path: str | Path, *, force: bool = False) -> Path:
        """Write the PSF file (JSON: the effect's parameters, so it also pastes into a scene's
        ``effects: stray_light:``); a measured image goes beside it as ``<stem>_measured.npy``.
        Refuses to overwrite without ``force``; returns the path written."""
        p = Path(path)
        side = p.with_name(p.stem + "_measured.npy") if self.measured is not None else None
        for f in (p, side):
            if f is not None and f.exists() and not force:
                raise TofhilError("already exists; refusing to overwrite (use --force)", file=f)
        doc = {"format": PSF_FORMAT, "stray_light": self.to_params(None if side is None else side.name),
               "info": self.info}
        text = json.dumps(doc, indent=2, default=_json_default)
        if side is not None:
            _atomic_write(side, lambda f: np.save(f, np.asarray(self.measured)))
        _atomic_write(p, lambda f: f.write(text.encode("utf-8")))
        return p

    @classmethod
    def load(cls, path: str | Path) -> "StrayLightPSF":
        """Read a PSF file written by :meth:`save` (``tofhil correct --save-psf``, diagnose)."""
        expected = "a stray-light PSF file (.json, written by --save-psf or tofhil diagnose)"
        p = require_input_file(path, expected=expected)
        raw = p.read_bytes()
        if raw[:2] == b"PK":  # an .npz: the kernel-array format of older versions
            raise InputFileError("is an .npz PSF of an older tofhil (kernel arrays, no parameters)", file=p,
                                 field="format", expected=f"{PSF_FORMAT!r}: recalibrate with --save-psf")
        try:
            doc = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, ValueError) as exc:
            raise InputFileError(f"cannot be read as JSON ({exc})", file=p, expected=expected) from None
        if not isinstance(doc, dict) or doc.get("format") != PSF_FORMAT:
            raise InputFileError("not a tofhil stray-light PSF", file=p, field="format", expected=repr(PSF_FORMAT))
        psf = cls.from_params(doc.get("stray_light"), source=p, prefix="stray_light", base_dir=p.parent)
        info = doc.get("info")
        return replace(psf, info=dict(info) if isinstance(info, dict) else {})


#: The ``format`` tag of a PSF file.
PSF_FORMAT = "tofhil.straylight_psf.v2"


def _ghost_mapping(g: Ghost) -> dict[str, Any]:
    d: dict[str, Any] = {"weight": g.weight, "sigma_px": g.sigma_px, "magnification": g.magnification,
                         "extra_path_m": g.extra_path_m}
    if g.center_px is not None:
        d["center_px"] = list(g.center_px)
    return d


def _json_default(x: Any) -> Any:
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def _atomic_write(path: Path, write: Any) -> None:
    """Write through a temporary file in the same directory, then rename: a failed write
    leaves nothing behind and never a half-written file under the real name."""
    import os
    import tempfile

    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as exc:
        raise TofhilError(f"cannot write here ({exc.strerror})", file=path,
                          expected="a writable directory") from None
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        os.replace(tmp, path)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        raise TofhilError(f"cannot write ({exc.strerror})", file=path, expected="a writable file") from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


# ---------------------------------------------------------------------------------------------
# Kernels
# ---------------------------------------------------------------------------------------------
def _pixel_gauss_1d(x: np.ndarray, mu: float, sigma: float) -> np.ndarray:
    """Integral of a unit Gaussian N(mu, sigma) over the pixels [x - 1/2, x + 1/2]."""
    s = max(float(sigma), 1e-9) * math.sqrt(2.0)
    return 0.5 * (erf((x + 0.5 - mu) / s) - erf((x - 0.5 - mu) / s))


def gaussian_kernel(shape: tuple[int, int], sigma_x_px: float, sigma_y_px: float,
                    offset_px: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """Pixel-integrated unit Gaussian on the ``[2H-1, 2W-1]`` shift grid, centred at
    ``(H-1, W-1) + offset``. Sums to 1 minus the tails beyond the grid (light leaving the
    sensor)."""
    h, w = shape
    ys = np.arange(-(h - 1), h, dtype=np.float64)
    xs = np.arange(-(w - 1), w, dtype=np.float64)
    gy = _pixel_gauss_1d(ys, offset_px[1], sigma_y_px)
    gx = _pixel_gauss_1d(xs, offset_px[0], sigma_x_px)
    return np.outer(gy, gx)


def _measured_normalised(img: np.ndarray, center: tuple[int, int] | None) -> tuple[np.ndarray, tuple[int, int]]:
    p = np.asarray(img, dtype=np.float64)
    total = p.sum()
    if center is None:
        cy, cx = np.unravel_index(int(np.argmax(p)), p.shape)
        center = (int(cx), int(cy))
    return p / total, center


def psf_kernel(psf: StrayLightPSF, shape: tuple[int, int]) -> np.ndarray:
    """The shift-invariant scattering kernel on the ``[2H-1, 2W-1]`` grid, centred at
    ``(H-1, W-1)``: Gaussians + veil + the measured PSF's scattered part, each times its
    weight. Excludes the ghost (not shift-invariant) and the ``delta`` / ``-W delta`` term."""
    h, w = shape
    k = np.zeros((2 * h - 1, 2 * w - 1))
    for g in psf.gaussians:
        if g.weight != 0:
            k += g.weight * gaussian_kernel(shape, g.sigma_x_px, g.sigma_y_px)
    if psf.veil:
        k += psf.veil / (h * w)  # every shift: each pixel gets veil * sum(S) / (H W)
    if psf.radial is not None:
        k += np.tensordot(np.asarray(psf.radial.values), radial_hats(psf.radial.radii_px, *shift_grid(shape),
                                                                     psf.radial.aspect), axes=1)
    if psf.measured is not None and psf.measured_scale != 0:
        p, (mcx, mcy) = _measured_normalised(psf.measured, psf.measured_center_px)
        p = p.copy()
        p[mcy, mcx] = 0.0  # the peak is the direct light, not scatter
        # Paste the measured image onto the shift grid, cropping what lies beyond it.
        ph, pw = p.shape
        y0, x0 = (h - 1) - mcy, (w - 1) - mcx
        ys, xs = max(0, y0), max(0, x0)
        ye, xe = min(2 * h - 1, y0 + ph), min(2 * w - 1, x0 + pw)
        if ye > ys and xe > xs:
            k[ys:ye, xs:xe] += psf.measured_scale * p[ys - y0:ye - y0, xs - x0:xe - x0]
    return k


def ghost_kernel(ghost: Ghost, shape: tuple[int, int], center_px: tuple[float, float]) -> np.ndarray:
    """Kernel of a ghost on the flipped image: ``ghost(S) = convolve(flip(S), ghost_kernel)``.

    Light at pixel ``p`` goes to ``2c - p``. With ``S'`` the image flipped in both axes
    (``S'[p'] = S[(W-1, H-1) - p']``), ``2c - p = p' + d`` with ``d = 2c - (W-1, H-1)``, so
    the ghost is ``S'`` convolved with the blur Gaussian shifted by ``d`` (sub-pixel: the
    pixel-integrated Gaussian, a box for ``sigma_px = 0``).
    """
    return ghost.weight * gaussian_kernel(shape, ghost.sigma_px, ghost.sigma_px, ghost_shift(shape, center_px))


def ghost_shift(shape: tuple[int, int], center_px: tuple[float, float]) -> tuple[float, float]:
    """``d = 2c - (W-1, H-1)``: the shift of the flipped image that mirrors through ``c``."""
    h, w = shape
    return 2.0 * center_px[0] - (w - 1), 2.0 * center_px[1] - (h - 1)


def radial_hats(radii_px: tuple[float, ...] | np.ndarray, dx: np.ndarray, dy: np.ndarray,
                aspect: float = 1.0) -> np.ndarray:
    """``[n, ...]``: the piecewise-linear-in-``log r`` hat functions of the knots at the shifts
    ``(dx, dy)`` (so ``k = sum_j values_j hat_j``); 0 at ``r = 0`` (the direct pixel), the
    first hat constant inside the first knot, nothing beyond the last."""
    radii = np.asarray(radii_px, dtype=np.float64)
    r = np.hypot(dx, np.asarray(dy) / aspect)
    lr = np.log(np.maximum(r, 1e-12))
    lk = np.log(radii)
    out = np.zeros((radii.size,) + np.shape(r))
    for j in range(radii.size):
        hat = np.zeros(np.shape(r))
        if j > 0:
            up = (lr >= lk[j - 1]) & (lr <= lk[j])
            hat[up] = (lr[up] - lk[j - 1]) / (lk[j] - lk[j - 1])
        else:
            hat[(r > 0) & (lr <= lk[0])] = 1.0
        if j + 1 < radii.size:
            down = (lr > lk[j]) & (lr < lk[j + 1])
            hat[down] = (lk[j + 1] - lr[down]) / (lk[j + 1] - lk[j])
        out[j] = hat
    return out


def radial_hat_sums(radii_px: tuple[float, ...] | np.ndarray, aspect: float = 1.0) -> np.ndarray:
    """Sum of each hat over the infinite pixel plane (the light one unit of ``values_j``
    moves): evaluated on a grid reaching past the last knot."""
    key = (tuple(float(r) for r in radii_px), float(aspect))
    if key not in _HAT_SUMS:
        half = int(math.ceil(max(key[0]) * max(1.0, aspect))) + 1
        y, x = np.mgrid[-half:half + 1, -half:half + 1].astype(np.float64)
        _HAT_SUMS[key] = radial_hats(key[0], x, y, aspect).sum(axis=(1, 2))
    return _HAT_SUMS[key]


_HAT_SUMS: dict[tuple[tuple[float, ...], float], np.ndarray] = {}


def shift_grid(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``(dx, dy)`` of the ``[2H-1, 2W-1]`` shift grid (centre ``(H-1, W-1)``)."""
    h, w = shape
    dy, dx = np.mgrid[-(h - 1):h, -(w - 1):w].astype(np.float64)
    return dx, dy


def field_rho2(shape: tuple[int, int], center_px: tuple[float, float]) -> np.ndarray:
    """``rho^2``: squared distance from the principal point over the squared half diagonal."""
    h, w = shape
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    return ((x - center_px[0]) ** 2 + (y - center_px[1]) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)


class GaussianBlur:
    """Pixel-integrated Gaussians of any widths and shifts applied to ONE image stack
    ``[..., H, W]`` (what a calibration does for every basis lobe): the image's FFT is taken
    once and each kernel's FFT is the outer product of two 1-D FFTs. ``blur(sx, sy,
    offset)`` equals ``convolve(s, gaussian_kernel(shape, sx, sy, offset), (H-1, W-1))``."""

    def __init__(self, s: np.ndarray, workers: int | None = None, *, single: bool = False) -> None:
        """``single``: transforms in single precision (half the time and memory; relative
        error ~1e-7 of the image's largest value, for a stray-light term of a few per cent of
        the light far below any measurement noise)."""
        s = np.asarray(s)
        self.h, self.w = s.shape[-2:]
        self.workers = workers
        self.ctype = np.complex64 if single else np.complex128
        self.fshape = fft_shape((self.h, self.w), (2 * self.h - 1, 2 * self.w - 1), (self.h - 1, self.w - 1))
        self.stack = s.shape[:-2]
        flat = s.reshape((-1, self.h, self.w))
        # An image that is zero everywhere (the ambient light of a scene without any) blurs to
        # zero: neither transformed nor blurred.
        self._lit = np.flatnonzero([np.any(x) for x in flat])
        if len(self._lit) == len(flat):
            lit = flat.astype(self.ctype, copy=False) if single else flat
        else:  # (one copy of the lit images, in the transform's precision)
            lit = np.empty((len(self._lit), self.h, self.w), dtype=self.ctype if single else flat.dtype)
            for j, i in enumerate(self._lit):
                lit[j] = flat[i]
        self._sf = sfft.fft2(lit, s=self.fshape, axes=(-2, -1), workers=workers)

    def __call__(self, sigma_x_px: float, sigma_y_px: float,
                 offset_px: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
        fy = sfft.fft(_pixel_gauss_1d(np.arange(-(self.h - 1), self.h, dtype=np.float64), offset_px[1],
                                      sigma_y_px), n=self.fshape[0]).astype(self.ctype, copy=False)
        fx = sfft.fft(_pixel_gauss_1d(np.arange(-(self.w - 1), self.w, dtype=np.float64), offset_px[0],
                                      sigma_x_px), n=self.fshape[1]).astype(self.ctype, copy=False)
        # Inverse along x, crop to the sensor's columns, then along y: half the work. One image
        # of the stack at a time: the padded temporaries are one image's, not the stack's
        # (at 512 x 512 a stack of 4 needed ~100 MB of them; each 1-D transform is the same).
        out = np.zeros((int(np.prod(self.stack)), self.h, self.w), dtype=self.ctype)
        for sf, i in zip(self._sf, self._lit):
            t = sfft.ifft(sf * fx, axis=-1, workers=self.workers)[:, self.w - 1:2 * self.w - 1]
            out[i] = sfft.ifft(t * fy[:, None], axis=-2, workers=self.workers)[self.h - 1:2 * self.h - 1, :]
        return out.reshape(self.stack + (self.h, self.w))


def lobes_only(psf: StrayLightPSF) -> bool:
    """True for a PSF of shift-invariant Gaussian lobes and a veil only (the form diagnosis
    fits): :func:`apply_lobes` applies it with the image's transform kept."""
    return (psf.radial is None and (psf.measured is None or psf.measured_scale == 0)
            and not any(g.weight for g in psf.ghosts)
            and not any(g.field_weight or g.field_weight4 for g in psf.gaussians))


#: The transforms of the last few images :func:`apply_lobes` scattered, by content: a fit
#: that changes only the PSF (every stray-light Jacobian column) transforms its image once.
_BLURS_KEPT = 1
_BLURS = LRUCache(_BLURS_KEPT)


#: The last results of :func:`apply_lobes`, by image content and PSF: a fit of an effect that
#: acts after the stray light, with the stray light held, scatters the same light every time.
_SCATTERED_KEPT = 1
_SCATTERED = LRUCache(_SCATTERED_KEPT)


def _blur_of(s: np.ndarray, key: str | None = None) -> GaussianBlur:
    key = content_digest(s) if key is None else key
    blur = _BLURS.get(key)
    if blur is None:
        _BLURS.make_room()  # (before the new one: never two frames' worth at once)
        blur = GaussianBlur(s, single=True)
        _BLURS.put(key, blur)
    return blur


def apply_lobes(psf: StrayLightPSF, s: np.ndarray) -> np.ndarray:
    """``keep * S + h * S`` on images ``[..., H, W]`` for a PSF of Gaussian lobes and a veil
    (:func:`lobes_only`): each lobe a separable blur of the image's transform (computed once
    per image content, :class:`GaussianBlur`, in single precision), the veil ``veil * sum(S) /
    (H W)`` on every pixel (its kernel is constant over every shift between two pixels). The
    operator of :class:`StrayLightOperator` to ~1e-7 of the scattered light."""
    if not lobes_only(psf):
        raise ValueError("apply_lobes takes Gaussian lobes and a veil only")
    s = np.asarray(s)
    h, w = s.shape[-2:]
    lobes = [g for g in psf.gaussians if g.weight]
    image = content_digest(s)
    key = (image, psf.keep, psf.veil, tuple((g.weight, g.sigma_x_px, g.sigma_y_px) for g in lobes))
    done = _SCATTERED.get(key)
    if done is not None:
        return done.copy()
    _SCATTERED.make_room()  # (a miss: the kept result is another light's or PSF's)
    out = np.multiply(s, psf.keep, dtype=np.result_type(s.dtype, np.float64))  # (no copy of s first)
    if lobes:
        blur = _blur_of(s, image)
        for g in lobes:
            b = blur(g.sigma_x_px, g.sigma_y_px)
            out += g.weight * (b if np.iscomplexobj(out) else b.real)
    if psf.veil:
        out += (psf.veil / (h * w)) * s.sum(axis=(-2, -1), keepdims=True)
    _SCATTERED.put(key, out.copy())
    return out


# ---------------------------------------------------------------------------------------------
# Padded FFT convolution (linear, no wrap-around)
# ---------------------------------------------------------------------------------------------
def fft_shape(image_shape: tuple[int, int], kernel_shape: tuple[int, int],
              kernel_center: tuple[int, int] | None = None) -> tuple[int, int]:
    """Smallest fast FFT size for which the retained ``[H, W]`` window of the circular
    convolution equals the linear one (the wrapped part lands only on discarded samples).

    For a kernel of length ``kh`` with centre ``ch`` the output sample ``q`` is the full
    linear convolution's ``q + ch``; aliasing stays out of ``[ch, ch + H - 1]`` when
    ``N >= H + max(ch, kh - 1 - ch)``.
    """
    out = []
    for n, kn, c in zip(image_shape, kernel_shape, kernel_center or (kernel_shape[0] // 2, kernel_shape[1] // 2)):
        out.append(sfft.next_fast_len(int(n + max(c, kn - 1 - c)), real=False))
    return out[0], out[1]


@dataclass
class PaddedConvolution:
    """``S -> S * kernel`` (linear, 'same' size, kernel centre at ``center``) for images of a
    fixed shape, with the kernel's FFT computed once. ``adjoint`` is the correlation."""

    kernel: np.ndarray
    image_shape: tuple[int, int]
    center: tuple[int, int] | None = None
    workers: int | None = None

    def __post_init__(self) -> None:
        self.kernel = np.asarray(self.kernel)
        if self.kernel.ndim != 2:
            raise ValueError(f"kernel must be 2-D, got shape {self.kernel.shape}")
        if self.center is None:
            self.center = (self.kernel.shape[0] // 2, self.kernel.shape[1] // 2)
        self.fshape = fft_shape(self.image_shape, self.kernel.shape, self.center)
        # Adjoint kernel: the flipped kernel with the mirrored centre; it needs its own size.
        kh, kw = self.kernel.shape
        self._adj_center = (kh - 1 - self.center[0], kw - 1 - self.center[1])
        self.fshape_adj = fft_shape(self.image_shape, self.kernel.shape, self._adj_center)

    @cached_property
    def _kfft(self) -> np.ndarray:
        return sfft.fft2(self.kernel, s=self.fshape)

    @cached_property
    def _kfft_adj(self) -> np.ndarray:
        return sfft.fft2(np.conj(self.kernel[::-1, ::-1]), s=self.fshape_adj)

    def _run(self, s: np.ndarray, kfft: np.ndarray, fshape: tuple[int, int], center: tuple[int, int]) -> np.ndarray:
        s = np.asarray(s)
        if s.shape[-2:] != tuple(self.image_shape):
            raise ValueError(f"image is {s.shape[-2:]}, operator built for {tuple(self.image_shape)}")
        real = not np.iscomplexobj(s) and not np.iscomplexobj(self.kernel)
        h, w = self.image_shape
        cy, cx = center
        if real:
            sf = sfft.rfft2(s, s=fshape, workers=self.workers)
            kf = kfft[..., : fshape[1] // 2 + 1]
            full = sfft.irfft2(sf * kf, s=fshape, workers=self.workers)
        else:
            sf = sfft.fft2(s, s=fshape, workers=self.workers)
            full = sfft.ifft2(sf * kfft, workers=self.workers)
        return full[..., cy:cy + h, cx:cx + w]

    def __call__(self, s: np.ndarray) -> np.ndarray:
        return self._run(s, self._kfft, self.fshape, self.center)  # type: ignore[arg-type]

    def adjoint(self, s: np.ndarray) -> np.ndarray:
        return self._run(s, self._kfft_adj, self.fshape_adj, self._adj_center)


def convolve(s: np.ndarray, kernel: np.ndarray, center: tuple[int, int] | None = None) -> np.ndarray:
    """Linear 2-D convolution of images ``[..., H, W]`` (real or complex) with ``kernel``,
    same-size output: ``out[q] = sum_j kernel[j] s[q - (j - center)]``. ``center`` is the
    kernel's origin index (default: its middle). Zero-padded FFT, no wrap-around."""
    s = np.asarray(s)
    return PaddedConvolution(kernel, s.shape[-2:], center)(s)


def correlate(s: np.ndarray, kernel: np.ndarray, center: tuple[int, int] | None = None) -> np.ndarray:
    """The adjoint of :func:`convolve` (correlation with the conjugate kernel)."""
    s = np.asarray(s)
    return PaddedConvolution(kernel, s.shape[-2:], center).adjoint(s)


def flip_image(s: np.ndarray) -> np.ndarray:
    """Mirror ``[..., H, W]`` in both axes (pixel ``p`` -> ``(W-1, H-1) - p``)."""
    return np.asarray(s)[..., ::-1, ::-1]


def _pixel_matrix(n: int, sigma: float, *, mirror_about: float | None = None,
                  magnification: float = -1.0) -> np.ndarray:
    """``[n, n]`` matrix of the pixel-integrated 1-D Gaussian: ``M[q, p] = g(q - p)`` (Toeplitz),
    or with ``mirror_about = c`` the ghost's ``M[q, p] = g(q - (c + m (p - c)))`` (``m = -1``:
    Hankel, the mirror)."""
    q = np.arange(n, dtype=np.float64)[:, None]
    p = np.arange(n, dtype=np.float64)[None, :]
    if mirror_about is None:
        shift = q - p
    else:
        shift = q - (mirror_about + magnification * (p - mirror_about))
        # A source pixel lands on |m| pixels: its footprint widens the blur (a box's variance).
        sigma = math.sqrt(sigma * sigma + max(magnification * magnification - 1.0, 0.0) / 12.0)
    return _pixel_gauss_1d(shift, 0.0, sigma)


def _separable(s: np.ndarray, my: np.ndarray, mx: np.ndarray) -> np.ndarray:
    """``My @ S @ Mx^T`` on images ``[..., H, W]`` (real matrices; complex images done as two
    real products, which BLAS runs at real speed)."""
    # Contiguous operands: numpy's matmul on a strided view (the real part of a complex array)
    # bypasses BLAS and is ~400x slower.
    if np.iscomplexobj(s):
        out = np.empty(s.shape, dtype=np.complex128)
        out.real = my @ np.ascontiguousarray(s.real) @ mx.T
        out.imag = my @ np.ascontiguousarray(s.imag) @ mx.T
        return out
    return my @ np.ascontiguousarray(s) @ mx.T


class StrayLightOperator:
    """``S -> (delta + h) * S`` for images of one size; kernels built once.

    ``apply`` is the forward model, ``scatter`` the stray light alone (``apply(S) = keep * S +
    scatter(S)``), ``adjoint`` the transpose (for least-squares corrections), ``invert`` the
    correction (fixed-point deconvolution). A ghost without a centre mirrors through
    ``center_px`` (the camera's principal point; default the image centre).

    ``method``: ``"separable"`` evaluates Gaussian lobes and ghosts as products with
    ``[H, H]`` and ``[W, W]`` pixel-Gaussian matrices (exact linear convolution, no padding
    needed) and the veil as a sum; ``"fft"`` (and ``"auto"``) uses the zero-padded FFT with the
    ``[2H-1, 2W-1]`` kernels. A measured PSF always goes through the FFT. Both give the same
    operator; the separable form is faster with a single-threaded BLAS, but multi-threaded
    BLAS on a busy machine makes it unpredictable, so the FFT is the default.
    """

    def __init__(self, psf: StrayLightPSF, shape: tuple[int, int],
                 center_px: tuple[float, float] | None = None, workers: int | None = None,
                 method: str = "auto") -> None:
        if method not in ("auto", "fft", "separable"):
            raise ValueError(f"method must be auto, fft or separable, got {method!r}")
        self.psf = psf
        self.shape = (int(shape[0]), int(shape[1]))
        h, w = self.shape
        c = center_px or ((w - 1) / 2.0, (h - 1) / 2.0)
        self.center_px = (float(c[0]), float(c[1]))
        self.keep: float | np.ndarray = psf.keep
        # A radial profile is not separable: it always goes through the FFT.
        self.method = ("fft" if method == "auto" or psf.radial is not None
                       or any(g.field_weight or g.field_weight4 for g in psf.gaussians) else method)
        self._field: PaddedConvolution | None = None
        self._field4: PaddedConvolution | None = None
        rad = psf.radial
        field_lobes = [g for g in psf.gaussians if g.field_weight]
        if field_lobes or (rad is not None and rad.field_values and np.any(rad.field_values)):
            # Shift-variant part: kernel applied to rho^2 S (a source's lobe grows with rho^2).
            self._rho2 = field_rho2(self.shape, self.center_px)
            kf = np.zeros((2 * h - 1, 2 * w - 1))
            moved = 0.0
            for g in field_lobes:
                kf += g.field_weight * gaussian_kernel(self.shape, g.sigma_x_px, g.sigma_y_px)
                moved += g.field_weight
            if rad is not None and rad.field_values:
                kf += np.tensordot(np.asarray(rad.field_values), radial_hats(rad.radii_px, *shift_grid(self.shape),
                                                                             rad.aspect), axes=1)
                moved += rad.field_weight
            self._field = PaddedConvolution(kf, self.shape, (h - 1, w - 1), workers)
            if psf.direct is None and psf.conserve:
                self.keep = psf.keep - self._rho2 * moved  # the field lobe moves light too
        lobes4 = [g for g in psf.gaussians if g.field_weight4]
        if lobes4:
            # Second order in the field: the kernel applied to rho^4 S.
            self._rho2 = field_rho2(self.shape, self.center_px)
            k4 = sum(g.field_weight4 * gaussian_kernel(self.shape, g.sigma_x_px, g.sigma_y_px) for g in lobes4)
            self._field4 = PaddedConvolution(k4, self.shape, (h - 1, w - 1), workers)
            if psf.direct is None and psf.conserve:
                self.keep = self.keep - self._rho2 ** 2 * sum(g.field_weight4 for g in lobes4)
        self._conv: PaddedConvolution | None = None
        self._ghosts: list[PaddedConvolution] = []
        self._lobes: list[tuple[float, np.ndarray, np.ndarray]] = []
        self._ghost_mats: list[tuple[float, np.ndarray, np.ndarray]] = []
        ghosts = [(g, self.ghost_center(g)) for g in psf.ghosts if g.weight and g.is_mirror]
        # Ghosts with another magnification or a delay: separable matrices in either method
        # (a magnified image is not a convolution), each with its extra optical path.
        self._gen_ghosts: list[tuple[float, np.ndarray, np.ndarray, float]] = [
            (g.weight, _pixel_matrix(h, g.sigma_px, mirror_about=gc[1], magnification=g.magnification),
             _pixel_matrix(w, g.sigma_px, mirror_about=gc[0], magnification=g.magnification), g.extra_path_m)
            for g, gc in ((g, self.ghost_center(g)) for g in psf.ghosts if g.weight and not g.is_mirror)]
        if self.method == "separable":
            for g in psf.gaussians:
                if g.weight:
                    self._lobes.append((g.weight, _pixel_matrix(h, g.sigma_y_px), _pixel_matrix(w, g.sigma_x_px)))
            for g, gc in ghosts:
                self._ghost_mats.append((g.weight, _pixel_matrix(h, g.sigma_px, mirror_about=gc[1]),
                                         _pixel_matrix(w, g.sigma_px, mirror_about=gc[0])))
            if psf.measured is not None and psf.measured_scale != 0:
                # Only the measured part goes through the FFT here.
                k = psf_kernel(StrayLightPSF(measured=psf.measured, measured_center_px=psf.measured_center_px,
                                             measured_scale=psf.measured_scale), self.shape)
                self._conv = PaddedConvolution(k, self.shape, (h - 1, w - 1), workers)
        else:
            k = psf_kernel(psf, self.shape)
            self._conv = PaddedConvolution(k, self.shape, (h - 1, w - 1), workers) if np.any(k) else None
            # Ghosts sharing a centre share one kernel (and one FFT per application).
            by_centre: dict[tuple[float, float], np.ndarray] = {}
            for g, gc in ghosts:
                by_centre[gc] = by_centre.get(gc, 0.0) + ghost_kernel(g, self.shape, gc)
            self._ghosts = [PaddedConvolution(gk, self.shape, (h - 1, w - 1), workers) for gk in by_centre.values()]

    def ghost_center(self, ghost: Ghost) -> tuple[float, float]:
        """The point a ghost mirrors through: its own centre, else the principal point."""
        c = ghost.center_px or self.center_px
        return float(c[0]), float(c[1])

    def _general_ghosts(self, s: np.ndarray, out: np.ndarray, freq_hz: Any, adjoint: bool) -> np.ndarray:
        """Adds the magnified/delayed ghosts; ``freq_hz`` (broadcast against ``s``, e.g.
        ``[F, NH, 1, 1]``: each channel's modulation frequency x harmonic) delays a ghost's
        phasor by ``exp(i 2 pi f extra_path / c)``; None = unmodulated light (no delay)."""
        for wgt, my, mx, path in self._gen_ghosts:
            img = _separable(s, my.T, mx.T) if adjoint else _separable(s, my, mx)
            if path and freq_hz is not None:
                ph = np.exp(2j * np.pi * np.asarray(freq_hz, dtype=np.float64) * path / C_M_PER_S)
                img = img * (np.conj(ph) if adjoint else ph)
                if not np.iscomplexobj(out):
                    out = out.astype(np.complex128)
            out = out + wgt * img
        return out

    def scatter(self, s: np.ndarray, freq_hz: Any = None) -> np.ndarray:
        """The stray light only: ``h * S`` (without the direct part); ``freq_hz`` see
        :meth:`_general_ghosts` (only ghosts with an extra path need it)."""
        s = np.asarray(s)
        out = np.zeros(s.shape, dtype=np.result_type(s.dtype, np.float64))
        out = self._general_ghosts(s, out, freq_hz, adjoint=False)
        if self.method == "separable":
            for wgt, my, mx in self._lobes + self._ghost_mats:
                out += wgt * _separable(s, my, mx)
            if self.psf.veil:
                h, w = self.shape
                out += (self.psf.veil / (h * w)) * s.sum(axis=(-2, -1), keepdims=True)
        elif self._ghosts:
            flipped = flip_image(s)
            for gc in self._ghosts:
                out += gc(flipped)
        if self._conv is not None:
            out += self._conv(s)
        if self._field is not None:
            out += self._field(self._rho2 * s)
        if self._field4 is not None:
            out += self._field4(self._rho2 ** 2 * s)
        return out

    def scatter_adjoint(self, s: np.ndarray, freq_hz: Any = None) -> np.ndarray:
        """Transpose of :meth:`scatter` (conjugate transpose for complex kernels)."""
        s = np.asarray(s)
        out = np.zeros(s.shape, dtype=np.result_type(s.dtype, np.float64))
        out = self._general_ghosts(s, out, freq_hz, adjoint=True)
        if self.method == "separable":
            for wgt, my, mx in self._lobes + self._ghost_mats:
                out += wgt * _separable(s, my.T, mx.T)
            if self.psf.veil:
                h, w = self.shape
                out += (self.psf.veil / (h * w)) * s.sum(axis=(-2, -1), keepdims=True)
        else:
            for gc in self._ghosts:
                out += flip_image(gc.adjoint(s))
        if self._conv is not None:
            out += self._conv.adjoint(s)
        if self._field is not None:
            out += self._rho2 * self._field.adjoint(s)
        if self._field4 is not None:
            out += self._rho2 ** 2 * self._field4.adjoint(s)
        return out

    def apply(self, s: np.ndarray, freq_hz: Any = None) -> np.ndarray:
        """``S_meas = keep * S + scatter(S)``."""
        return self.keep * np.asarray(s) + self.scatter(s, freq_hz)

    __call__ = apply

    def adjoint(self, s: np.ndarray, freq_hz: Any = None) -> np.ndarray:
        """Transpose of :meth:`apply` (conjugate transpose for complex kernels)."""
        s = np.asarray(s)
        return self.keep * s.astype(np.result_type(s.dtype, np.float64)) + self.scatter_adjoint(s, freq_hz)

    @property
    def scattered_fraction(self) -> float:
        """Largest fraction of one pixel's light that lands on other pixels of this sensor:
        the operator 1-norm of ``h`` on the sensor (its largest column sum; every part of
        ``h`` is non-negative). Light scattered beyond the edge does not count, so it is at
        most :attr:`StrayLightPSF.total_weight`."""
        if not hasattr(self, "_scattered"):
            self._scattered = float(self.scatter_adjoint(np.ones(self.shape)).max())
        return self._scattered

    def invert(self, s_meas: np.ndarray, *, iterations: int = 30, tol: float = 1e-7,
               freq_hz: Any = None) -> np.ndarray:
        """Remove the stray light: solve ``keep * S + h * S = S_meas`` by the fixed point
        ``S_{k+1} = (S_meas - h * S_k) / keep`` (a Neumann series; Kavli et al. 2008).

        The error shrinks by ``scattered_fraction / keep`` per iteration, so a few tens of
        iterations reach float precision for realistic optics (< 0.3). Stops early when the
        update is below ``tol`` of the signal. Refuses optics it cannot invert this way.
        """
        keep_min = float(np.min(self.keep))
        ratio = self.scattered_fraction / keep_min if keep_min > 0 else math.inf
        if ratio >= 1.0:
            raise TofhilError(f"the PSF scatters {self.scattered_fraction:.3f} of the signal against a direct "
                              f"part of {keep_min:.3f}; the fixed-point inversion needs a ratio < 1",
                              field="psf", expected="scattered fraction / direct < 1")
        s_meas = np.asarray(s_meas)
        scale = float(np.abs(s_meas).max()) or 1.0
        s = s_meas.astype(np.result_type(s_meas.dtype, np.float64), copy=True)
        for _ in range(iterations):
            nxt = (s_meas - self.scatter(s, freq_hz)) / self.keep
            done = float(np.abs(nxt - s).max()) <= tol * scale
            s = nxt
            if done:
                break
        return s


def apply_stray_light(s: np.ndarray, psf_params: StrayLightPSF | Mapping[str, Any],
                      camera: CameraModel | None = None) -> np.ndarray:
    """``S_meas = (delta + h) * S`` on images ``[..., H, W]``; ghosts without a centre mirror
    through the camera's principal point (or the image centre without a camera)."""
    psf = psf_params if isinstance(psf_params, StrayLightPSF) else StrayLightPSF.from_params(psf_params)
    if psf.is_identity:
        return np.array(s, copy=True)
    s = np.asarray(s)
    center = (camera.cx, camera.cy) if camera is not None else None
    return StrayLightOperator(psf, s.shape[-2:], center).apply(s)


# ---------------------------------------------------------------------------------------------
# Parameters (the `stray_light` effect's mapping)
# ---------------------------------------------------------------------------------------------
PSF_KEYS = ("weight", "sigma_px", "sigma_y_px", "gaussians", "veil", "ghost_weight", "ghost_sigma_px",
            "ghost_center_px", "ghosts", "psf_file", "psf_center_px", "psf_scale", "conserve", "direct", "radial")


def _num(params: Mapping[str, Any], key: str, default: float, *, source: str | Path, prefix: str,
         lo: float = 0.0, hi: float = math.inf, expected: str = "a number >= 0") -> float:
    return Schema(source).number(params.get(key, default), f"{prefix}.{key}", lo=lo,
                                 hi=None if hi == math.inf else hi, expected=expected)


def _pair(v: Any, *, source: str | Path, field_: str) -> tuple[float, float]:
    try:
        a, b = (float(x) for x in v)
    except (TypeError, ValueError):
        a = b = math.nan
    if not (math.isfinite(a) and math.isfinite(b)):
        raise InputFileError(f"got {v!r}", file=source, field=field_, expected="[x, y] in pixels")
    return a, b


def load_psf_image(path: str | Path, *, source: str | Path = "<effects>", field_: str = "psf_file") -> np.ndarray:
    """A measured PSF image: ``.npy`` or an image file OpenCV reads (16-bit PNG, TIFF, ...)."""
    p = Path(path)
    if not p.is_file():
        raise InputFileError(f"no such file {str(p)!r}", file=source, field=field_,
                             expected="a PSF image (.npy, .png, .tif)")
    if p.suffix.lower() == ".npy":
        img = np.load(p)
    else:
        import cv2

        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH)
        if img is None:
            raise InputFileError("cannot be read as an image", file=p, field=field_,
                                 expected="a PSF image (.npy, .png, .tif)")
        if img.ndim == 3:
            img = img.mean(axis=2)
    img = np.asarray(img, dtype=np.float64)
    if img.ndim == 2 and np.all(np.isfinite(img)) and img.size and img.min() >= -1e-9 * np.abs(img).max():
        img = np.clip(img, 0.0, None)  # round-off below zero (e.g. an FFT-made PSF) is zero light
    if img.ndim != 2 or not np.all(np.isfinite(img)) or img.min() < 0 or img.sum() <= 0:
        raise InputFileError("is not a 2-D non-negative image with positive sum", file=p, field=field_,
                             expected="a PSF image (.npy, .png, .tif)")
    return img


def _psf_from_params(params: Mapping[str, Any], *, source: str | Path, prefix: str,
                     base_dir: Path | None) -> StrayLightPSF:
    if not isinstance(params, Mapping):
        raise InputFileError(f"got {params!r}", file=source, field=prefix, expected="a mapping of parameters")
    unknown = sorted(set(params) - set(PSF_KEYS))
    if unknown:
        raise InputFileError(f"unknown parameter {unknown[0]!r}", file=source, field=f"{prefix}.{unknown[0]}",
                             expected="one of " + ", ".join(PSF_KEYS))
    kw: dict[str, Any] = {}
    lobes: list[GaussianLobe] = []
    weight = _num(params, "weight", 0.0, source=source, prefix=prefix, hi=1.0, expected="a fraction in [0, 1]")
    if weight:
        sx = _num(params, "sigma_px", 20.0, source=source, prefix=prefix, expected="a sigma in pixels >= 0")
        sy = _num(params, "sigma_y_px", sx, source=source, prefix=prefix, expected="a sigma in pixels >= 0")
        lobes.append(GaussianLobe(weight, sx, sy))
    for i, g in enumerate(params.get("gaussians") or []):
        try:
            vals = [float(x) for x in g]
            if len(vals) == 2:
                vals.append(vals[1])
            if len(vals) == 3:
                vals.append(0.0)
            if len(vals) == 4:
                vals.append(0.0)
            w, sx, sy, fw, fw4 = vals
            ok = 0 <= w <= 1 and 0 <= sx < math.inf and 0 <= sy < math.inf and -1 <= fw <= 1 and -1 <= fw4 <= 1
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise InputFileError(f"got {g!r}", file=source, field=f"{prefix}.gaussians[{i}]",
                                 expected="[weight in [0, 1], sigma_x_px >= 0, sigma_y_px >= 0(, field_weight "
                                          "in [-1, 1](, field_weight4 in [-1, 1]))]")
        lobes.append(GaussianLobe(w, sx, sy, fw, fw4))
    kw["gaussians"] = tuple(lobes)
    kw["veil"] = _num(params, "veil", 0.0, source=source, prefix=prefix, hi=1.0, expected="a fraction in [0, 1]")
    ghosts: list[Ghost] = []
    gw = _num(params, "ghost_weight", 0.0, source=source, prefix=prefix, hi=1.0, expected="a fraction in [0, 1]")
    gs = _num(params, "ghost_sigma_px", 0.0, source=source, prefix=prefix, expected="a sigma in pixels >= 0")
    gc = None
    if params.get("ghost_center_px") is not None:
        gc = _pair(params["ghost_center_px"], source=source, field_=f"{prefix}.ghost_center_px")
    if gw:
        ghosts.append(Ghost(gw, gs, gc))
    extra = params.get("ghosts") or []
    if not isinstance(extra, (list, tuple)):
        raise InputFileError(f"got {extra!r}", file=source, field=f"{prefix}.ghosts",
                             expected="a list of [weight, sigma_px] or [weight, sigma_px, cx, cy]")
    for i, g in enumerate(extra):
        if isinstance(g, Mapping):
            ghosts.append(_ghost_from_mapping(g, source=source, field_=f"{prefix}.ghosts[{i}]"))
            continue
        try:
            vals = [float(x) for x in g]
            ok = len(vals) in (2, 4) and all(map(math.isfinite, vals)) and 0 <= vals[0] <= 1 and vals[1] >= 0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise InputFileError(f"got {g!r}", file=source, field=f"{prefix}.ghosts[{i}]",
                                 expected="[weight in [0, 1], sigma_px >= 0] or [weight, sigma_px, cx, cy]")
        ghosts.append(Ghost(vals[0], vals[1], (vals[2], vals[3]) if len(vals) == 4 else None))
    kw["ghosts"] = tuple(ghosts)
    if params.get("psf_file"):
        f = Path(str(params["psf_file"]))
        if not f.is_absolute() and base_dir is not None:
            f = base_dir / f
        kw["measured"] = load_psf_image(f, source=source, field_=f"{prefix}.psf_file")
        kw["measured_scale"] = _num(params, "psf_scale", 1.0, source=source, prefix=prefix,
                                    expected="a scale >= 0")
        if params.get("psf_center_px") is not None:
            cx, cy = _pair(params["psf_center_px"], source=source, field_=f"{prefix}.psf_center_px")
            ph, pw = kw["measured"].shape
            if not (float(cx).is_integer() and float(cy).is_integer() and 0 <= cx < pw and 0 <= cy < ph):
                raise InputFileError(f"got {params['psf_center_px']!r}", file=source,
                                     field=f"{prefix}.psf_center_px",
                                     expected=f"integer pixel [x, y] inside the {pw}x{ph} PSF image")
            kw["measured_center_px"] = (int(cx), int(cy))
    if params.get("radial") is not None:
        kw["radial"] = _radial_from_params(params["radial"], source=source, field_=f"{prefix}.radial")
    conserve = params.get("conserve", True)
    if not isinstance(conserve, bool):
        raise InputFileError(f"got {conserve!r}", file=source, field=f"{prefix}.conserve", expected="true or false")
    kw["conserve"] = conserve
    if params.get("direct") is not None:
        kw["direct"] = _num(params, "direct", 1.0, source=source, prefix=prefix, hi=1.0,
                            expected="a fraction in (0, 1]")
        if kw["direct"] <= 0:
            raise InputFileError(f"got {params['direct']!r}", file=source, field=f"{prefix}.direct",
                                 expected="a fraction in (0, 1]")
    psf = StrayLightPSF(**kw)
    if psf.conserve and psf.direct is None and psf.total_weight > 1.0 + 1e-12:
        raise InputFileError(f"the weights add up to {psf.total_weight:g}", file=source, field=prefix,
                             expected="a total scattered fraction <= 1")
    return psf


def _ghost_from_mapping(g: Mapping[str, Any], *, source: str | Path, field_: str) -> Ghost:
    expected = ("{weight: in [0, 1], sigma_px: >= 0, magnification: a non-zero number (default -1), "
                "extra_path_m: metres (default 0), center_px: [x, y] (optional)}")
    try:
        unknown = set(g) - {"weight", "sigma_px", "magnification", "extra_path_m", "center_px"}
        w, sg = float(g["weight"]), float(g.get("sigma_px", 0.0))
        m, path = float(g.get("magnification", -1.0)), float(g.get("extra_path_m", 0.0))
        c = g.get("center_px")
        cc = None if c is None else (float(c[0]), float(c[1]))
        ok = (not unknown and all(map(math.isfinite, (w, sg, m, path) + (cc or ()))) and 0 <= w <= 1 and sg >= 0
              and m != 0 and (c is None or len(c) == 2))
    except (TypeError, ValueError, KeyError, IndexError):
        ok = False
    if not ok:
        raise InputFileError(f"got {dict(g)!r}", file=source, field=field_, expected=expected)
    return Ghost(w, sg, cc, m, path)


def _radial_from_params(v: Any, *, source: str | Path, field_: str) -> RadialProfile:
    expected = ("{radii_px: [increasing radii > 0], values: [per-pixel fractions >= 0, one per radius], "
                "field_values: [one per radius] (optional), aspect: > 0 (optional)}")
    try:
        radii = [float(x) for x in v["radii_px"]]
        values = [float(x) for x in v["values"]]
        fv = [float(x) for x in (v.get("field_values") or [])]
        aspect = float(v.get("aspect", 1.0))
        unknown = set(v) - {"radii_px", "values", "field_values", "aspect"}
        ok = (not unknown and len(radii) >= 1 and len(values) == len(radii) and len(fv) in (0, len(radii))
              and all(map(math.isfinite, radii + values + fv)) and radii[0] > 0
              and all(b > a for a, b in zip(radii, radii[1:])) and min(values) >= 0
              and math.isfinite(aspect) and aspect > 0
              and all(a + b >= 0 for a, b in zip(values, fv or [0.0] * len(values))))
    except (TypeError, ValueError, KeyError, AttributeError):
        ok = False
    if not ok:
        raise InputFileError(f"got {v!r}", file=source, field=field_, expected=expected)
    return RadialProfile(tuple(radii), tuple(values), tuple(fv), aspect)
