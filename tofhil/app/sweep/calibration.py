"""The sweep's one stray-light PSF calibration, fitted before the cases (``calibrate``).

The documented bench procedure (a card in front of the wall against its stray-light-free
twin, or bright targets on black) on scenes that are not the cases, simulated through the
spec's ``effects`` (the lens under test); every case's ``psf:psf=@calibration`` correction
then uses ``calibration/psf.json``. A finished calibration is reused by ``--resume``.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Callable

from tofhil.app.sweep.cases import load_with_camera
from tofhil.app.sweep.spec import SweepSpec
from tofhil.outputs import atomic_path, remove_partial

def calibrated_psf_path(out_dir: str | Path) -> Path:
    """Where a sweep directory keeps its calibrated PSF."""
    return Path(out_dir) / "calibration" / "psf.json"


def run_calibration(spec: SweepSpec, out: Path, say: Callable[[str], None]) -> Path:
    """Fit the sweep's stray-light PSF once (``calibration/psf.json``), before the cases.

    Each calibration capture is the calibration scene with its parameters, simulated with
    the scene's own effects and the spec's ``effects`` (the lens under test; not the cases'
    axes), with the spec's noise; with ``reference: twin`` each is fitted against its
    stray-light-free, noise-free twin, with ``none`` as bright targets on a dark background.
    The captures and the PSF are written to a temporary directory renamed onto
    ``calibration/`` when the fit is done, so ``calibration/psf.json`` is a finished
    calibration; it is reused by ``--resume`` (the spec, and so the calibration, is the same)."""
    from tofhil.eval.corrections.psf_calibration import calibrate_from_sessions

    cal = spec.calibrate
    path = calibrated_psf_path(out)
    if path.is_file():
        say(f"calibration: reusing {path}")
        return path
    for stale in out.glob(f".{path.parent.name}.*.partial"):  # the work of a killed earlier attempt
        remove_partial(stale)
    with atomic_path(path.parent) as work:
        work.mkdir(parents=True)
        captures, refs = _calibration_captures(spec, work, say)
        gc = cal["ghost_center"]
        psf = calibrate_from_sessions(captures, refs or None, form=cal["form"],
                                      ghost_center_px=tuple(gc) if isinstance(gc, list) else gc)
        for warning in psf.info.get("warnings", []):
            say(f"warning: PSF calibration: {warning}")
        say(f"PSF calibrated: residual {100 * psf.info['relative_residual']:.2f} % of the calibration's stray light, "
            f"condition {psf.info['condition']:.3g}")
        psf.save(work / "psf.json", force=True)
        shutil.rmtree(path.parent, ignore_errors=True)  # a calibration/ without psf.json: not a result
    return path


def _calibration_captures(spec: SweepSpec, work: Path, say: Callable[[str], None]) -> tuple[list[Path], list[Path]]:
    """Simulate the calibration captures (and, with ``reference: twin``, their stray-light-free
    references) into ``work``."""
    from tofhil.sim.effects import effects_to_block
    from tofhil.sim.pipeline import resolve_effects, simulate_session

    cal = spec.calibrate
    captures, refs = [], []
    camera = {k: v[0] for k, v in spec.axes.items() if k.startswith("camera.")}  # one value (validated)
    for i, params in enumerate(cal["captures"]):
        scene = load_with_camera(cal["scene"], camera, {"params": params} if params else None)
        eff = effects_to_block(resolve_effects(scene))
        for k, v in spec.effects.items():
            eff[k] = {**(eff.get(k) or {}), **v}
        say(f"calibration capture {i + 1}/{len(cal['captures'])}: {cal['scene']} {params or ''}".rstrip())
        captures.append(simulate_session(scene, work / f"capture_{i}.h5", frames=cal["frames"], seed=spec.seed + 7919 + i,
                                         noise=spec.noise, effects=eff))
        if cal["reference"] == "twin":
            plain = {k: v for k, v in eff.items() if k != "stray_light"}
            refs.append(simulate_session(scene, work / f"reference_{i}.h5", frames=1, noise=False,
                                         effects=plain))
    return captures, refs
