"""Report pages: self-contained HTML (``html``: the page, its figures and the JSON beside it),
the simulation's report (``simulate``) and the twin's lens in a report (``optics``).
Reports of one family live with it (``tofhil.eval.diagnose.report``, ``tofhil.eval.rgb.report``,
``tofhil.eval.multiview.report``)."""

from tofhil.faces import lazy_face

__all__, __getattr__, __dir__ = lazy_face(__name__, {
    "write_page": "html",
    "write_json": "html",
    "write_simulate_report": "simulate",
    "lens_section": "optics",
})
