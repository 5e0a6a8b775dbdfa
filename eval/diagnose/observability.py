"""What a capture can and cannot tell: unobservable effects and ambiguous causes.

Two statements a diagnosis owes its reader besides the cause it names:

- **unobservable**: effects left out of the candidates because the data or the scene cannot
  show them (an offset-only effect in depth data; a constant range offset on planes whose
  pose was fitted to the same depth, see :mod:`tofhil.sim.from_capture`);
- **ambiguous**: two readings the capture cannot tell apart, with the capture that would
  (found by :func:`tofhil.eval.diagnose.ambiguity.ambiguities`, the one place of "A or B").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

from tofhil.eval.diagnose.ambiguity import Ambiguity


@dataclass
class Observability:
    unobservable: dict[str, str] = field(default_factory=dict)
    #: The rounds' and the one-view ambiguities, as diagnosis.json has them.
    ambiguous: list[dict[str, Any]] = field(default_factory=list)

    @classmethod
    def of(cls, unobservable: dict[str, str] | None, ambiguous: Sequence[Ambiguity]) -> Observability:
        return cls(unobservable=dict(unobservable or {}), ambiguous=[a.to_json() for a in ambiguous])

    @property
    def lines(self) -> list[str]:
        out = [f"not a candidate: {e} -- {why}" for e, why in self.unobservable.items()]
        out += [a["text"] for a in self.ambiguous]
        return out

    def to_json(self) -> dict[str, Any]:
        return {"unobservable": self.unobservable, "ambiguous": self.ambiguous}
