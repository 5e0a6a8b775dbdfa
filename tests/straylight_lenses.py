"""Lenses of other forms than the correction's model, written independently of tofhil's optics.

Each lens scatters the complex signal ``S`` of the synthetic scene (``tests/straylight_synthetic``,
80 x 60) with kernels written here (numpy/scipy only, nothing from ``tofhil.sim.straylight``):

    S_meas = (1 - W) S + sum_k w_k (K_k * S)  [+ ghosts: w_g blur(S mirrored through c_g)]

Every kernel ``K_k`` is normalised to unit sum over a grid much larger than the sensor, so the
lens moves a fraction ``W`` of every pixel's light (energy conserved; light scattered beyond
the sensor edge is lost). The dark-square error is the mean |distance error| over the dark
square's pixels against the stray-light-free signal.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.signal import fftconvolve

from tests.straylight_synthetic import CAMERA, FREQ, H, SQUARE, W, scene_signal
from tofhil import C_M_PER_S

#: Half-size of the grid every kernel is normalised on (pixels): far beyond the sensor.
BIG = 400
CX, CY = CAMERA.cx, CAMERA.cy


def _grid(half: int) -> tuple[np.ndarray, np.ndarray]:
    y, x = np.mgrid[-half:half + 1, -half:half + 1].astype(np.float64)
    return x, y


def gaussian(sigma_x: float, sigma_y: float | None = None) -> np.ndarray:
    """A sampled Gaussian (pixel centres, oversampled 5x5 inside each pixel), unit sum."""
    sy = sigma_x if sigma_y is None else sigma_y
    half = int(min(BIG, np.ceil(6 * max(sigma_x, sy)) + 2))
    x, y = _grid(half)
    sub = (np.arange(5) - 2) / 5.0
    k = np.zeros_like(x)
    for a in sub:
        for b in sub:
            k += np.exp(-0.5 * (((x + a) / sigma_x) ** 2 + ((y + b) / sy) ** 2))
    return k / k.sum()


def power_law(r0: float = 1.5, p: float = 3.0) -> np.ndarray:
    """``(r^2 + r0^2)^(-p/2)``: an r^-p tail, unit sum over the big grid."""
    x, y = _grid(BIG)
    k = (x ** 2 + y ** 2 + r0 ** 2) ** (-p / 2)
    return k / k.sum()


def crop(k: np.ndarray) -> np.ndarray:
    """The part of a centred kernel that reaches from any sensor pixel to any other."""
    c = k.shape[0] // 2
    hy, hx = min(c, H - 1), min(c, W - 1)
    return k[c - hy:c + hy + 1, c - hx:c + hx + 1]


def convolve(s: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Linear (zero-padded) convolution of the complex image with a centred kernel."""
    k = crop(k)
    hy, hx = k.shape[0] // 2, k.shape[1] // 2
    full = fftconvolve(s.real, k, mode="full") + 1j * fftconvolve(s.imag, k, mode="full")
    return full[hy:hy + H, hx:hx + W]


def ghost(s: np.ndarray, c: tuple[float, float], sigma: float, pad: int = 60) -> np.ndarray:
    """Light at pixel p is imaged at 2c - p (c on the half-pixel grid: integer targets) and
    blurred there, on a canvas larger than the sensor (the optics form the ghost before the
    sensor crops it: light mirrored just past the edge blurs back in); then cropped."""
    canvas = np.zeros((H + 2 * pad, W + 2 * pad), dtype=s.dtype)
    ys, xs = np.mgrid[0:H, 0:W]
    tx, ty = np.rint(2 * c[0] - xs).astype(int) + pad, np.rint(2 * c[1] - ys).astype(int) + pad
    ok = (tx >= 0) & (tx < W + 2 * pad) & (ty >= 0) & (ty < H + 2 * pad)
    canvas[ty[ok], tx[ok]] = s[ok]
    if sigma > 0:
        k = gaussian(sigma)
        canvas = (fftconvolve(canvas.real, k, mode="same") + 1j * fftconvolve(canvas.imag, k, mode="same"))
    return canvas[pad:pad + H, pad:pad + W]


