"""Flexible forms fitted in closed form: the fixed-pattern range offset map, and the
per-frame drift.

A per-column, per-row or per-pixel range offset is not a few scalars, so the optimiser over
``Param``s does not fit it. It is linear in the residual: with the twin's prediction ``P`` and
its change ``J`` per metre of radial offset (one prediction with a uniform 1 mm map: the
effect acts on each pixel alone, so that one evaluation is every pixel's derivative), each
pixel's whitened residual ``z`` is ``g d + noise`` with ``g = J / sigma``. Per pixel that
gives the weight ``a = |g|^2`` and the least-squares offset ``d = (g . z) / a`` (variance
``1 / a``), and the map is

    map[v, u] = column[u] + row[v] + pixel[v, u]

- column and row offsets: weighted ridge regression, ``min sum a (d - col - row)^2 +
  lam_c |col|^2 + lam_r |row|^2``; the two strengths (each may be infinite: that part off)
  are chosen on the held-out pixel blocks of the *training* frames after a fit on the
  training blocks, then the fit is redone on every usable pixel of the training frames;
- the per-pixel part: empirical-Bayes shrinkage of what is left, ``pixel = s e`` with
  ``s = tau^2 a / (1 + tau^2 a)`` and ``tau^2`` the variance of the true pixel offsets
  estimated by the method of moments (0 for noise: nothing kept). It is fitted on the
  training frames of the very pixels it is scored on, so it is scored on the held-out
  *frames*; a session with one frame (training = held-out frame) cannot score it and it is
  left out, with the reason. It is kept only when its expected held-out gain, ``sum s tau^2
  a``, beats the selection's penalty for its degrees of freedom.

The held-out frames are never used here: the selection scores the fitted map on them. The
effective degrees of freedom are the trace of the hat matrix of the parts that reach the
held-out score (columns and rows: ``tr((X'WX + L)^-1 X'WX)``; pixels: the sum of ``s`` over
the held-out pixels), reported through :attr:`EffectSpec.dof <tofhil.eval.diagnose.selection.EffectSpec>`
so the selection penalises the map for what it can fit.

The per-frame drift (:func:`fit_frame_drift`) is the same linearisation frame by frame: one
offset and one scale of the modulated light per frame from its training pixels, smooth in
time, scored on every frame's held-out pixels against constants.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence, TypeVar

import numpy as np

from tofhil.demod import radians_per_metre
from tofhil.eval.diagnose.heldout import HeldOutData
from tofhil.eval.metrics.noise import pooled_variance
from tofhil.sim.effects import RangeOffsetMapEffect

T = TypeVar("T")

#: The effect the map forms fit (``tofhil.sim.effects.RangeOffsetMapEffect``).
MAP_EFFECT = RangeOffsetMapEffect.name
#: Radial offset of the linearisation (m): small against the wrap, large against round-off.
EPS_M = 1e-3
#: Ridge strengths tried, relative to the median weight of a column (two per decade).
RIDGE_GRID = 10.0 ** np.arange(-3.0, 2.01, 0.5)


@dataclass
class MapFit:
    """A fitted range offset map, its parts, strengths and effective degrees of freedom."""

    map_m: np.ndarray  # [H, W]
    column_m: np.ndarray  # [W]
    row_m: np.ndarray  # [H]
    pixel_m: np.ndarray  # [H, W]
    dof: float
    dof_parts: dict[str, float] = field(default_factory=dict)
    #: Ridge strength of each part (inf: the part is off), in whitened units per m^2.
    strength: dict[str, float] = field(default_factory=dict)
    #: Standard deviation of each part's offsets (m).
    rms_m: dict[str, float] = field(default_factory=dict)
    #: Why the per-pixel part is in or out.
    pixel_note: str = ""

    @property
    def form(self) -> str:
        parts = [p for p in ("column", "row", "pixel") if self.dof_parts.get(p, 0.0) > 0.0]
        return " + ".join(parts) or "none"

    def summary(self) -> dict[str, Any]:
        """JSON-safe flat figures (the map itself goes to a .npy file)."""
        out: dict[str, Any] = {"form": self.form, "dof": round(self.dof, 2)}
        for part in ("column", "row", "pixel"):
            out[f"dof_{part}"] = round(self.dof_parts.get(part, 0.0), 2)
            out[f"rms_mm_{part}"] = round(1e3 * self.rms_m.get(part, 0.0), 3)
        for part, v in self.strength.items():
            out[f"ridge_{part}"] = "off" if not np.isfinite(v) else float(f"{v:.4g}")
        out["pixel_part"] = self.pixel_note
        return out


def pixel_offsets(model: Any, data: HeldOutData, current: dict[str, dict[str, Any]]
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per usable pixel of the training frames: weight ``a`` (1 / variance of the offset),
    least-squares radial offset ``d`` (m) and the flat indices of those pixels."""
    base = {k: v for k, v in current.items() if k != MAP_EFFECT}
    prev = current.get(MAP_EFFECT)
    shape = data.usable.shape
    prev_map = np.zeros(shape) if prev is None else np.asarray(prev["values"], dtype=np.float64)
    p0 = model.predict(base | {MAP_EFFECT: {"values": prev_map}})
    p1 = model.predict(base | {MAP_EFFECT: {"values": prev_map + EPS_M}})
    z = data.whitened(p0, "train_frames")  # [C, N] complex, measured - predicted
    g = (z - data.whitened(p1, "train_frames")) / EPS_M  # d(prediction) / d(offset), whitened
    a = (g.real ** 2 + g.imag ** 2).sum(axis=0)
    b = (g.real * z.real + g.imag * z.imag).sum(axis=0)
    idx = np.flatnonzero(data.part("train_frames")[2].ravel())
    ok = a > 0
    d = np.where(ok, b / np.where(ok, a, 1.0), 0.0) + prev_map.ravel()[idx]
    return a, d, idx


