"""tofhil.eval: real against simulated frames, and what the simulation gets wrong.

Subpackages: ``metrics`` (the one evaluation core: residual maps, regions, ICP, NDT),
``compare`` (A against B, before and after corrections), ``corrections`` (stray light,
taps, depth filters), ``calibration`` (camera and taps), ``rgb`` (colour beside depth),
``multiview`` (models from several views), ``reports`` (pages and figures) and
``diagnose`` (the scientific loop). eval may use sim (diagnosis re-renders); nothing
depends on eval."""

from tofhil.faces import lazy_face

__all__, __getattr__, __dir__ = lazy_face(__name__, {
    "compare_sessions": "compare",
    "evaluate": "metrics.core",
})