def magnified_ghost(s: np.ndarray, c: tuple[float, float], m: float, sigma: float, pad: int = 60,
                    sub: int = 5) -> np.ndarray:
    """A ghost that images the scene scaled by ``m`` about ``c`` (light at p lands at
    ``c + m (p - c)``; ``m = -1`` is the mirror, a filter's ghost is near ``+1``): each pixel's
    area is split into ``sub x sub`` parts, each part's light moved to its image point and
    binned into the pixel there (a magnified pixel covers ``|m|`` pixels), then blurred, on a
    canvas larger than the sensor; cropped. Every part of the light lands somewhere on the
    canvas, so the ghost moves exactly its weight of the light that stays near the sensor."""
    canvas = np.zeros((H + 2 * pad, W + 2 * pad), dtype=np.complex128)
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    offs = (np.arange(sub) + 0.5) / sub - 0.5
    for a in offs:
        for b in offs:
            tx = np.floor(c[0] + m * (xs + a - c[0]) + 0.5).astype(int) + pad
            ty = np.floor(c[1] + m * (ys + b - c[1]) + 0.5).astype(int) + pad
            ok = (tx >= 0) & (tx < W + 2 * pad) & (ty >= 0) & (ty < H + 2 * pad)
            np.add.at(canvas, (ty[ok], tx[ok]), s[ok] / sub ** 2)
    if sigma > 0:
        k = gaussian(sigma)
        canvas = fftconvolve(canvas.real, k, mode="same") + 1j * fftconvolve(canvas.imag, k, mode="same")
    return canvas[pad:pad + H, pad:pad + W]


@dataclass
class Lens:
    name: str
    lobes: list[tuple[float, np.ndarray]] = field(default_factory=list)
    veil: float = 0.0
    #: (w, sigma, centre) mirror ghosts, or (w, sigma, centre, magnification).
    ghosts: list[tuple] = field(default_factory=list)
    field_lobe: tuple[float, Callable[[np.ndarray], np.ndarray]] | None = None

    @property
    def total(self) -> float:
        return (sum(w for w, _ in self.lobes) + self.veil + sum(g[0] for g in self.ghosts)
                + (self.field_lobe[0] if self.field_lobe else 0.0))

    def __call__(self, s: np.ndarray) -> np.ndarray:
        out = (1.0 - self.total) * s
        for w, k in self.lobes:
            out = out + w * convolve(s, k)
        if self.veil:
            out = out + self.veil * s.sum() / (H * W)  # uniform over the sensor
        for w, sg, c, *m in self.ghosts:
            out = out + w * (magnified_ghost(s, c, m[0], sg) if m else ghost(s, c, sg))
        if self.field_lobe:
            w, fn = self.field_lobe
            out = out + w * fn(s)
        return out


def field_dependent_lobe(s: np.ndarray, sigma0: float = 4.0, gain: float = 2.0, bins: int = 10) -> np.ndarray:
    """A shift-variant lobe: light from pixel p spreads by a Gaussian whose sigma grows with
    the field, ``sigma(p) = sigma0 (1 + gain |p - c|^2 / R^2)`` (R the half diagonal), and
    which is elongated along the radial direction by nothing else; sigma quantised in bins."""
    ys, xs = np.mgrid[0:H, 0:W]
    rho2 = ((xs - CX) ** 2 + (ys - CY) ** 2) / (CX ** 2 + CY ** 2)
    sig = sigma0 * (1 + gain * rho2)
    edges = np.linspace(sig.min(), sig.max() + 1e-9, bins + 1)
    out = np.zeros_like(s)
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (sig >= lo) & (sig < hi)
        if m.any():
            out += convolve(np.where(m, s, 0), gaussian(0.5 * (lo + hi)))
    return out


def _ghost_centre(off: tuple[int, int]) -> tuple[float, float]:
    return CX + off[0], CY + off[1]