def _normal_equations(a: np.ndarray, d: np.ndarray, u: np.ndarray, v: np.ndarray, w: int,
                      h: int) -> tuple[np.ndarray, np.ndarray]:
    """The weighted normal equations of ``d ~ col[u] + row[v]``: ``(X'WX, X'Wd)``."""
    m = np.zeros((w + h, w + h))
    m[np.arange(w), np.arange(w)] = np.bincount(u, a, w)
    m[w + np.arange(h), w + np.arange(h)] = np.bincount(v, a, h)
    cross = np.bincount(u * h + v, a, w * h).reshape(w, h)
    m[:w, w:] = cross
    m[w:, :w] = cross.T
    rhs = np.concatenate([np.bincount(u, a * d, w), np.bincount(v, a * d, h)])
    return m, rhs


def _ridge(m: np.ndarray, rhs: np.ndarray, w: int, lam_c: float, lam_r: float, *,
           dof: bool = False, schur: dict | None = None) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    """Weighted ridge fit from the normal equations: (col, row, the trace of the hat matrix
    split into the columns' and the rows' diagonal entries; zeros unless ``dof``).

    The columns' block of the normal equations is diagonal (a pixel is in one column), so the
    columns are eliminated first and a rows-sized system is solved (its Schur complement, kept
    in ``schur`` per column strength: a strength search solves it for every row strength)."""
    h = m.shape[0] - w
    if dof:
        reg = np.concatenate([np.full(w, lam_c), np.full(h, lam_r)])
        on = np.isfinite(reg)  # an infinite strength: that part is off (zero), not in the system
        x = np.zeros(w + h)
        diag = np.zeros(w + h)
        if on.any():
            sub = m[np.ix_(on, on)] + np.diag(reg[on])
            x[on] = np.linalg.solve(sub, rhs[on])
            diag[on] = np.diag(np.linalg.solve(sub, m[np.ix_(on, on)]))
        return x[:w], x[w:], (float(diag[:w].sum()), float(diag[w:].sum()))
    d_col, d_row = np.diag(m)[:w], np.diag(m)[w:]
    p, q = rhs[:w], rhs[w:]
    col, row = np.zeros(w), np.zeros(h)
    if not np.isfinite(lam_c):
        if np.isfinite(lam_r):
            row = q / (d_row + lam_r)
        return col, row, (0.0, 0.0)
    inv = 1.0 / (d_col + lam_c)
    if np.isfinite(lam_r):
        cached = None if schur is None else schur.get(lam_c)
        if cached is None:
            cross = m[:w, w:]
            cached = (np.diag(d_row) - cross.T @ (inv[:, None] * cross), q - cross.T @ (inv * p))
            if schur is not None:
                schur[lam_c] = cached
        s_rows, t = cached
        row = np.linalg.solve(s_rows + lam_r * np.eye(h), t)
        col = inv * (p - m[:w, w:] @ row)
    else:
        col = inv * p
    return col, row, (0.0, 0.0)


def held_out_strength(grid: Sequence[T], score: Callable[[T], float]) -> T:
    """The regularisation strength of ``grid`` whose fit on the training blocks scores lowest
    on the held-out blocks (``score``); the first of equals, so a grid that starts with the
    strongest prior keeps it unless the data ask for less. The one rule every regularised
    form's strength is chosen by (the maps here, the optimiser's forms in
    :mod:`tofhil.eval.diagnose.form_prior`)."""
    best, best_score = grid[0], score(grid[0])
    for lam in grid[1:]:
        sc = score(lam)
        if sc < best_score:
            best, best_score = lam, sc
    return best


