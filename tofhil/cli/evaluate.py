"""``tofhil correct`` and ``tofhil compare``."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import typer

from tofhil.outputs import refuse_existing
from tofhil.cli import app, console, lit, new_output_dir, out, progress
from tofhil.cli import options as opt
from tofhil.errors import TofhilError

_METHOD_HELP = ("METHOD[:key=value,...] (the same syntax as compare --correct): uniform:w=W | "
                "gaussian-inverse:sigma_h=S,sigma_v=S,w=W[,mu=M] | psf:psf=FILE (a PSF file or diagnosis.json; "
                "or --calibrate)[,iterations=N] | twin:scene=EXTENDED.yaml[,remove=light|all] (remove what the fitted "
                "twin predicts beyond each pixel's direct return) | taps:flat=T.npz | amplitude:min_amplitude=A | "
                "jump-angle[:angle_deg=D] | jump-distance[:max_step_m=M,relative=R] | smooth-gaussian[:sigma_px=S] | "
                "smooth-median[:size=N] | smooth-bilateral[:sigma_px=S,sigma_m=M]; complex-domain methods "
                "take flat=T.npz too; uniform, gaussian-inverse and psf take twin=SCENE.yaml (the light of clipped "
                "source pixels from the twin; without it the pixels it would leave wrong are marked untrusted)")


def _pixel_pair(text: str, option: str) -> tuple[float, float]:
    import math

    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        x = y = math.nan
    if not (math.isfinite(x) and math.isfinite(y)):
        raise TofhilError(f"got {text!r}", field=option, expected="X,Y in pixels (two finite numbers)")
    return x, y


@app.command()
def correct(session: Path = typer.Argument(..., parser=opt.existing_file, help="Session to correct (.h5)."),
            method: str = typer.Option(..., "--method", help=_METHOD_HELP),
            out_path: Path = typer.Option(..., "--out", parser=opt.new_file, help="Corrected session to write."),
            calibrate: list[Path] = typer.Option([], "--calibrate", parser=opt.existing_file,
                                                 help="psf: calibration capture (.h5) to fit the PSF from; "
                                                      "repeatable (a card on black, a bright patch at several "
                                                      "field positions: fitted together)."),
            reference: list[Path] = typer.Option([], "--reference", parser=opt.existing_file,
                                                 help="Stray-light-free twin of each calibration capture (one "
                                                      "per --calibrate, same order); without it the captures "
                                                      "must be bright targets on a dark background."),
            psf_form: str = typer.Option("gaussian", "--psf-form",
                                         help="gaussian: Gaussian widths, veil, ghost through the principal "
                                              "point; free: also shift-variant lobes, the ghost's centre "
                                              "fitted, smoothness chosen on held-out pixels."),
            target_threshold: float = typer.Option(0.2, parser=opt.finite(0.0, 1.0, lo_open=True, hi_open=True),
                                                   help="Target pixels: amplitude above this fraction "
                                                             "of the brightest (calibration without reference)."),
            ghost_center: Optional[str] = typer.Option(None, "--ghost-center",
                                                       help="X,Y (pixels) the calibrated ghost mirrors through, "
                                                            "or 'fit' (default the principal point; with "
                                                            "--psf-form free 'fit')."),
            save_psf: Optional[Path] = typer.Option(None, "--save-psf", parser=opt.new_file,
                                                    help="Write the calibrated PSF here (.json)."),
            min_amplitude: float = typer.Option(0.0, "--min-amplitude", parser=opt.finite(0.0, unit="DN"),
                                                help="Invalidate low-amplitude pixels when demodulating."),
            average: bool = typer.Option(False, "--average",
                                         help="Write ONE frame: all frames averaged in the complex domain (taps, "
                                              "before demodulation), then corrected (for the complex methods the "
                                              "same as correcting each frame and averaging, one correction "
                                              "instead of N)."),
            force: bool = typer.Option(False, "--force", help="Overwrite OUT (and --save-psf) if they exist.")) -> None:
    """Apply one correction to every frame of a session (complex-domain ones need raw taps)."""
    from tofhil.eval.corrections import check_min_amplitude, correct_session, parse_method_spec

    # With --calibrate the PSF comes from the calibration, not from psf=FILE.
    name, params = parse_method_spec(method, supplied=("psf",) if calibrate else ())
    check_min_amplitude(min_amplitude, "--min-amplitude")
    if name != "psf" and (calibrate or reference or save_psf is not None or ghost_center is not None):
        raise TofhilError("--calibrate, --reference, --ghost-center and --save-psf belong to --method psf",
                          field="--method")
    # Refuse before any work: nothing is written when an output exists.
    for target in (out_path, save_psf):
        if target is not None:
            refuse_existing(target, force)
    from tofhil.session import open_session

    open_session(session, need_frames=True).close()  # a session of no frames: one line, not "wrote 0"
    fitted = None
    if calibrate:
        if "psf" in params:
            raise TofhilError("give either psf=FILE or --calibrate, not both", field="psf:psf")
        from tofhil.eval.corrections.psf_calibration import calibrate_from_sessions
        from tofhil.eval.calibration.taps import TapCalibration

        flat = TapCalibration.load(params["flat"]) if params.get("flat") else None
        if psf_form not in ("gaussian", "free"):
            raise TofhilError(f"got {psf_form!r}", field="--psf-form", expected="gaussian or free")
        gc: Any = None
        if ghost_center is not None:
            gc = "fit" if ghost_center.strip() == "fit" else _pixel_pair(ghost_center, "--ghost-center")
        fitted = calibrate_from_sessions(calibrate, reference or None, target_threshold=target_threshold,
                                         flat=flat, ghost_center_px=gc, form=psf_form, progress=progress)
        for warning in fitted.info.get("warnings", []):
            console.print(f"warning: PSF calibration: {warning}")
        out.print(f"PSF fit: residual {100 * fitted.info['relative_residual']:.2f} % of the calibration's stray "
                  f"light ({fitted.info['residual_relative_to_signal']:.2e} of its signal), condition "
                  f"{fitted.info['condition']:.3g}")
        params["psf"] = fitted
    elif reference or save_psf is not None or ghost_center is not None:
        raise TofhilError("--reference, --ghost-center and --save-psf need --calibrate CAL.h5", field="--calibrate")
    report: dict[str, Any] = {}
    n = correct_session(session, out_path, name, params, force=force, min_amplitude=min_amplitude,
                        average=average, progress=progress, summary=report)
    for note in report.get("notes", []):
        out.print(f"  {note}", highlight=False, markup=False)
    flagged = {k: v for k, v in (report.get("flagged_pixels") or {}).items() if v}
    if flagged:
        out.print("  flagged pixels (correction/flags): " + ", ".join(f"{k} {v}" for k, v in flagged.items()),
                  highlight=False, markup=False)
    if fitted is not None and save_psf is not None:
        real = fitted.save(save_psf, force=force)
        out.print(f"saved PSF (scattered fraction {fitted.info['scattered_fraction']:.4f}, direct "
                  f"{fitted.keep:.4f}) to {lit(real)}")
    what = "mean frame" if average else "frames"
    out.print(f"wrote {n} corrected {what} ({lit(name)}) to {lit(out_path)}")


@app.command()
def compare(a: Path = typer.Argument(..., parser=opt.existing_file, help="Measured session A (.h5)."),
            b: Path = typer.Argument(..., parser=opt.existing_file, help="Reference session B (.h5): the twin or a ground truth."),
            out_dir: Path = typer.Option(..., "--out", parser=opt.out_dir, help="Directory for metrics.json and report.html."),
            correct_specs: list[str] = typer.Option([], "--correct",
                                                    help="Correction applied to A, METHOD[:key=value,...], e.g. "
                                                         "psf:psf=cal.npz or uniform:w=2e-5; repeatable."),
            roi: list[str] = typer.Option([], "--roi", help="Region X0,Y0,X1,Y1 in pixels, half-open (X1, Y1 "
                                                            "exclusive, as numpy slices); repeatable."),
            mask: list[Path] = typer.Option([], "--mask", parser=opt.existing_file, help="Region mask, .png (non-zero = inside) or .npy, "
                                                              "of the image's size; repeatable."),
            row: Optional[int] = typer.Option(None, "--row", parser=opt.count(0, 10**6), help="Cross-section along this pixel row "
                                                                  "(default: the centre row)."),
            column: Optional[int] = typer.Option(None, "--column", parser=opt.count(0, 10**6), help="Cross-section along this pixel column."),
            frames: int = typer.Option(10, "--frames", parser=opt.count(1, 1_000_000), help="Frames averaged per session."),
            cell_size: float = typer.Option(0.1, "--cell-size", parser=opt.finite(0.0, 100.0, lo_open=True, unit="m"),
                                            help="NDT cell size, m."),
            threshold: float = typer.Option(0.01, "--threshold", parser=opt.finite(0.0, 100.0, lo_open=True, unit="m"),
                                            help="F-score distance threshold, m (> 0)."),
            min_amplitude: float = typer.Option(0.0, "--min-amplitude", parser=opt.finite(0.0, unit="DN"),
                                                help="Invalidate low-amplitude pixels when demodulating."),
            min_relative_amplitude: float = typer.Option(1e-3, "--min-relative-amplitude", parser=opt.finite(0.0, 1.0),
                                                         help="Invalidate pixels below this fraction of the "
                                                              "99th-percentile amplitude (shadows)."),
            no_objects: bool = typer.Option(False, "--no-objects",
                                            help="No per-object regions from the twin's scene."),
            flat: Optional[Path] = typer.Option(None, "--flat", parser=opt.existing_file,
                                                help="Tap calibration (.npz from tofhil calibrate-taps) applied to "
                                                     "BOTH A and B before averaging (refused when a side has depth "
                                                     "only or another calibration)."),
            force: bool = typer.Option(False, "--force", help="Overwrite an existing report.")) -> None:
    """Pixel-aligned residuals, cloud and NDT metrics of A against B, before and after corrections.

    Raw sessions are averaged in the complex domain (taps over --frames frames, before
    demodulation); each region's noise floor (the RMSE noise alone would give) is printed
    beside its error."""
    from tofhil.eval.compare import compare_sessions

    with new_output_dir(out_dir):
        m = compare_sessions(a, b, out_dir, corrections=correct_specs, rois=roi, masks=mask, row=row, column=column,
                             max_frames=frames, cell_size=cell_size, threshold=threshold, min_amplitude=min_amplitude,
                             min_relative_amplitude=min_relative_amplitude, objects=not no_objects, force=force,
                             flat=flat, log=lambda s: console.print(s, highlight=False, markup=False))
    for name, v in m["variants"].items():
        out.print(compare_line(name, v["regions"]["all"]), highlight=False, markup=False)
        for region, r in v["regions"].items():
            if region != "all":
                out.print(compare_line(f"  {region}", r), highlight=False, markup=False)
        for note in v["notes"]:
            out.print(f"  {note}", highlight=False, markup=False)
    out.print(rmse_footnote(), highlight=False, markup=False)
    out.print(f"wrote {lit(out_dir / 'metrics.json')} and {lit(out_dir / 'report.html')}")


#: The console's short name of the headline figure; :func:`rmse_footnote` defines it once, below
#: the lines that use it (the 100-character definition was repeated on every line).
RMSE_LABEL = "depth RMSE*"


def rmse_footnote(a: str = "A", b: str = "B") -> str:
    """The one definition of :data:`RMSE_LABEL`, printed once after the lines that use it."""
    from tofhil.eval.metrics.core import DEPTH_RMSE

    return f"* {DEPTH_RMSE}: sqrt(mean(({a} - {b})^2))"


def compare_line(name: str, region: dict[str, Any]) -> str:
    """One line per variant and region: median, MAD, the trimmed RMSE, the depth RMSE
    (:data:`RMSE_LABEL`, defined once by :func:`rmse_footnote`) and the noise floor (the RMSE
    noise alone would give)."""
    def mm(x: Any) -> str:
        return "-" if x is None else f"{x * 1000:.2f}"

    from tofhil.eval.metrics.core import TRIM_FRACTION

    d = region["depth_residual_m"]  # the robust figures first (a strip of outliers moves the RMSE alone)
    return (f"{name:24s} median {mm(d['median'])} mm  MAD {mm(d['mad'])} mm  "
            f"RMSE {100 * TRIM_FRACTION:g}%-trimmed {mm(d.get('rmse_trimmed'))} mm  {RMSE_LABEL} {mm(d['rmse'])} mm  "
            f"noise floor {mm(region.get('noise_floor_m'))} mm  (n={d['n']})")


@app.command("calibrate-taps")
def calibrate_taps_cmd(flat: Path = typer.Option(..., "--flat", parser=opt.existing_file, help="Capture with the emitter off, lit by "
                                                                     "unmodulated light on a surface filling the view."),
                       dark: Optional[Path] = typer.Option(None, "--dark", parser=opt.existing_file, help="Capture with no light at all."),
                       out_path: Path = typer.Option(..., "--out", parser=opt.new_file, help="Tap calibration to write (.npz; the "
                                                                        "suffix is added when missing)."),
                       no_pixel_gain: bool = typer.Option(False, "--no-pixel-gain",
                                                          help="Balance the taps of each pixel only."),
                       force: bool = typer.Option(False, "--force", help="Overwrite OUT if it exists.")) -> None:
    """Per-tap offsets (dark) and gains (flat) for flat=T.npz of tofhil correct."""
    from tofhil.eval.calibration.taps import TapCalibration, calibrate_taps, mean_taps

    real = TapCalibration.file_path(out_path)
    refuse_existing(real, force)
    f_taps, _cam, theta = mean_taps(flat, progress)
    d_taps = None
    if dark is not None:
        d_taps, _, _ = mean_taps(dark, progress)
    try:
        cal = calibrate_taps(f_taps, theta, d_taps, pixel_gain=not no_pixel_gain)
    except TofhilError as exc:
        raise TofhilError(str(exc), file=flat if exc.field != "dark" else dark) from None
    cal.info.update({"flat": str(flat), "dark": None if dark is None else str(dark)})
    real = cal.save(out_path, force=force)
    out.print(f"wrote tap calibration to {lit(real)} (tap gain spread {cal.info['tap_gain_spread']:.4f}, "
              f"pixel gain spread {cal.info['pixel_gain_spread']:.4f})")
