"""``tofhil correct`` and ``tofhil compare``."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import typer

from tofhil.cli import app, console, lit, new_output_dir, out, progress
from tofhil.cli import options as opt
from tofhil.errors import TofhilError

_METHOD_HELP = ("uniform (w) | gaussian-inverse (sigma-h, sigma-v, w, mu) | psf (psf or calibration) | "
                "amplitude (min-amplitude) | jump-angle (angle-deg) | jump-distance (max-step, relative) | "
                "smooth-gaussian (sigma-px) | smooth-median (size) | smooth-bilateral (sigma-px, sigma-m)")


def _npz_name(path: Path) -> Path:
    """The file ``np.savez`` really writes for ``path`` (it appends .npz when missing)."""
    return path if path.suffix == ".npz" else path.with_name(path.name + ".npz")


def _mean_taps(path: Path) -> tuple[Any, Any]:
    """Mean raw taps ``[F, K, H, W]`` of a session and the session's camera and phases."""
    import numpy as np

    from tofhil.session import open_session

    with open_session(path) as s:
        if not s.has_raw or s.n_frames == 0:
            raise TofhilError("needs raw taps (at least one frame)", file=path, field="raw/taps")
        acc = None
        for raw in progress(s.raw_frames(), s.n_frames, f"reading {path.name}"):  # printed literally
            acc = raw.taps.astype(np.float64) if acc is None else acc + raw.taps
        return acc / s.n_frames, (s.camera, s.theta_rad)


def _calibrate(cal_path: Path, reference: Optional[Path], target_threshold: float, flat: Any = None) -> Any:
    """Fit a stray-light PSF from a calibration session (frames averaged in S)."""
    import numpy as np

    from tofhil.demod import phasor
    from tofhil.eval import straylight_correction as sl
    def mean_s(path: Path) -> tuple[np.ndarray, Any]:
        taps, (camera, theta) = _mean_taps(path)
        if flat is not None:
            taps = flat.apply(taps)  # the same pre-processing as the sessions it will correct
        return phasor(taps, theta), camera

    s_meas, cam = mean_s(cal_path)
    if reference is not None:
        s_true, cam_ref = mean_s(reference)
        if s_true.shape != s_meas.shape:
            raise TofhilError(f"has signals of shape {s_true.shape}, the calibration capture {s_meas.shape}",
                              file=reference, field="raw/taps", expected="the same camera and frequencies")
        psf = sl.calibrate_psf(s_meas, s_true, cam.cx, cam.cy)
        psf.info["calibration"] = {"mode": "reference", "capture": str(cal_path), "reference": str(reference)}
    else:
        psf = sl.calibrate_psf_target(s_meas, cam.cx, cam.cy, threshold=target_threshold)
        psf.info["calibration"]["capture"] = str(cal_path)
    if psf.direct <= 0.1 + 1e-9 or psf.scattered_fraction >= psf.direct:
        raise TofhilError(f"the PSF fit is degenerate (direct {psf.direct:.3f}, scattered "
                          f"{psf.scattered_fraction:.3f})", file=reference or cal_path,
                          expected="a noise-free twin reference (tofhil simulate --no-noise) or more frames "
                                   "averaged, and a capture whose stray light is visible")
    return psf


