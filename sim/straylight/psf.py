"""The one stray-light PSF type of tofhil and its parameter mapping.

:class:`StrayLightPSF` holds the scatter kernel ``h`` (Gaussian lobes, a veil, ghosts, a free
radial lobe, a measured point-source image) and the direct part: simulated (the
``stray_light`` effect's parameters, :meth:`~StrayLightPSF.from_params` /
:meth:`~StrayLightPSF.to_params`), diagnosed, calibrated, saved and loaded (JSON) and
corrected with alike. What it does to an image is in :mod:`.scattering`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from tofhil.outputs import atomic_file, refuse_existing, write_text_atomic

from tofhil.errors import InputFileError, require_input_file
from tofhil.schema import Schema
from tofhil.sim.straylight.kernels import _measured_normalised, radial_hat_sums


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
            if f is not None:
                refuse_existing(f, force)
        doc = {"format": PSF_FORMAT, "stray_light": self.to_params(None if side is None else side.name),
               "info": self.info}
        text = json.dumps(doc, indent=2, default=_json_default)
        if side is not None:
            with atomic_file(side) as f:
                np.save(f, np.asarray(self.measured))
        write_text_atomic(p, text)
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