def lenses() -> dict[str, Lens]:
    """The lens forms of issue 17 (none of them the correction's parametric model)."""
    study = [(0.02, gaussian(3.0)), (0.03, gaussian(15.0, 12.0)), (0.02, gaussian(60.0, 50.0))]
    out = {
        "gauss_other": Lens("other Gaussian sigmas, weights, veil, ghost",
                            [(0.03, gaussian(1.7)), (0.04, gaussian(8.0, 5.5)), (0.025, gaussian(33.0))],
                            veil=0.015, ghosts=[(0.008, 2.5, (CX, CY))]),
        "power_law": Lens("power-law tail (r^-3) plus veil", [(0.09, power_law(1.5, 3.0))], veil=0.02),
    }
    for k, off in ((1, (1, 0)), (2, (2, 1)), (7, (6, 4)), (10, (9, 5))):
        out[f"ghost_{k}px"] = Lens(f"study lens, ghost {np.hypot(*off):.1f} px off the principal point",
                                   list(study), veil=0.01, ghosts=[(0.005, 4.0, _ghost_centre(off))])
    # Ghosts that are not mirrors (sim/optics.py traces magnifications of 1.2-1.5): upright and
    # magnified about the principal point, and inverted, magnified and 5 px off it.
    out["ghost_mag_up"] = Lens("study lens, upright ghost magnified 1.3x about the principal point",
                               list(study), veil=0.01, ghosts=[(0.006, 3.0, (CX, CY), 1.3)])
    out["ghost_mag_inv"] = Lens("study lens, inverted ghost magnified 1.2x, 5 px off the principal point",
                                list(study), veil=0.01, ghosts=[(0.005, 3.0, _ghost_centre((4, 3)), -1.2)])
    out["field_lobe"] = Lens("field-dependent lobe (sigma 4 px on axis, 12 px in the corners) plus veil",
                             [(0.02, gaussian(20.0))], veil=0.01, field_lobe=(0.05, field_dependent_lobe))
    return out


REFLECTANCES = (0.5, 0.05, 0.02, 0.01)


def distance(s: np.ndarray) -> np.ndarray:
    """Radial distance of the (single-frequency) signal, computed here from the phase."""
    ph = np.mod(np.angle(s), 2 * np.pi)
    return C_M_PER_S * ph / (4 * np.pi * FREQ[0])


def square_error(s: np.ndarray, s_true: np.ndarray) -> float:
    return float(np.mean(np.abs(distance(s[SQUARE]) - distance(s_true[SQUARE]))))


def calibration_capture(lens: Lens) -> np.ndarray:
    """A white card on black (nothing else in view), through the lens: ``[1, H, W]``."""
    s, _ = scene_signal(square_rho=None, card=True, wall=False)
    return lens(s)[None]


#: Bright patches on black for the bench procedure (rows, cols): the card's place in the
#: dark-square scene, then the other field corners and the centre.
PATCHES = ((slice(10, 26), slice(8, 24)), (slice(36, 52), slice(58, 74)), (slice(8, 20), slice(56, 70)),
           (slice(40, 54), slice(6, 20)), (slice(24, 36), slice(34, 46)))


def patch_captures(lens: Lens, n: int = len(PATCHES)) -> list[np.ndarray]:
    """A bright patch (the card: 0.3 m, reflectance 1) on black at ``n`` field positions,
    each through the lens: ``[1, H, W]`` each."""
    out = []
    dist = 0.3 / CAMERA.ray_z
    for rows, cols in PATCHES[:n]:
        amp = np.zeros((H, W))
        amp[rows, cols] = 1.0 / dist[rows, cols] ** 2
        s = amp * np.exp(1j * 4 * np.pi * FREQ[0] * dist / C_M_PER_S)
        out.append(lens(s)[None])
    return out


def cases(lens: Lens) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """(reflectance, S_meas [1,H,W], S_true [1,H,W]) of the dark-square scene."""
    out = []
    for rho in REFLECTANCES:
        s, _ = scene_signal(square_rho=rho, card=True, wall=True)
        out.append((rho, lens(s)[None], s[None]))
    return out


def removed(lens: Lens, correct: Callable[[np.ndarray], np.ndarray]) -> dict[float, float]:
    """Fraction of the dark-square error removed by ``correct`` (S_meas -> S_corr)."""
    res = {}
    for rho, s_meas, s_true in cases(lens):
        before = square_error(s_meas[0], s_true[0])
        after = square_error(correct(s_meas)[0], s_true[0])
        res[rho] = 1.0 - after / before
    return res
