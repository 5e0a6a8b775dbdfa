"""One case of a sweep: simulate (or capture) its session, compare it, diagnose it, and
flatten what each step found into the figures of its record.

:func:`run_case` is the task the Dask engine submits (a top-level function: workers import
it by this module's path). It never raises for a failing case: the error and its traceback
are its record. Its files go to ``cases/CASE_ID/`` of the sweep's directory.

The one module-level state of the sweep lives here: each worker process keeps the
:class:`tofhil.sim.twin.Twin` of the last few scene contents it rendered (``_TWINS``, a small
LRU), so cases whose scene has the same content (other seeds, effects that act after the
render) share one render; ``RENDER_COUNT`` counts the renders those twins traced (a test
checks the sharing).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import time
import traceback
from collections import OrderedDict
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from tofhil.app.sweep.calibration import calibrated_psf_path
from tofhil.app.sweep.capture import capture_case, twin_scene_for_capture
from tofhil.app.sweep.cases import Case, case_effects, case_scene
from tofhil.app.sweep.spec import CALIBRATED_PSF, SweepSpec
from tofhil.errors import TofhilError

_TWINS: "OrderedDict[str, Any]" = OrderedDict()
_TWIN_CACHE_SIZE = 4
#: Renders traced by this process's cached twins (a sweep's test checks the sharing).
RENDER_COUNT = {"renders": 0}


def cached_twin(scene: Any) -> Any:
    """The :class:`Twin` of a scene's content in this process (per Dask worker), so cases
    sharing a scene share its renders."""
    from tofhil.sim.effects import effects_to_block
    from tofhil.sim.pipeline import resolve_effects
    from tofhil.sim.render import content_key
    from tofhil.sim.twin import Twin

    key = content_key(scene, effects_to_block(resolve_effects(scene)))
    twin = _TWINS.get(key)
    if twin is None:
        twin = _TWINS[key] = Twin(scene)
        while len(_TWINS) > _TWIN_CACHE_SIZE:
            _TWINS.popitem(last=False)
    _TWINS.move_to_end(key)
    return twin


# ----------------------------------------------------------------------------- a case's figures
def flatten(prefix: str, x: Any, out: dict[str, Any], depth: int = 0) -> None:
    """Numeric and string leaves of nested mappings as ``prefix.a.b`` columns (lists are
    left out: they are maps or per-frame series, not one figure per case)."""
    if isinstance(x, Mapping):
        if depth > 6:
            return
        for k, v in x.items():
            flatten(f"{prefix}.{k}" if prefix else str(k), v, out, depth + 1)
    elif isinstance(x, (bool, np.bool_)):
        out[prefix] = bool(x)
    elif isinstance(x, (int, float, np.integer, np.floating)):
        v = float(x) if isinstance(x, (float, np.floating)) else int(x)
        out[prefix] = None if isinstance(v, float) and not math.isfinite(v) else v
    elif isinstance(x, str) and len(x) <= 200:
        out[prefix] = x
    elif x is None:
        out[prefix] = None


def compare_metrics(metrics: Mapping[str, Any]) -> dict[str, Any]:
    """The figures of a compare run, one column each: every variant's scalar metrics."""
    out: dict[str, Any] = {}
    for label, v in (metrics.get("variants") or {}).items():
        flatten(f"compare.{label}", {k: val for k, val in v.items() if k not in ("params", "notes", "method")}, out)
    return out


def diagnose_metrics(res: Mapping[str, Any], hidden: Mapping[str, Any] | None) -> dict[str, Any]:
    """The figures of a diagnosis: cause(s), misfit per held-out value, gain before/after,
    and (when the case knows what was hidden) whether the named causes are exactly that."""
    out: dict[str, Any] = {"diagnose.causes": "+".join(res.get("causes") or []) or "none",
                           "diagnose.seconds": res.get("seconds")}
    flatten("diagnose.chi2_per_value", res.get("chi2_per_value") or {}, out)
    flatten("diagnose.gain", res.get("gain") or {}, out)
    if hidden is not None:
        out["diagnose.correct"] = sorted(res.get("causes") or []) == sorted(hidden)
    return out


def plain_params(params: Mapping[str, Any]) -> dict[str, Any]:
    """A case's axis values as plain JSON values (what its record stores)."""
    return json.loads(json.dumps(dict(params), default=str))


# ----------------------------------------------------------------------------- one case
def run_case(spec: SweepSpec, case: Case, out_dir: str) -> dict[str, Any]:
    """Run one case and return its record; never raises for a failing case (the error and
    its traceback are in the record). Writes its files under ``cases/CASE_ID/``."""
    t0 = time.perf_counter()
    record: dict[str, Any] = {"id": case.id, "index": case.index, "params": plain_params(case.params),
                              "status": "ok", "error": None, "metrics": {}, "host": os.uname().nodename,
                              "pid": os.getpid()}
    cdir = Path(out_dir) / "cases" / case.id
    try:
        if cdir.exists():  # a half-done earlier attempt: its files are not results
            shutil.rmtree(cdir)
        cdir.mkdir(parents=True)
        record["metrics"] = _run_case_steps(spec, case, cdir)
    except BaseException as exc:  # noqa: BLE001 - a failing case is a result, not the end of the sweep
        if isinstance(exc, (KeyboardInterrupt, SystemExit)) and not isinstance(exc, TofhilError):
            raise
        record["status"] = "error"
        record["error"] = f"{type(exc).__name__}: {exc}" if not isinstance(exc, TofhilError) else str(exc)
        record["traceback"] = traceback.format_exc(limit=8)
    record["seconds"] = time.perf_counter() - t0
    return record


