"""Bench procedures a ToF engineer runs, each with the twin's prediction beside the measured result.

A procedure is a capture plan (``tofhil.app.campaign``), the metrics it defines, the twin's
predicted result for the same plan, and a verdict against a spec sheet. One module per
procedure family: ``photon_transfer`` (EMVA 1288), ``depth`` (accuracy and precision against
distance, flatness and fill rate). :func:`run_bench` runs one; :data:`PROCEDURES` lists them.
"""

from tofhil.app.bench.base import FIGURES, BenchOptions, BenchResult, Figure, SpecSheet, load_spec_sheet
from tofhil.app.bench.run import PROCEDURES, procedure_list, run_bench

__all__ = ["FIGURES", "BenchOptions", "BenchResult", "Figure", "SpecSheet", "load_spec_sheet", "PROCEDURES",
           "procedure_list", "run_bench"]