@app.command()
def correct(session: Path = typer.Argument(..., parser=opt.existing_file, help="Session to correct (.h5)."),
            method: str = typer.Option(..., "--method", help=_METHOD_HELP),
            out_path: Path = typer.Option(..., "--out", parser=opt.new_file, help="Corrected session to write."),
            w: Optional[float] = typer.Option(None, "--w", parser=opt.finite(0.0, 1.0, hi_open=True),
                                              help="Stray-light weight (uniform, gaussian-inverse)."),
            sigma_h: Optional[float] = typer.Option(None, "--sigma-h", parser=opt.finite(0.0, 1e4, lo_open=True, unit="px"),
                                                    help="Horizontal Gaussian sigma, pixels."),
            sigma_v: Optional[float] = typer.Option(None, "--sigma-v", parser=opt.finite(0.0, 1e4, lo_open=True, unit="px"),
                                                    help="Vertical Gaussian sigma, pixels."),
            mu: Optional[float] = typer.Option(None, "--mu", parser=opt.finite(0.0, 1e6), help="Inverse-filter regularisation."),
            psf: Optional[Path] = typer.Option(None, "--psf", parser=opt.existing_file,
                                               help="Calibrated PSF (.npz) for --method psf."),
            calibrate: Optional[Path] = typer.Option(None, "--calibrate", parser=opt.existing_file,
                                                     help="Calibration capture (.h5) to fit the PSF from."),
            reference: Optional[Path] = typer.Option(None, "--reference", parser=opt.existing_file,
                                                     help="Stray-light-free twin of the calibration capture; "
                                                          "without it the capture must be a bright target on a "
                                                          "dark background."),
            target_threshold: float = typer.Option(0.2, parser=opt.finite(0.0, 1.0, lo_open=True, hi_open=True),
                                                   help="Target pixels: amplitude above this fraction "
                                                             "of the brightest (calibration without reference)."),
            save_psf: Optional[Path] = typer.Option(None, "--save-psf", parser=opt.new_file,
                                                    help="Write the calibrated PSF here."),
            flat: Optional[Path] = typer.Option(None, "--flat", parser=opt.existing_file,
                                                help="Tap calibration (.npz from calibrate-taps) "
                                                                     "applied to the taps first (taps, uniform, "
                                                                     "gaussian-inverse, psf)."),
            iterations: Optional[int] = typer.Option(None, "--iterations", parser=opt.count(1, 10_000),
                                                     help="Deconvolution iterations (psf)."),
            min_amplitude: Optional[float] = typer.Option(None, "--min-amplitude", parser=opt.finite(0.0, unit="DN"),
                                                          help="Amplitude threshold (amplitude method; "
                                                               "invalidation when demodulating)."),
            angle_deg: Optional[float] = typer.Option(None, "--angle-deg", parser=opt.finite(0.0, 90.0, lo_open=True,
                                                                                         unit="deg"),
                                                      help="Jump-edge angle, degrees."),
            max_step: Optional[float] = typer.Option(None, "--max-step", parser=opt.finite(0.0, 1e4, lo_open=True, unit="m"),
                                                     help="Jump-edge distance step, m."),
            relative: Optional[float] = typer.Option(None, "--relative", parser=opt.finite(0.0, 10.0),
                                                     help="Jump-edge step per metre."),
            sigma_px: Optional[float] = typer.Option(None, "--sigma-px", parser=opt.finite(0.0, 1e3, lo_open=True, unit="px"),
                                                     help="Smoothing sigma, pixels."),
            sigma_m: Optional[float] = typer.Option(None, "--sigma-m", parser=opt.finite(0.0, 1e3, lo_open=True, unit="m"),
                                                    help="Bilateral range sigma, m."),
            size: Optional[int] = typer.Option(None, "--size", parser=opt.odd_size(1, 99), help="Median window size (odd)."),
            force: bool = typer.Option(False, "--force", help="Overwrite OUT (and --save-psf) if they exist.")) -> None:
    """Apply one correction to every frame of a session (complex-domain ones need raw taps)."""
    from tofhil.eval.corrections import correct_session, get_method

    m = get_method(method)
    given = {"w": w, "sigma_h": sigma_h, "sigma_v": sigma_v, "mu": mu, "iterations": iterations,
             "min_amplitude": min_amplitude, "angle_deg": angle_deg, "max_step_m": max_step,
             "relative": relative, "sigma_px": sigma_px, "sigma_m": sigma_m, "size": size,
             "flat": None if flat is None else str(flat)}
    params: dict[str, Any] = {k: v for k, v in given.items() if v is not None and k in m.params}
    stray = sorted(k for k, v in given.items() if v is not None and k not in m.params and k != "min_amplitude")
    if stray:
        raise TofhilError(f"method {method!r} takes no {', '.join('--' + k.replace('_', '-') for k in stray)}",
                          field="--method", expected="options of that method: " + (", ".join(m.params) or "none"))
    if method == "psf":
        if psf is not None and calibrate is not None:
            raise TofhilError("give either --psf or --calibrate, not both", field="--psf")
        if calibrate is not None:
            save_psf = None if save_psf is None else _npz_name(save_psf)
            if save_psf is not None and save_psf.exists() and not force:
                raise TofhilError("already exists; refusing to overwrite (use --force)", file=save_psf)
            from tofhil.eval.fixed_pattern import TapCalibration

            fitted = _calibrate(calibrate, reference, target_threshold,
                                None if flat is None else TapCalibration.load(flat))
            if save_psf is not None:
                fitted.save(save_psf)
                # np.savez adds .npz when missing; report the real name.
                real = save_psf if save_psf.suffix == ".npz" else Path(str(save_psf) + ".npz")
                out.print(f"saved PSF (scattered fraction {fitted.scattered_fraction:.4f}, direct "
                          f"{fitted.direct:.4f}) to {lit(real)}")
            params["psf"] = fitted
        elif psf is not None:
            params["psf"] = str(psf)
        else:
            raise TofhilError("method 'psf' needs --psf FILE.npz or --calibrate CAL.h5", field="--psf")
    elif calibrate is not None or reference is not None or save_psf is not None:
        raise TofhilError("--calibrate, --reference and --save-psf belong to --method psf", field="--method")
    n = correct_session(session, out_path, method, params, force=force,
                        min_amplitude=min_amplitude if (min_amplitude is not None and method != "amplitude") else 0.0,
                        progress=progress)
    out.print(f"wrote {n} corrected frames ({lit(method)}) to {lit(out_path)}")


