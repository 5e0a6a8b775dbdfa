"""Depth (+ amplitude, + confidence) sessions as held-out data for diagnosis.

Most cameras deliver depth, an amplitude (active brightness / IR) and a confidence, often one
frame at a time, and no raw taps. Where the modulation frequencies are known, the phasor

    S_f = A exp(i 4 pi f d / c)

of each frequency is what the device measured before it unwrapped (up to its own gain): it
stands in for the complex signal, so the twin's forward model and the effect selection apply
unchanged (the twin predicts S; S is compared). The frequencies come from the session (a
recorded sensor configuration) or else from the twin's scene; ``tofhil scene-from-capture``
writes them into the scene it builds.

The split and the noise:

- **one frame**: training and held-out pixels are the two colours of a checkerboard of square
  blocks (a fit cannot memorise the pixels it is scored on); both parts are the same frame.
  The noise comes from the local spatial scatter: the high-pass ``x - mean(4 neighbours)``
  of the phase term ``A k d`` (``k = 4 pi f / c``), whose variance is ``1.25 sigma^2`` for
  independent pixel noise, robustly (1.4826 MAD, so edges and texture do not inflate it).
  A shot-noise-limited pixel has a depth noise ``~ 1/A``, so this tangential noise of S is
  about the same everywhere; it is taken isotropic (the same for the real and imaginary
  part), as for raw taps;
- **several frames**: frames as well (even frames train, odd frames test) and the noise from
  the frame-to-frame scatter of S, pooled over 5 x 5 pixels, as for raw taps.

Large images are binned (the complex phasor averaged over ``b x b`` pixels, the camera model
scaled to match) so that a diagnosis renders a few tens of thousands of pixels; a bin counts
only where all its pixels are valid and its depths agree within 5 % (no depth edge inside).

Limits (docs/diagnose.md): there is no tap offset, so nothing that shows only in the offset
(ambient light) can be observed; the amplitude is in the device's counts, so it is compared
after the twin's emitter power was fitted to it (scene-from-capture) and the absolute level
is not a finding; the device has already unwrapped, filtered and calibrated its depth.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from tofhil.eval.diagnose.defects import BIN_USABLE_SHARE, Defects, binned_defects, depth_defects
from tofhil import C_M_PER_S
from tofhil.eval.metrics.noise import NOISE_POOL_PX, phasor_depth_sigma, pooled_variance, robust_sigma
from tofhil.binning import bin_factor, bin_mean, binned_camera, one_surface
from tofhil.depth import saturated_amplitude
from tofhil.demod import distance_to_phase, equally_spaced_phases
from tofhil.errors import TofhilError
from tofhil.eval.diagnose.heldout import HeldOutData, block_checkerboard
from tofhil.session import Session
from tofhil.sim.effects import EFFECTS

#: Effects that act only on the tap offset: not observable without raw taps.
OFFSET_ONLY_EFFECTS = tuple(n for n, e in EFFECTS.items() if e.offset_only)

#: Pixels a diagnosis of a depth session renders at most (larger images are binned).
MAX_DIAGNOSIS_PIXELS = 6_000


def frequencies_for(session: Session, scene: Any | None) -> tuple[np.ndarray, str]:
    """The modulation frequencies of a depth session: recorded, else the twin scene's."""
    sc = session.sensor_config or {}
    if sc.get("freq_hz"):
        return np.atleast_1d(np.asarray(sc["freq_hz"], float)), "the session's recorded sensor configuration"
    recorded = getattr(session, "depth_freq_hz", None)
    if recorded is not None:
        return np.asarray(recorded, float), "the session (depth.freq_hz: the device's modulation frequency)"
    sensor = getattr(scene, "sensor", None)
    if sensor is not None and getattr(sensor, "freq_hz", None):
        return np.asarray(sensor.freq_hz, float), "the twin scene's sensor block (the session records none)"
    raise TofhilError("records no modulation frequency and the scene gives none", file=session.path,
                      field="sensor.freq_hz", expected="a scene with sensor.freq_hz (tofhil scene-from-capture "
                      "--freq-hz writes it)")


