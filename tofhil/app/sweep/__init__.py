"""Sweeps: many cases of simulate (or capture) / compare / diagnose, one table of results, on Dask.

A sweep spec (YAML) names a scene, the axes to vary (scene parameters, effect parameters,
whole effect sets, camera presets, a camera scale, seeds, capture settings) and a design
(``grid``: every combination; ``random``: ``n`` draws). Each case is one task: it simulates a
session, captures one from a device, or takes a recorded one (a batch over sessions),
compares it with the twin or a reference session, and diagnoses it against the twin, as the
spec says. Every finished case is one record on disk; the table and the report are rebuilt
from the records, so a killed sweep resumes where it stopped. docs/sweeps.md is the user's
guide.

Its modules, in the order a sweep uses them:

- ``spec``: the spec, validated once (:func:`load_spec`, :func:`parse_spec`), and the specs of
  ``tofhil batch`` over recorded sessions (:func:`batch_spec`, :func:`session_list`);
- ``cases``: the design expanded into cases (:func:`expand_cases`) and what one case
  simulates (:func:`case_effects`, :func:`case_scene`);
- ``calibration``: the one stray-light PSF calibration before the cases (``calibrate``);
- ``capture``: capture cases from a device (settings, the device lock, the capture's twin);
- ``run``: one case (:func:`run_case`, the Dask task), its steps and its figures; it holds
  the sweep's one module-level state, the per-process twin cache (``run._TWINS``) and
  its render count (``run.RENDER_COUNT``);
- ``results``: the case records, the table and the report page;
- ``dask_runner``: the engine (:func:`run_sweep`: in this process or on Dask; resume, retry).
"""

from tofhil.faces import lazy_face

__all__, __getattr__, __dir__ = lazy_face(__name__, {
    "SweepSpec": "spec",
    "parse_spec": "spec",
    "load_spec": "spec",
    "batch_spec": "spec",
    "session_list": "spec",
    "Case": "cases",
    "expand_cases": "cases",
    "case_effects": "cases",
    "case_scene": "cases",
    "effects_label": "cases",
    "run_calibration": "calibration",
    "device_lock": "capture",
    "capture_case": "capture",
    "run_case": "run",
    "write_record": "results",
    "read_records": "results",
    "results_table": "results",
    "write_report": "results",
    "run_sweep": "dask_runner",
    "finish_sweep": "dask_runner",
    "local_client": "dask_runner",
    "prepare_sweep_dir": "dask_runner",
    "SweepResult": "dask_runner",
    "SweepInterrupted": "dask_runner",
})