def fit_offset_map(model: Any, data: HeldOutData, current: dict[str, dict[str, Any]],
                   penalty_per_dof: float) -> MapFit:
    """The regularised column + row + pixel range offset map on the training frames (module
    doc), on top of the current model ``current`` (fitted effects)."""
    h, w = data.usable.shape
    a, d, idx = pixel_offsets(model, data, current)
    v, u = np.divmod(idx, w)
    train = data.train_pixels.ravel()[idx]
    test = data.test_pixels.ravel()[idx]
    scale = float(np.median(np.bincount(u, a, w)[np.bincount(u, minlength=w) > 0])) if a.size else 1.0
    grid = [np.inf] + list(scale * RIDGE_GRID)
    # Strengths from the held-out blocks of the training frames (the held-out frames stay unseen).
    m_train, rhs_train = _normal_equations(a[train], d[train], u[train], v[train], w, h)

    schur: dict = {}

    def held_out(lam: tuple[float, float]) -> float:
        col, row, _ = _ridge(m_train, rhs_train, w, *lam, schur=schur)
        return float(np.sum(a[test] * (d[test] - col[u[test]] - row[v[test]]) ** 2))

    # both parts off first: a map is fitted only when it does better on the held-out blocks
    lam_c, lam_r = held_out_strength([(np.inf, np.inf)] + [(c, r) for c in grid for r in grid
                                                           if np.isfinite(c) or np.isfinite(r)], held_out)
    col, row, (dof_c, dof_r) = _ridge(*_normal_equations(a, d, u, v, w, h), w, lam_c, lam_r, dof=True)
    e = d - col[u] - row[v]
    pixel = np.zeros(h * w)
    dof_pix = 0.0
    tau2 = max(float(np.sum(a * e * e - 1.0) / max(np.sum(a), 1e-300)), 0.0)
    if not data.frames_held_out:
        note = "not fitted: one frame (a per-pixel map is scored on held-out frames of the same pixels)"
    elif tau2 == 0.0:
        note = "not kept: the pixel-to-pixel scatter left is within the noise"
    else:
        s = tau2 * a / (1.0 + tau2 * a)
        gain = float(np.sum((s * tau2 * a)[test]))
        dof_test = float(np.sum(s[test]))
        if gain > penalty_per_dof * dof_test:
            pixel[idx] = s * e
            dof_pix = dof_test
            note = (f"kept: pixel offsets {1e3 * np.sqrt(tau2):.1f} mm rms, each shrunk by its noise "
                    f"(mean factor {float(np.mean(s)):.2f})")
        else:
            note = (f"not kept: pixel offsets {1e3 * np.sqrt(tau2):.1f} mm rms are too weak against the noise of "
                    f"{data.n_train_frames} training frame(s) to pay for their {dof_test:.0f} degrees of freedom "
                    "(more frames would tell)")
    # A column or row that has no usable pixel stays at 0 (ridge): so does its part of the map.
    map_m = col[None, :] + row[:, None] + pixel.reshape(h, w)
    dof_parts = {"column": dof_c, "row": dof_r, "pixel": dof_pix}
    return MapFit(map_m=map_m, column_m=col, row_m=row, pixel_m=pixel.reshape(h, w), dof=dof_c + dof_r + dof_pix,
                  dof_parts=dof_parts, strength={"column": lam_c, "row": lam_r},
                  rms_m={"column": float(np.std(col)), "row": float(np.std(row)),
                         "pixel": float(np.std(pixel[idx])) if idx.size else 0.0},
                  pixel_note=note)


# =============================================================================================
# per-frame drift
# =============================================================================================
#: Smoothness strengths tried for the drift, relative to the median weight of one frame.
DRIFT_GRID = 10.0 ** np.arange(-4.0, 4.01, 0.5)


