"""What the fit leaves, said as a signature: the channels it is in, the shape it has over the
field, and the channels it is not in.

When nothing in the library explains a part of the residual, the verdict says where that part
is (a frequency's phase, the taps' alternating part, the offset, the frames) and what shape it
has over the field (smooth, radial, edges, a column pattern, a spot), each against its noise;
naming the clean channels tells the user what it is not (a part in no tap, frequency or frame
channel is light or geometry the twin lacks, not a calibration of the camera).
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

from tofhil.eval.diagnose.verdict import Kind
from tofhil.sim.effects import OFFSET_CHANNEL

#: The channels of :mod:`tofhil.eval.diagnose.channels`, as a sentence names them.
CHANNEL_WORDS = {"tap": "tap", "frequency": "frequency", OFFSET_CHANNEL: OFFSET_CHANNEL, "frame": "frame", "noise": "noise"}


def _field_part(f: Mapping[str, Any]) -> str:
    if f["channel"] == "depth":
        size = f"{1e3 * f['rms']:.1f} mm rms"
    else:  # the amplitude's is a log ratio: a factor where it is large
        size = f"{100 * f['rms']:.1f} % rms" if f["rms"] < 0.5 else f"a factor {math.exp(f['rms']):.2g} rms"
    where = f" on {f['object']}" if f.get("object") else ""
    ratio = f["rms"] / f["noise_rms"] if f.get("noise_rms") else None
    vs = f" ({ratio:.1f} x its noise)" if ratio is not None else ""
    what = f"a {f['channel']} error at depth edges" if f["kind"] == "edges" else f"a {f['kind']} {f['channel']} error"
    return f"{what} of {size}{where}{vs}"


def _join(words: Sequence[str]) -> str:
    words = list(words)
    return words[0] if len(words) == 1 else ", ".join(words[:-1]) + " or " + words[-1]


def what_is_left(channels_after: Mapping[str, Any], structure: Sequence[Mapping[str, Any]],
                 verdict_kind: str) -> str | None:
    """One sentence on the residual left by the fit, or None when the fit leaves nothing to
    say (within noise, explained, nothing searched)."""
    if not Kind(verdict_kind).leaves_a_residual:
        return None
    readings = channels_after.get("readings", [])
    significant = [r for r in readings if r.get("significant")]
    parts = [r["text"] for r in significant]
    # the largest structure of each residual map (depth, amplitude)
    biggest: dict[str, Mapping[str, Any]] = {}
    for f in structure:
        if f["channel"] not in biggest or f["rms"] > biggest[f["channel"]]["rms"]:
            biggest[f["channel"]] = f
    parts += [_field_part(f) for f in biggest.values()]
    if not parts:
        return ("what is left has no shape the residual can be read for: no channel part beyond noise and no "
                "structure over the field (see the residual regions)")
    read = [c for c in CHANNEL_WORDS if any(r["channel"] == c for r in readings)]
    clean = [CHANNEL_WORDS[c] for c in read if not any(r["channel"] == c for r in significant) and c != "noise"]
    text = "what is left: " + "; ".join(parts)
    if clean:
        text += f"; not in any {_join(clean)} channel"
    if biggest and not significant:
        # over the field only, in no calibration channel: light or geometry the twin lacks
        text += (" (light or geometry the twin lacks: a surface it does not have, also outside the view, that "
                 "reflects onto the scene, or a shape of the scene that differs; not a calibration of the camera)")
    return text