def depth_phasor(radial_m: np.ndarray, amplitude: np.ndarray, freq_hz: np.ndarray) -> np.ndarray:
    """``S_f = A exp(i 4 pi f d / c)`` per frequency, ``[F, H, W]`` complex."""
    phi = distance_to_phase(np.asarray(radial_m, np.float64)[None], np.asarray(freq_hz, float)[:, None, None])
    return np.asarray(amplitude, np.float64)[None] * np.exp(1j * phi)


def _with_usable_neighbours(usable: np.ndarray) -> np.ndarray:
    """Usable pixels whose 4 neighbours are usable too (the border excluded): where the
    high-pass of :func:`_highpass_on_phasor` sees no invalid pixel."""
    ok = usable.copy()
    ok[1:] &= usable[:-1]
    ok[:-1] &= usable[1:]
    ok[:, 1:] &= usable[:, :-1]
    ok[:, :-1] &= usable[:, 1:]
    ok[0], ok[-1], ok[:, 0], ok[:, -1] = False, False, False, False
    return ok


def _highpass_on_phasor(sf: np.ndarray) -> np.ndarray:
    """``sf - mean(4 neighbours)`` rotated onto each pixel's phasor: imaginary part across
    it (phase, i.e. depth), real part along it (amplitude)."""
    nb = 0.25 * (np.roll(sf, 1, 0) + np.roll(sf, -1, 0) + np.roll(sf, 1, 1) + np.roll(sf, -1, 1))
    return (sf - nb) * np.conj(_unit(sf))