@dataclass
class DriftFit:
    """A range offset and an amplitude scale per frame, smooth in time, and their held-out
    test against none (one constant offset and scale for every frame)."""

    offsets_m: np.ndarray  # [N] radial offset of each frame about the session's mean
    dof: float  # effective degrees of freedom beyond the constants
    strength: float  # the range offsets' smoothness
    #: Held-out misfit (sum of squares over the held-out pixels of every frame) without and
    #: with the drift, and the number of values.
    chi2_static: float
    chi2_drift: float
    n_values: int
    named: bool
    text: str
    #: [N] each frame's modulated light relative to the session's mean (1 = no change)
    amplitude_scale: np.ndarray = field(default_factory=lambda: np.ones(0))
    amplitude_strength: float = 0.0

    def to_json(self) -> dict[str, Any]:
        return {"named": self.named, "offsets_mm": [round(1e3 * float(x), 3) for x in self.offsets_m],
                "amplitude_scale": [round(float(x), 5) for x in self.amplitude_scale],
                "dof": round(self.dof, 2), "smoothness": float(f"{self.strength:.4g}"),
                "amplitude_smoothness": float(f"{self.amplitude_strength:.4g}"),
                "chi2_static": round(self.chi2_static, 2), "chi2_drift": round(self.chi2_drift, 2),
                "values": self.n_values, "text": self.text}


#: Relative amplitude change of the linearisation of the per-frame scale.
EPS_SCALE = 1e-3


def _smooth_fit_2(a: np.ndarray, b: np.ndarray, lam: tuple[float, float]) -> tuple[np.ndarray, float]:
    """Two parameters per frame (``a`` ``[N, 2, 2]`` normal matrices, ``b`` ``[N, 2]``):
    ``min sum (d_i - u_i)' a_i (d_i - u_i) + lam_k |D2 u_k|^2`` (second differences of each
    parameter in time: a straight line is free); returns ``u`` ``[N, 2]`` and the trace of
    the hat matrix."""
    n = b.shape[0]
    w = np.zeros((2 * n, 2 * n))
    for k in range(2):
        for j in range(2):
            w[k * n:(k + 1) * n, j * n:(j + 1) * n] = np.diag(a[:, k, j])
    d2 = np.zeros((0, n)) if n < 3 else np.diff(np.eye(n), 2, axis=0)
    pen = np.zeros_like(w)
    for k in range(2):
        pen[k * n:(k + 1) * n, k * n:(k + 1) * n] = lam[k] * d2.T @ d2
    m = w + pen
    u = np.linalg.solve(m, np.concatenate([b[:, 0], b[:, 1]]))
    return np.stack([u[:n], u[n:]], axis=1), float(np.trace(np.linalg.solve(m, w)))


