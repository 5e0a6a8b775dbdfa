"""Property tests: sessions another tool wrote with hostile values are either read and
demodulated, or refused with an InputFileError naming the file and a field -- never any other
exception (issue 11)."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tofhil.depth import depth_from_raw
from tofhil.errors import InputFileError
from tofhil.session import open_session

H, W = 6, 8
CAMERA = {"width": W, "height": H, "fx": 10.0, "fy": 10.0, "cx": 3.5, "cy": 2.5, "dist": [0, 0, 0, 0, 0]}

hostile_float = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([0.0, -1.0, 1e300, -0.0]))
# HDF5 variable-length strings cannot hold NUL: such a file cannot be written, so it is not generated
hdf5_text = st.text(st.characters(blacklist_characters='\x00'), max_size=5)
hostile_value = st.one_of(hostile_float, st.integers(-2**40, 2**40), hdf5_text, st.none())


@st.composite
def sessions(draw):
    """A session dict: which parts are broken, and how."""
    f = draw(st.integers(1, 2))
    k = draw(st.sampled_from([2, 3, 4, 5]))
    freq = draw(st.lists(hostile_float, min_size=1, max_size=3)) if draw(st.booleans()) else [20e6, 30e6][:f]
    theta = (draw(st.lists(hostile_float, min_size=1, max_size=5)) if draw(st.booleans())
             else list(2 * np.pi * np.arange(k) / k))
    dtype = draw(st.sampled_from(["f4", "f8", "i2", "c8", "u1"]))
    shape = draw(st.sampled_from([(2, f, k, H, W), (2, f, k, H, W + 1), (2, f, k, H), (2, len(freq), len(theta), H, W)]))
    fill = draw(st.sampled_from([0.0, np.nan, np.inf, 2047.0, 1e30]))
    camera = dict(CAMERA)
    for key in draw(st.lists(st.sampled_from(list(CAMERA)), max_size=2, unique=True)):
        camera[key] = draw(hostile_value)
    attrs = {"format": "tofhil.session", "format_version": 1, "n_frames": 2}
    for key in draw(st.lists(st.sampled_from(["format_version", "n_frames", "device"]), max_size=2, unique=True)):
        attrs[key] = draw(st.one_of(hostile_float, st.integers(-5, 5), hdf5_text))
    integration = draw(st.one_of(st.just(1e-3), hostile_float))
    saturation = draw(st.one_of(st.none(), hostile_float))
    drop = draw(st.lists(st.sampled_from(["raw/freq_hz", "raw/theta_rad", "frames/sequence"]), max_size=1))
    return dict(freq=freq, theta=theta, dtype=dtype, shape=shape, fill=fill, camera=camera, attrs=attrs,
                integration=integration, saturation=saturation, drop=drop)


def _write(path: Path, s: dict) -> None:
    rng = np.random.default_rng(0)
    taps = rng.uniform(-500, 500, s["shape"])
    taps.flat[::7] = s["fill"]
    with h5py.File(path, "w") as f:
        for key, value in s["attrs"].items():
            f.attrs[key] = value
        f.attrs["camera"] = json.dumps(s["camera"])
        with np.errstate(invalid="ignore", over="ignore"):
            f["raw/taps"] = taps.astype(s["dtype"])
        f["raw/freq_hz"] = np.asarray(s["freq"], dtype=np.float64)
        f["raw/theta_rad"] = np.asarray(s["theta"], dtype=np.float64)
        f["raw"].attrs["integration_time_s"] = s["integration"]
        if s["saturation"] is not None:
            f["raw"].attrs["saturation_dn"] = s["saturation"]
        f["frames/timestamp_s"] = np.arange(2.0)
        f["frames/sequence"] = np.arange(2)
        for name in s["drop"]:
            del f[name]


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(s=sessions())
def test_hostile_sessions_are_read_or_refused_by_field(tmp_path: Path, s: dict) -> None:
    path = tmp_path / "hostile.h5"
    _write(path, s)
    try:
        with open_session(path) as session:
            for i in range(session.n_frames):
                depth = depth_from_raw(session.raw_frame(i))
                # whatever was read: invalid pixels are flagged, never NaN depth marked valid
                assert np.all(np.isfinite(depth.distance_m[depth.valid]))
    except InputFileError as exc:
        assert exc.file == str(path)
        assert exc.field, str(exc)


@pytest.mark.parametrize("k", [2])
def test_two_tap_session_names_the_estimator_requirement(tmp_path: Path, k: int) -> None:
    s = dict(freq=[20e6], theta=[0.0, np.pi], dtype="f4", shape=(2, 1, k, H, W), fill=0.0, camera=dict(CAMERA),
             attrs={"format": "tofhil.session", "format_version": 1, "n_frames": 2}, integration=1e-3,
             saturation=None, drop=[])
    _write(tmp_path / "two.h5", s)
    with pytest.raises(InputFileError, match="K >= 3") as exc:
        open_session(tmp_path / "two.h5")
    assert exc.value.field == "raw/taps"