@app.command()
def compare(a: Path = typer.Argument(..., parser=opt.existing_file, help="Measured session A (.h5)."),
            b: Path = typer.Argument(..., parser=opt.existing_file,
                                     help="Reference session B (.h5): the twin or a ground truth."),
            out_dir: Path = typer.Option(..., "--out", parser=opt.out_dir,
                                         help="Directory for metrics.json and report.html."),
            correct_specs: list[str] = typer.Option([], "--correct",
                                                    help="Correction applied to A, METHOD[:key=value,...], e.g. "
                                                         "psf:psf=cal.npz or uniform:w=2e-5; repeatable."),
            roi: list[str] = typer.Option([], "--roi", help="Region x0,y0,x1,y1 in pixels; repeatable."),
            frames: int = typer.Option(10, "--frames", parser=opt.count(1, 1_000_000), help="Frames averaged per session."),
            cell_size: float = typer.Option(0.1, "--cell-size", parser=opt.finite(0.0, 100.0, lo_open=True, unit="m"),
                                            help="NDT cell size, m."),
            threshold: float = typer.Option(0.01, "--threshold", parser=opt.finite(0.0, 100.0, lo_open=True, unit="m"),
                                            help="F-score distance threshold, m."),
            min_amplitude: float = typer.Option(0.0, "--min-amplitude", parser=opt.finite(0.0, unit="DN"),
                                                help="Invalidate low-amplitude pixels when demodulating."),
            min_relative_amplitude: float = typer.Option(1e-3, "--min-relative-amplitude", parser=opt.finite(0.0, 1.0),
                                                         help="Invalidate pixels below this fraction of the "
                                                              "99th-percentile amplitude (shadows)."),
            no_objects: bool = typer.Option(False, "--no-objects",
                                            help="No per-object regions from the twin's scene."),
            force: bool = typer.Option(False, "--force", help="Overwrite an existing report.")) -> None:
    """Pixel-aligned residuals, cloud and NDT metrics of A against B, before and after corrections."""
    from tofhil.eval.report import compare_sessions

    if frames < 1:
        raise TofhilError(f"got {frames}", field="--frames", expected="an integer >= 1")
    with new_output_dir(out_dir):
        m = compare_sessions(a, b, out_dir, corrections=correct_specs, rois=roi, max_frames=frames,
                             cell_size=cell_size, threshold=threshold, min_amplitude=min_amplitude,
                             min_relative_amplitude=min_relative_amplitude,
                             objects=not no_objects, force=force,
                             log=lambda s: console.print(s, highlight=False, markup=False))
    for name, v in m["variants"].items():
        d = v["regions"]["all"]["depth_residual_m"]
        med = "-" if d["median"] is None else f"{d['median'] * 1000:.2f}"
        mad = "-" if d["mad"] is None else f"{d['mad'] * 1000:.2f}"
        out.print(f"{name:32s} median {med} mm  MAD {mad} mm  (n={d['n']})", markup=False)
    out.print(f"wrote {lit(out_dir / 'metrics.json')} and {lit(out_dir / 'report.html')}")


@app.command("calibrate-taps")
def calibrate_taps_cmd(flat: Path = typer.Option(..., "--flat", parser=opt.existing_file,
                                                  help="Capture with the emitter off, lit by "
                                                                     "unmodulated light on a surface filling the view."),
                       dark: Optional[Path] = typer.Option(None, "--dark", parser=opt.existing_file,
                                                           help="Capture with no light at all."),
                       out_path: Path = typer.Option(..., "--out", parser=opt.new_file,
                                                     help="Tap calibration to write (.npz)."),
                       no_pixel_gain: bool = typer.Option(False, "--no-pixel-gain",
                                                          help="Balance the taps of each pixel only."),
                       force: bool = typer.Option(False, "--force", help="Overwrite OUT if it exists.")) -> None:
    """Per-tap offsets (dark) and gains (flat) for --flat of tofhil correct."""
    from tofhil.eval.fixed_pattern import calibrate_taps

    out_path = _npz_name(out_path)  # np.savez adds .npz: check and name the file really written
    if out_path.exists() and not force:
        raise TofhilError("already exists; refusing to overwrite (use --force)", file=out_path)
    f_taps, (cam, theta) = _mean_taps(flat)
    d_taps = None
    if dark is not None:
        d_taps, _ = _mean_taps(dark)
    try:
        cal = calibrate_taps(f_taps, theta, d_taps, pixel_gain=not no_pixel_gain)
    except TofhilError as exc:
        raise TofhilError(str(exc), file=flat) from None
    cal.info.update({"flat": str(flat), "dark": None if dark is None else str(dark)})
    cal.save(out_path)
    out.print(f"wrote tap calibration to {lit(out_path)} (tap gain spread {cal.info['tap_gain_spread']:.4f}, "
              f"pixel gain spread {cal.info['pixel_gain_spread']:.4f})")
