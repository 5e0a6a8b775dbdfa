"""Fault injection for the emulated TOFcam635: which image replies go wrong, and how."""

from __future__ import annotations

from dataclasses import dataclass, field

import math

import numpy as np

from tofhil.errors import DeviceError


FAULT_KINDS = ("crc", "truncate", "garbage", "timeout", "stall", "disconnect")
#: Longest disconnect accepted (s): a device away longer is a test that never ends.
MAX_DISCONNECT_S = 3600.0


@dataclass
class FaultPlan:
    """Which image replies go wrong: ``at`` maps the image-request index (0-based) to a
    fault; ``rates`` gives per-request probabilities. ``disconnect_s`` is how long a
    disconnected device stays away."""

    at: dict[int, str] = field(default_factory=dict)
    rates: dict[str, float] = field(default_factory=dict)
    seed: int = 0
    disconnect_s: float = 0.2

    def __post_init__(self) -> None:
        for kind in list(self.at.values()) + list(self.rates):
            if kind not in FAULT_KINDS:
                raise DeviceError(f"unknown fault {kind!r}", field="--faults", expected=" | ".join(FAULT_KINDS))
        # checked here, not where a reply goes wrong: a probability of 1.5 would otherwise fail
        # every reply and the capture would blame the device
        for kind, p in self.rates.items():
            if not (math.isfinite(p) and 0.0 <= p <= 1.0):
                raise DeviceError(f"{kind}={p:g}", field="--faults", expected="a probability in [0, 1]")
        for idx in self.at:
            if idx < 0:
                raise DeviceError(f"fault at request {idx}", field="--faults",
                                  expected="KIND@FRAME with FRAME an integer >= 0")
        if not (math.isfinite(self.disconnect_s) and 0.0 <= self.disconnect_s <= MAX_DISCONNECT_S):
            raise DeviceError(f"disconnect_s={self.disconnect_s:g}", field="--faults",
                              expected=f"a duration in [0, {MAX_DISCONNECT_S:g}] s")
        self._rng = np.random.default_rng(self.seed)

    def fault_for(self, index: int) -> str | None:
        if index in self.at:
            return self.at[index]
        for kind, p in self.rates.items():
            if self._rng.random() < p:
                return kind
        return None

    @classmethod
    def parse(cls, text: str) -> "FaultPlan":
        """``"crc@3,truncate@5,disconnect@8"``, ``"crc=0.05,timeout=0.01"``; ``disconnect_s=2``
        sets how long a disconnect lasts."""
        at: dict[int, str] = {}
        rates: dict[str, float] = {}
        away = 0.2
        for item in filter(None, (t.strip() for t in text.split(","))):
            try:
                if item.startswith("disconnect_s="):
                    away = float(item.partition("=")[2])
                elif "@" in item:
                    kind, idx = item.split("@")
                    at[int(idx)] = kind
                else:
                    kind, p = item.split("=")
                    rates[kind] = float(p)
            except ValueError:
                raise DeviceError(f"bad fault item {item!r}", field="--faults",
                                  expected="KIND@FRAME or KIND=PROBABILITY, comma separated") from None
        return cls(at=at, rates=rates, disconnect_s=away)
