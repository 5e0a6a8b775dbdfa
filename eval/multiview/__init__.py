"""Multi-view models: views registered, fused and scored against the truth (``model``), and the
report (``report``)."""

from tofhil.faces import lazy_face

__all__, __getattr__, __dir__ = lazy_face(__name__, {
    "build_model": "model",
    "MultiViewModel": "model",
    "load_view": "model",
    "score_model": "model",
    "write_model_report": "report",
})
