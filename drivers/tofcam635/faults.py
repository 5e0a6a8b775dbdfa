"""Fault injection for the emulated TOFcam635: which image replies go wrong, and how."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tofhil.errors import DeviceError


FAULT_KINDS = ("crc", "truncate", "garbage", "timeout", "stall", "disconnect")


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
                raise DeviceError(f"unknown fault {kind!r}", field="faults", expected=" | ".join(FAULT_KINDS))
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