def _run_case_steps(spec: SweepSpec, case: Case, cdir: Path) -> dict[str, Any]:
    """The steps the spec asks for, in order: capture or simulate (or take the case's
    session), compare, diagnose; the figures of each, in that order."""
    metrics: dict[str, Any] = {}
    scene = case_scene(spec, case.params) if spec.scene is not None else None
    hidden: dict[str, Any] | None = case_effects(spec, case.params) if spec.simulate else None
    if spec.capture is not None:
        t = time.perf_counter()
        measured, hidden = capture_case(spec, case, cdir)
        metrics["capture.seconds"] = time.perf_counter() - t
        if scene is not None:  # the twin re-renders with the capture's settings
            scene = twin_scene_for_capture(spec, case, measured, cdir)
    twin = cached_twin(scene) if scene is not None else None
    if spec.simulate:
        t = time.perf_counter()
        measured = _simulate(spec, case, scene, twin, cdir)
        metrics["simulate.seconds"] = time.perf_counter() - t
    elif spec.capture is None:
        measured = Path(case.params["session"])
    if spec.compare is not None:
        t = time.perf_counter()
        metrics.update(_compare(spec, measured, scene, twin, cdir))
        metrics["compare.seconds"] = time.perf_counter() - t
    if spec.diagnose is not None:
        metrics.update(_diagnose(spec, measured, scene, hidden, cdir))
    if (spec.simulate or spec.capture is not None) and not spec.keep_sessions:
        for name in ("measured.h5", "twin.h5"):
            (cdir / name).unlink(missing_ok=True)
    return metrics


def _simulate(spec: SweepSpec, case: Case, scene: Any, twin: Any, cdir: Path) -> Path:
    """The case's measurement: its scene with the scene's own effects, then the case's
    (:func:`case_effects`), rendered by the shared twin (``cdir/measured.h5``)."""
    from tofhil.sim.effects import effects_to_block
    from tofhil.sim.pipeline import resolve_effects, simulate_session

    eff = effects_to_block(resolve_effects(scene)) | {}
    for k, v in case_effects(spec, case.params).items():
        eff[k] = {**(eff.get(k) or {}), **v}
    before = twin.renders
    measured = simulate_session(scene, cdir / "measured.h5", frames=spec.frames,
                                seed=int(case.params.get("seed", spec.seed)), noise=spec.noise, effects=eff,
                                twin=twin)
    RENDER_COUNT["renders"] += twin.renders - before
    return measured


def _compare(spec: SweepSpec, measured: Any, scene: Any, twin: Any, cdir: Path) -> dict[str, Any]:
    """Compare the measurement with the reference (the twin, or a session), before and after
    each correction; ``@calibration`` is the sweep's calibrated PSF."""
    from tofhil.eval.compare import compare_sessions
    from tofhil.sim.pipeline import simulate_session

    ref = spec.compare["reference"]
    if ref == "twin":
        # The twin's expectation (no noise) of the scene as modelled (its own effects).
        before = twin.renders
        ref = simulate_session(scene, cdir / "twin.h5", frames=1, seed=0, noise=False, effects=None, twin=twin)
        RENDER_COUNT["renders"] += twin.renders - before
    kw = {k: spec.compare[k] for k in ("min_relative_amplitude",) if k in spec.compare}
    psf = str(calibrated_psf_path(cdir.parent.parent))
    m = compare_sessions(measured, ref, cdir / "compare", max_frames=spec.compare["frames"], force=True,
                         corrections=[c.replace(f"={CALIBRATED_PSF}", f"={psf}") for c in spec.compare["corrections"]],
                         **kw)
    # the table names the calibrated PSF by its token, not by this machine's path
    m["variants"] = {k.replace(f"={psf}", f"={CALIBRATED_PSF}"): v for k, v in m["variants"].items()}
    return compare_metrics(m)


def _diagnose(spec: SweepSpec, measured: Any, scene: Any, hidden: Mapping[str, Any] | None,
              cdir: Path) -> dict[str, Any]:
    """Diagnose the measurement against the case's twin scene (``cdir/twin_scene.yaml``);
    ``hidden``: the effects the case really has, where known (``diagnose.correct``)."""
    from tofhil.eval.diagnose.run import run_diagnosis
    from tofhil.sim.scene import scene_to_yaml

    scene_path = cdir / "twin_scene.yaml"
    scene_path.write_text(scene_to_yaml(scene), encoding="utf-8")
    res = run_diagnosis(measured, scene_path, cdir / "diagnose", force=True, **spec.diagnose)
    return diagnose_metrics(res.to_json(), hidden)