def fit_frame_drift(model: Any, data: HeldOutData, current: dict[str, dict[str, Any]], penalty_per_dof: float,
                    *, min_relative_gain: float = 0.02) -> DriftFit | None:
    """A per-frame range offset and amplitude scale (temperature, warm-up: the range and the
    emitter's power drift) on top of the current model.

    Each frame's offset and scale are the weighted least-squares values of its *training*
    pixels (linearised as for the map: the offset by a radial shift of the prediction, the scale
    by a relative change of its modulated light); they are smoothed in time (second
    differences, each parameter's strength by generalised cross-validation) and scored on the
    *held-out* pixels of every frame against one constant offset and scale for all frames.
    Named by the selection's rule: the held-out gain beats ``penalty_per_dof`` per extra degree
    of freedom and removes ``min_relative_gain`` of the excess over noise. None when the session keeps no frames (or fewer than 3)."""
    frames = data.s_frames
    if frames is None or frames.shape[0] < 3 or not data.frames_held_out:
        return None
    shape = data.usable.shape
    prev = current.get(MAP_EFFECT)
    prev_map = np.zeros(shape) if prev is None else np.asarray(prev["values"], dtype=np.float64)
    base = {k: v for k, v in current.items() if k != MAP_EFFECT}
    p0 = model.predict(base | {MAP_EFFECT: {"values": prev_map}})
    p1 = model.predict(base | {MAP_EFFECT: {"values": prev_map + EPS_M}})
    nf = data.n_freq
    p2 = p0.copy()
    p2[:nf] = p0[:nf] * (1.0 + EPS_SCALE)  # the modulated light only: ambient does not follow the emitter
    var1 = data.var_frame
    train = data.train_pixels[data.usable]
    test = data.test_pixels[data.usable]
    n = frames.shape[0]

    def sums(var: np.ndarray) -> tuple[np.ndarray, ...]:
        """Per frame: the normal matrix and weighted residual of its training and held-out
        pixels ([N, 2, 2], [N, 2]), and the held-out pixels' squared residual (whitened with ``var``)."""
        at, ah = np.zeros((n, 2, 2)), np.zeros((n, 2, 2))
        bt, bh, zz = np.zeros((n, 2)), np.zeros((n, 2)), np.zeros(n)
        for i in range(n):
            one = _one_frame(data, frames[i], var)
            z = one.whitened(p0, "train_frames")
            gs = ((z - one.whitened(p1, "train_frames")) / EPS_M, (z - one.whitened(p2, "train_frames")) / EPS_SCALE)
            for k in range(2):
                b = (gs[k].real * z.real + gs[k].imag * z.imag).sum(axis=0)
                bt[i, k], bh[i, k] = b[train].sum(), b[test].sum()
                for j in range(2):
                    a = (gs[k].real * gs[j].real + gs[k].imag * gs[j].imag).sum(axis=0)
                    at[i, k, j], ah[i, k, j] = a[train].sum(), a[test].sum()
            zz[i] = float((np.abs(z[:, test]) ** 2).sum())
        return at, bt, ah, bh, zz

    at, bt, ah, bh, zz = sums(var1)
    d = np.linalg.solve(at, bt[:, :, None])[:, :, 0]
    scales = (float(np.median(at[:, 0, 0])), float(np.median(at[:, 1, 1])))
    best = None
    for lo in DRIFT_GRID:
        for la in DRIFT_GRID:
            lam = (scales[0] * lo, scales[1] * la)
            u, tr = _smooth_fit_2(at, bt, lam)
            e = d - u
            rss = float(np.einsum("ik,ikj,ij->", e, at, e))
            gcv = 2 * n * rss / max(2 * n - tr, 1e-9) ** 2
            if best is None or gcv < best[0]:
                best = (gcv, lam, u, tr)
    _, lam, u, tr = best

    def chi2(v: np.ndarray, ah: np.ndarray, bh: np.ndarray, zz: np.ndarray) -> float:
        # quadratic in the offsets and scales: exact for the linearised model
        return float(np.sum(zz) - 2.0 * np.sum(v * bh) + np.einsum("ik,ikj,ij->", v, ah, v))

    const = np.linalg.solve(at.sum(axis=0), bt.sum(axis=0))
    static = np.broadcast_to(const, u.shape)
    chi2_static, chi2_drift = chi2(static, ah, bh, zz), chi2(u, ah, bh, zz)
    n_values = int(test.sum() * data.values_per_pixel * n)
    dof = max(tr - 2.0, 0.0)
    gain, excess = chi2_static - chi2_drift, max(chi2_static - n_values, 0.0)
    # named against the session's own noise estimate (conservative: it contains the drift)
    named = bool(gain > dof * penalty_per_dof and gain > min_relative_gain * excess)
    x, y = u[:, 0] - const[0], u[:, 1] - const[1]
    noise_note = ""
    if named:
        # The frame-to-frame scatter contains the drift; the figures are restated with the
        # noise re-estimated from the frames with the drift taken out (same pooling).
        k = np.zeros(frames.shape[1])
        k[:nf] = radians_per_metre(data.freq_hz)
        g = np.ones((n, frames.shape[1]))
        g[:, :nf] = 1.0 + y[:, None]
        clean = frames * np.exp(-1j * k[None, :, None, None] * x[:, None, None, None]) / g[:, :, None, None]
        pool = [pooled_variance((np.abs(f - f.mean(axis=0)) ** 2).sum(axis=0)) for f in (frames, clean)]
        ratio = np.clip(pool[1] / np.maximum(pool[0], 1e-300), 1e-3, 1.0)
        _, _, ah2, bh2, zz2 = sums(var1 * ratio)
        chi2_static, chi2_drift = chi2(static, ah2, bh2, zz2), chi2(u, ah2, bh2, zz2)
        noise_note = " (noise re-estimated with the drift taken out)"
    spread = 1e3 * float(np.ptp(x))
    text = (f"per-frame drift: the range moves by {spread:.1f} mm and the modulated light by "
            f"{100 * float(np.ptp(y)):.2f} % over {n} frames (smooth in time, {dof:.1f} degrees of freedom beyond "
            f"constants); on the held-out pixels of every frame it lowers the misfit from {chi2_static / n_values:.3f} "
            f"to {chi2_drift / n_values:.3f} per value{noise_note} -- " + ("named" if named else "not significant"))
    return DriftFit(offsets_m=x, dof=dof, strength=lam[0], chi2_static=chi2_static, chi2_drift=chi2_drift,
                    n_values=n_values, named=named, text=text, amplitude_scale=1.0 + y, amplitude_strength=lam[1])


def _one_frame(data: HeldOutData, s: np.ndarray, var1: np.ndarray) -> HeldOutData:
    """``data`` with one frame as its training part (the whitening of that frame), on every
    usable pixel (the drift's frames are all of them: no frame set is held out of the choice)."""
    return dataclasses.replace(data, s_train=s, var_train=var1, n_train_frames=1, usable_train_frames=data.usable)
