"""Where an emulated device's images come from: a frame source its caller injects.

Drivers speak devices' protocols; they never import the simulator. An emulator is either
given its frame source (``Epc635Emulator(source)``, ``DepthAIToF(host_scene=...)``) or, when
opened from a device spec (``emulator:SCENE``, ``depthai-sim:SCENE``), asks the provider the
application registered for its device family here. ``tofhil.app.emulators.connect_emulators``
registers the simulator twin's sources (``tofhil.sim.sources``); the CLI does so at start.
The interfaces are the core's (``tofhil.frame_source``).
"""

from __future__ import annotations

from typing import Any, Callable

from tofhil.errors import DeviceError

#: A provider: the text after the scheme of a device spec (``None`` when there is none) ->
#: a frame source for that device family.
SourceProvider = Callable[[str | None], Any]

#: Device families whose emulators take a frame source: what each one's source must be.
FAMILIES = {"tofcam635": "a tofhil.frame_source.ImageSource (raw taps)",
            "depthai": "a tofhil.frame_source.DepthScene (depth frames)"}

_PROVIDERS: dict[str, SourceProvider] = {}


def provide_frame_sources(family: str, provider: SourceProvider) -> None:
    """Register where emulated devices of ``family`` opened from a spec get their images."""
    if family not in FAMILIES:
        raise ValueError(f"unknown device family {family!r}; expected one of {sorted(FAMILIES)}")
    _PROVIDERS[family] = provider


def frame_source(family: str, rest: str | None) -> Any:
    """The frame source of an emulated ``family`` device opened from a spec."""
    provider = _PROVIDERS.get(family)
    if provider is None:
        raise DeviceError(f"no frame source for the emulated {family} device", field="--device",
                          expected=f"{FAMILIES[family]} passed to the emulator, or sources connected by the "
                                   "application (tofhil.app.emulators.connect_emulators())")
    return provider(rest)
