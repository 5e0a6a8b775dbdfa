"""Diagnosis: what the twin gets wrong, why, the extended model, and the held-out gain.

Its modules, in the order a diagnosis runs them:

- ``heldout`` / ``depth_heldout``: a session (raw taps, or depth + amplitude) -> the complex
  signal per frequency split into training and held-out pixels, with its noise;
- ``twin_model``: the twin as a forward model of those channels (effect parameters -> prediction);
- ``selection``: greedy held-out selection over the effect library, with ``form_prior``
  (priors of flexible forms), ``linear_forms`` (forms fitted in closed form) and
  ``identifiability`` (whether a form's extra parameters are told apart);
- ``verdict``: the tests (noise threshold, per-channel misfits, what is left, the effect sizes)
  and the verdict kinds;
- ``decide``: the decision after the selection, ordered rules with a ledger, the verdict made once;
- ``ambiguity``: every "A or B", with the capture that separates them;
- ``observability``: what the capture cannot tell (unobservable, ambiguous);
- ``structure``: what the residual left looks like;
- ``report``: the HTML page; ``run``: the whole loop (``diagnose``, ``run_diagnosis``)."""

from tofhil.faces import lazy_face

__all__, __getattr__, __dir__ = lazy_face(__name__, {
    "diagnose": "run",
    "run_diagnosis": "run",
    "DiagnosisResult": "run",
    "HeldOutData": "heldout",
    "split_session": "heldout",
    "Selection": "selection",
    "greedy_select": "selection",
    "Verdict": "verdict",
    "write_report": "report",
})
