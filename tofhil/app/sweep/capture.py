"""Capture cases: each case captured from a device with its acquisition settings.

The settings of a case are the spec's ``capture`` block, then its ``capture.*`` axes. With
``device: emulator`` and a scene, each case captures from an in-process TOFcam635 emulator
looking at the case's own scene (its effects are the bench's hidden truth); any other device
is the bench as it stands. A camera is one resource: on Dask, captures from one device take
a cluster-wide lock in turn. The twin of a capture is re-rendered with the capture's own
settings.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any, Iterator, Mapping

from tofhil.app.sweep.cases import Case, case_effects, case_scene
from tofhil.app.sweep.spec import EMULATED_BENCH, SweepSpec
from tofhil.errors import TofhilError

def capture_settings(spec: SweepSpec, params: Mapping[str, Any]) -> Any:
    """The acquisition settings of a capture case: the spec's, then the case's axes."""
    from tofhil.drivers.base import CaptureSettings

    c = {**spec.capture, **{k.split(".", 1)[1]: v for k, v in params.items() if k.startswith("capture.")}}
    it = c.get("integration_time_us")
    return CaptureSettings(mode=c["mode"], integration_time_s=None if it is None else float(it) * 1e-6,
                           mod_freq_hz=c.get("mod_freq_hz"), channel=c.get("channel"),
                           min_amplitude=c.get("min_amplitude"),
                           roi=None if c.get("roi") is None else tuple(c["roi"]))


def emulates_bench(spec: SweepSpec) -> bool:
    """True when each case captures from an emulator looking at the case's own scene."""
    return spec.capture is not None and spec.capture["device"] == EMULATED_BENCH and spec.scene is not None


@contextlib.contextmanager
def device_lock(device: str) -> Iterator[None]:
    """One capture at a time per device across a Dask cluster's workers (a camera is one
    resource; the cases' compare and diagnose steps still run in parallel). Outside a worker
    (``workers=0``) the cases run one by one anyway."""
    try:
        from distributed import Lock, get_worker

        get_worker()
    except (ImportError, ValueError):
        yield
        return
    with Lock(f"tofhil-device:{device}"):
        yield


def capture_case(spec: SweepSpec, case: Case, cdir: Path) -> tuple[Path, dict[str, Any] | None]:
    """Capture a case's session from the spec's device into ``cdir/measured.h5``.

    Returns the session and the effects the bench really has where the sweep knows them (an
    emulated bench: the case's effects, else the emulator's own hidden truth), else None."""
    from tofhil.drivers.base import create_driver
    from tofhil.drivers.capture import capture

    device = spec.capture["device"]
    hidden = None
    scene_text = ""
    if emulates_bench(spec):
        from tofhil.drivers.tofcam635.emulator import EmulatedTofCam635, Epc635Emulator
        from tofhil.sim.sources import HIDDEN_TRUTH_EFFECTS, TOFCAM635_OVERRIDES, SimulatedSource
        from tofhil.sim.scene import scene_to_yaml

        # the bench as the emulated TOFcam635 sees it (its camera and sensor model); the twin
        # of each capture starts from the same file
        bench = cdir / "bench_scene.yaml"
        scene_text = scene_to_yaml(case_scene(spec, case.params, TOFCAM635_OVERRIDES))
        bench.write_text(scene_text, encoding="utf-8")
        effects = case_effects(spec, case.params)
        hidden = effects or HIDDEN_TRUTH_EFFECTS
        emulator = Epc635Emulator(SimulatedSource(bench, effects=effects or None),
                                  seed=int(case.params.get("seed", spec.seed)))
        driver = EmulatedTofCam635(device, emulator=emulator)
    else:
        driver = create_driver(device)
    out = cdir / "measured.h5"
    with device_lock(device), driver:
        summary = capture(driver, out, spec.capture["frames"], capture_settings(spec, case.params), force=True,
                          scene_text=scene_text, timeout_s=spec.capture["timeout_s"])
    if summary.ended_early or summary.frames_written < summary.requested:
        raise TofhilError(f"capture from {device} ended after {summary.frames_written} of {summary.requested} "
                          f"frames: {summary.ended_early or 'too few frames'}", file=out)
    return out, hidden


def twin_scene_for_capture(spec: SweepSpec, case: Case, session_path: Path, cdir: Path) -> Any:
    """The case's scene as the twin of its capture (``cdir/twin_scene.yaml``): an emulated
    TOFcam635's camera and sensor model where the bench is emulated, and the capture's own
    acquisition settings (:func:`tofhil.sim.session_setup.write_twin_scene`)."""
    from tofhil.sim.scene import load_scene
    from tofhil.sim.session_setup import write_twin_scene

    if emulates_bench(spec):
        scene = load_scene(cdir / "bench_scene.yaml")
    else:
        scene = case_scene(spec, case.params)
    return write_twin_scene(scene, session_path, cdir / "twin_scene.yaml")[0]