def value_quantum(x: np.ndarray, max_values: int = 100_000) -> float:
    """The recorded unit of ``x``: the smallest step between its distinct finite values (1 mm
    for depth stored in millimetres, 1 for integer amplitudes), about 0 for continuous data."""
    v = np.asarray(x, np.float64).ravel()
    v = v[np.isfinite(v) & (v != 0)]
    if v.size > max_values:
        v = v[:: v.size // max_values + 1]
    u = np.unique(v)
    if u.size < 2:
        return 0.0
    steps = np.diff(u)
    # rounding of float32 storage leaves steps of ~1e-7 of the value beside the true unit
    steps = steps[steps > 1e-6 * float(np.max(np.abs(u)))]
    return float(steps.min()) if steps.size else 0.0


def temporal_noise_present(s_all: np.ndarray, usable: np.ndarray, freq_hz: np.ndarray, q_depth: float) -> bool:
    """Whether the frames scatter about their mean by more than the recorded depth unit's
    quantisation (``q^2 / 12``) at the median usable pixel: frames of a camera that filters over
    time, or of an emulation without noise, do not, and their scatter is no noise estimate."""
    if not usable.any():
        return True
    phase = np.angle(s_all[:, 0] * np.conj(s_all.mean(axis=0)[0])[None])
    d_var = np.var(phase[:, usable], axis=0, ddof=1) * (C_M_PER_S / (4 * np.pi * float(freq_hz[0]))) ** 2
    return bool(np.median(d_var) > max(q_depth ** 2 / 12.0, 1e-30))


def quantisation_variance(s: np.ndarray, usable: np.ndarray, freq_hz: np.ndarray, q_depth: float,
                          q_amp: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-frequency tangential and radial variance of the phasor that the recorded units'
    rounding alone gives (``q^2 / 12`` of depth and of amplitude) at the median amplitude."""
    amp = np.array([float(np.median(np.abs(sf[usable]))) if usable.any() else 0.0 for sf in s])
    k = 4 * np.pi * np.asarray(freq_hz, float) / C_M_PER_S
    return (amp * k) ** 2 * q_depth ** 2 / 12.0, np.full(amp.shape, q_amp ** 2 / 12.0)


def _robust_noise_variance(hp: np.ndarray) -> float:
    """Noise variance from high-pass values: (1.4826 MAD)^2 / 1.25 (the 4-neighbour
    high-pass of white noise has variance ``1.25 sigma^2``)."""
    return robust_sigma(hp) ** 2 / 1.25


def spatial_noise_variance(s: np.ndarray, usable: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frequency noise variances of ``s [F, H, W]`` across (tangential: phase, i.e. depth)
    and along (radial: amplitude) each pixel's phasor, from the local spatial scatter: the
    robust spread (1.4826 MAD) of ``s - mean(4 neighbours)``, divided by 1.25 (that high-pass
    of white noise has variance ``1.25 sigma^2``), over pixels whose neighbours are all usable.
    Fine amplitude texture the twin's per-object reflectance cannot follow counts as radial
    scatter: it is not a cause any effect of the library could explain."""
    ok = _with_usable_neighbours(usable)
    if ok.sum() < 20:
        raise TofhilError(f"has {int(ok.sum())} pixels with usable neighbours", field="depth/valid",
                          expected="at least 20 to estimate the noise")
    tang, rad = [], []
    for sf in s:
        hp = _highpass_on_phasor(sf)[ok]
        tang.append(max(_robust_noise_variance(hp.imag), 1e-30))
        rad.append(max(_robust_noise_variance(hp.real), 1e-30))
    return np.asarray(tang), np.asarray(rad)


#: Confidence classes (quantiles) the device's confidence is calibrated in.
CONFIDENCE_CLASSES = 6


def confidence_noise(s: np.ndarray, usable: np.ndarray, confidence: np.ndarray
                     ) -> tuple[np.ndarray, str] | None:
    """The device's confidence as a noise source, calibrated against the local scatter.

    Pixels are split into :data:`CONFIDENCE_CLASSES` quantile classes of the confidence; in
    each, the robust tangential scatter of the phasor's high-pass (as
    :func:`spatial_noise_variance`) gives that class's noise variance. The confidence is
    used when the classes differ by more than their sampling error (chi-square of the log
    variances about their mean, ``1e-3`` false-alarm; a robust variance of ``k`` values has a
    relative standard error of about ``1.65 sqrt(2 / k)``): each pixel's variance is then
    scaled by its class's over the global one (linear in the class's median confidence,
    interpolated). Returns ``(scale [H, W], note)``, or None when the confidence does not
    predict the scatter."""
    from scipy import stats

    ok = usable & np.isfinite(confidence)
    if ok.sum() < 20 * CONFIDENCE_CLASSES:
        return None
    values = np.unique(confidence[ok])
    if values.size < 2:
        return None  # a constant confidence says nothing
    if values.size <= CONFIDENCE_CLASSES:  # a few levels: one class each
        cls = np.searchsorted(values, confidence)
        n_cls = values.size
    else:
        edges = np.unique(np.quantile(confidence[ok], np.linspace(0, 1, CONFIDENCE_CLASSES + 1)))
        n_cls = edges.size - 1
        cls = np.clip(np.searchsorted(edges, confidence, side="right") - 1, 0, n_cls - 1)
    # the high-pass over every usable pixel (neighbours of any class), then its scatter per class
    inner = _with_usable_neighbours(usable) & ok
    hp = np.stack([_highpass_on_phasor(sf).imag for sf in s])

    def robust_var(m: np.ndarray) -> float:
        return float(np.mean([_robust_noise_variance(c) for c in hp[:, m]]))

    v_all = robust_var(inner)
    centres, logv, w = [], [], []
    for c in range(n_cls):
        m = inner & (cls == c)
        k = int(m.sum())
        if k < 20:
            continue
        v = max(robust_var(m), 1e-30)
        centres.append(float(np.median(confidence[m])))
        logv.append(math.log(v))
        w.append(1.0 / (1.65 ** 2 * 2.0 / k))
    if len(logv) < 2:
        return None
    logv_a, w_a = np.asarray(logv), np.asarray(w)
    mean = float(np.sum(w_a * logv_a) / w_a.sum())
    chi = float(np.sum(w_a * (logv_a - mean) ** 2))
    if chi <= stats.chi2.isf(1e-3, len(logv) - 1):
        return None
    order = np.argsort(centres)
    cx, cv = np.asarray(centres)[order], np.exp(logv_a[order])
    scale = np.interp(np.where(np.isfinite(confidence), confidence, np.median(confidence[ok])), cx, cv) / v_all
    note = ("; the device's confidence calibrated against the local scatter and used as the noise: per confidence "
            "class (median confidence -> noise relative to the image's) "
            + ", ".join(f"{c:.3g} -> {math.sqrt(v / v_all):.2f}" for c, v in zip(cx, cv)))
    return scale, note


def _unit(s: np.ndarray) -> np.ndarray:
    return s / np.maximum(np.abs(s), 1e-30)


def split_depth_session(session: Session, scene: Any | None = None, *, block_px: int = 8,
                        max_frames: int | None = None, valid_mask: np.ndarray | None = None,
                        max_pixels: int = MAX_DIAGNOSIS_PIXELS,
                        amplitude_model_error: float | None = None) -> HeldOutData:
    """A depth (+ amplitude) session as training and held-out phasors with their noise.

    ``amplitude_model_error`` (relative): how well the twin scene can know the amplitude at
    all (a scene built from the capture has one reflectance per object; its fit left this
    scatter of the log amplitude). Amplitude differences below it are no evidence: the
    amplitude residual is weighed against it (:meth:`HeldOutData.whitened`), so the depth
    channel is not outweighed by texture."""
    if not session.has_depth:
        raise TofhilError("has neither raw taps nor depth", file=session.path, field="depth/radial_m")
    freq_hz, freq_source = frequencies_for(session, scene)
    n = session.n_frames if max_frames is None else min(session.n_frames, max_frames)
    if n < 1:
        raise TofhilError("has no frame", file=session.path, field="depth/radial_m", expected="at least 1 frame")
    cam = session.camera
    b = bin_factor(cam.shape, max_pixels)
    frames_s, frames_ok, conf_seen, conf0 = [], [], False, None
    quanta: list[tuple[float, float]] = []
    defects = _frame_defects(session, cam, valid_mask)
    for i in range(n):
        df = session.depth_frame(i)
        d = np.asarray(df.radial_m, np.float64)
        amp = None if df.amplitude is None else np.asarray(df.amplitude, np.float64)
        if amp is None or not np.isfinite(amp).any():
            raise TofhilError("is missing or all NaN", file=session.path, field="depth/amplitude",
                              expected="an amplitude (active brightness / IR) image: the depth-only diagnosis "
                                       "compares the phasor A exp(i 4 pi f d / c)")
        if i < 2:  # the recorded units, from the first frames as stored
            quanta.append((value_quantum(d), value_quantum(amp)))
        ok = np.asarray(df.valid, bool) & np.isfinite(d) & (d > 0) & np.isfinite(amp) & (amp > 0)
        ok &= ~saturated_amplitude(amp, ok)
        if valid_mask is not None and valid_mask.shape == ok.shape:
            ok &= valid_mask
        ok &= ~defects.mask
        s = depth_phasor(np.where(ok, d, 0.0), np.where(ok, amp, 0.0), freq_hz)
        if i == 0 and df.confidence is not None and np.isfinite(df.confidence[ok]).any():
            conf0 = bin_mean(np.where(ok, np.asarray(df.confidence, np.float64), np.nan), b)
        if b > 1:
            # a bin is the mean of its usable pixels when they are most of it (a defective
            # pixel or two do not cost the bin), and one surface (no depth step inside)
            share = bin_mean(ok.astype(float), b)
            okb = (share >= BIN_USABLE_SHARE) & one_surface(d, ok, b)
            s, ok = bin_mean(s, b) / np.where(okb, share, 1.0), okb
        frames_s.append(s)
        frames_ok.append(ok)
        conf_seen |= "depth/confidence" in session.datasets
    s_all = np.stack(frames_s)            # [N, F, H, W]
    usable = np.logical_and.reduce(frames_ok)
    bcam = binned_camera(cam, b)
    q_depth, q_amp = min(q for q, _ in quanta), min(q for _, q in quanta)
    frozen = n >= 2 and not temporal_noise_present(s_all, usable, freq_hz, q_depth)
    if frozen:
        # Frames without temporal scatter (an emulation, or a camera that filters over time)
        # are one measurement n times: their noise is the local spatial scatter of one frame.
        s_all, n = s_all.mean(axis=0)[None], 1
    if n >= 2:
        train_idx, test_idx = np.arange(0, n, 2), np.arange(1, n, 2)
        mean_all = s_all.mean(axis=0)
        ref = _unit(mean_all)
        dev = (s_all - mean_all[None]) * np.conj(ref)[None]

        def pooled(x: np.ndarray) -> np.ndarray:
            v = (x ** 2).sum(axis=0) / (n - 1)
            v = pooled_variance(v)
            return np.maximum(v, max(float(np.median(v)) * 1e-3, 1e-30))

        var_t, var_r = pooled(dev.imag), pooled(dev.real)
        s_train, s_test = s_all[train_idx].mean(axis=0), s_all[test_idx].mean(axis=0)
        var_train, var_test = var_t / len(train_idx), var_t / len(test_idx)
        radial_scale = var_r / var_t
        noise = (f"frame-to-frame scatter of the phasor over {n} frames, across (depth) and along "
                 f"(amplitude) it separately, pooled over {NOISE_POOL_PX} x {NOISE_POOL_PX} pixels")
        n_train, n_test = len(train_idx), len(test_idx)
    else:
        s_train = s_test = s_all[0]
        ref = _unit(s_all[0])
        var_t, var_r = spatial_noise_variance(s_all[0], usable)
        # never below what the recorded units can resolve (a smooth plane's high-pass can be 0)
        floor_t, floor_r = quantisation_variance(s_all[0], usable, freq_hz, q_depth, q_amp)
        var_t, var_r = np.maximum(var_t, floor_t), np.maximum(var_r, floor_r)
        var_train = var_test = np.broadcast_to(var_t[:, None, None], s_train.shape).copy()
        radial_scale = np.broadcast_to((var_r / var_t)[:, None, None], s_train.shape).copy()
        conf_note = ("; depth noise taken as 1/amplitude (shot-noise limited: the phasor's scatter the same "
                     "everywhere), its level from that scatter")
        if conf0 is not None:
            cal = confidence_noise(s_all[0], usable, conf0)
            if cal is not None:
                scale, conf_note = cal
                var_train = var_test = var_train * scale[None]
            else:
                conf_note = ("; the device's confidence was calibrated against the local scatter and does not "
                             "predict it (per-class scatter equal within its error): not used" + conf_note)
        amp_med = [max(float(np.median(np.abs(s_all[0][k][usable]))), 1e-30) for k in range(freq_hz.size)]
        sigma_mm = [1e3 * float(phasor_depth_sigma(v, amp_med[k], freq_hz[k])) for k, v in enumerate(var_t)]
        sigma_a = [100 * math.sqrt(v) / amp_med[k] for k, v in enumerate(var_r)]
        noise = (("the frames carry no temporal scatter (all equal within the recorded depth unit "
                  f"{q_depth * 1e3:.3g} mm): their mean taken as one frame; " if frozen else "")
                 + "local spatial scatter of one frame (1.4826 MAD of the phasor's high-pass, across and along "
                 "the phasor, at least the recorded units' quantisation: depth "
                 f"{q_depth * 1e3:.3g} mm / sqrt(12), amplitude {q_amp:.3g} / sqrt(12)): depth noise " + ", ".join(f"{x:.2f} mm" for x in sigma_mm)
                 + " and amplitude scatter " + ", ".join(f"{x:.1f}%" for x in sigma_a)
                 + " at the median amplitude" + conf_note)
        n_train = n_test = 1
    if amplitude_model_error:
        noise += (f"; amplitude known to the scene only to {100 * amplitude_model_error:.0f}% (one reflectance "
                  "per object): the amplitude residual is the log ratio measured / twin over that error and the "
                  "instrument's in quadrature")
    board = block_checkerboard(usable.shape, block_px)
    sensor = getattr(scene, "sensor", None)
    theta = np.asarray(sensor.theta_rad, float) if sensor is not None else equally_spaced_phases(4)
    t_int = float(sensor.integration_time_s) if sensor is not None else 1e-3
    return HeldOutData(camera=bcam, freq_hz=np.asarray(freq_hz, float), theta_rad=theta, integration_time_s=t_int,
                       s_train=s_train, s_test=s_test, var_train=var_train, var_test=var_test, usable=usable,
                       train_pixels=usable & board, test_pixels=usable & ~board,
                       n_train_frames=n_train, n_test_frames=n_test, offset_channel=False,
                       sensor_config=session.sensor_config, source=str(session.path),
                       channels=("depth + amplitude phasor A exp(i 4 pi f d / c) at "
                                 + ", ".join(f"{f / 1e6:g} MHz" for f in freq_hz) + f" (frequencies from {freq_source})"
                                 + (f"; binned {b} x {b} pixels" if b > 1 else "")
                                 + ("; the device's confidence is stored but not used as noise (frames give the "
                                    "noise)" if conf_seen and n >= 2 else "")),
                       noise=noise, phase_ref=ref, radial_var_scale=radial_scale,
                       amplitude_model_error=amplitude_model_error or None, frames_held_out=n >= 2,
                       s_frames=s_all if n >= 2 else None,
                       defects=defects if b == 1 else binned_defects(defects, b), sensor_shape=cam.shape)


def _frame_defects(session: Session, cam: Any, valid_mask: np.ndarray | None) -> Defects:
    """The defects of the session's first frame (no depth where valid, outliers, flying pixels)."""
    df = session.depth_frame(0)
    valid = np.asarray(df.valid, bool)
    if valid_mask is not None and valid_mask.shape == valid.shape:
        valid &= valid_mask
    return depth_defects(np.asarray(df.radial_m, np.float64), valid, cam)


def _objects_on_sensor(scene: Any, camera: Any) -> np.ndarray | None:
    """The scene's object on each sensor pixel (one centre ray each), -1 where none."""
    from tofhil.sim.render import render

    if scene is None or not getattr(scene, "objects", None):
        return None
    r = render(scene, camera=camera, samples_per_pixel=1, bounces=0, subpixel=False)
    return np.asarray(r.object_id)


def split_for_diagnosis(session: Session, scene: Any, *, block_px: int = 8, max_frames: int | None = None,
                        valid_mask: np.ndarray | None = None, amplitude_model_error: float | None = None
                        ) -> HeldOutData:
    """Raw taps when the session has them, else its depth and amplitude (this module)."""
    from tofhil.eval.diagnose.heldout import split_session

    if session.has_raw:
        return split_session(session, block_px=block_px, max_frames=max_frames,
                             objects_on_sensor=lambda camera: _objects_on_sensor(scene, camera))
    return split_depth_session(session, scene, block_px=block_px, max_frames=max_frames, valid_mask=valid_mask,
                               amplitude_model_error=amplitude_model_error)


def observable_candidates(candidates: Sequence[str] | None, data: HeldOutData, *, depth_only: bool,
                          unobservable: dict[str, str] | None = None) -> tuple[list[str], dict[str, str]]:
    """The effects diagnosis may name, and those it leaves out with the reason: for a depth
    session, effects that act only on the tap offset (it has none), and those the scene
    cannot observe (``unobservable``, e.g. from scene-from-capture's metadata)."""
    from tofhil.sim.effects import ORDER

    names = list(candidates) if candidates is not None else list(ORDER)
    dropped: dict[str, str] = {}
    if depth_only and not data.offset_channel:
        for e in OFFSET_ONLY_EFFECTS:
            dropped[e] = "acts only on the tap offset, which these data do not contain"
    for e, why in (unobservable or {}).items():
        dropped.setdefault(e, why)
    return [e for e in names if e not in dropped], {e: w for e, w in dropped.items() if e in names}
