"""Bench session files (HDF5): the public contract documented in docs/session-format.md.

Writing is crash-safe frame by frame: every frame is written to all its datasets and
flushed, and only then is the root attribute ``n_frames`` raised and flushed again. A
writer killed at any instant leaves a file whose ``n_frames`` counts only frames whose
data reached the file; readers trust ``n_frames`` when present, and otherwise the shortest
per-frame dataset.
"""

from __future__ import annotations

import json
import math
import os
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterator, Mapping

import h5py
import numpy as np

from tofhil import __version__
from tofhil.camera import CameraModel
from tofhil.errors import InputFileError
from tofhil.frames import DepthFrame, RawFrame
from tofhil.schema import to_plain

FORMAT = "tofhil.session"
FORMAT_VERSION = 1


def check_new_path(path: Path, force: bool) -> None:
    """Refuse to replace an existing file unless forced; the directory must exist."""
    if path.exists() and not force:
        raise InputFileError("already exists; refusing to overwrite recorded data "
                             "(use --force to replace it)", file=path)
    if not path.parent.exists():
        raise InputFileError("directory does not exist", file=path.parent)


class SessionWriter:
    """Append frames to a new session file as they arrive.

    >>> with SessionWriter("s.h5", camera, device={"model": "emulator"}) as w:
    ...     w.append(raw_frame)
    """

    def __init__(self, path: str | Path, camera: CameraModel, *, device: dict[str, Any] | None = None,
                 scene_text: str = "", force: bool = False, extra_attrs: dict[str, Any] | None = None,
                 sensor_config: Mapping[str, Any] | None = None) -> None:
        self.path = Path(path)
        check_new_path(self.path, force)
        self.camera = camera
        self.n_frames = 0
        self._raw_shape: tuple[int, ...] | None = None
        self._has_raw: bool | None = None
        self._has_depth: bool | None = None
        self._file = h5py.File(self.path, "w")
        a = self._file.attrs
        a["format"] = FORMAT
        a["format_version"] = FORMAT_VERSION
        a["created_utc"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
        a["software_version"] = f"tofhil {__version__}"
        a["device"] = json.dumps(device or {})
        a["camera"] = camera.to_json()
        a["scene"] = scene_text or ""
        if sensor_config is not None:
            # The fully resolved sensor the frames were made with (a simulated device); a
            # re-render of this session uses it instead of a scene's or a preset's defaults.
            a["sensor_config"] = json.dumps(to_plain(sensor_config), allow_nan=False)
        a["n_frames"] = 0
        for k, v in (extra_attrs or {}).items():
            a[k] = v
        fr = self._file.create_group("frames")
        fr.create_dataset("timestamp_s", shape=(0,), maxshape=(None,), dtype="f8", chunks=(1024,))
        fr.create_dataset("sequence", shape=(0,), maxshape=(None,), dtype="i8", chunks=(1024,))
        fr.create_dataset("temperature_c", shape=(0,), maxshape=(None,), dtype="f4", chunks=(1024,))
        self._file.flush()

    # ------------------------------------------------------------------ datasets
    def _create_raw(self, frame: RawFrame) -> None:
        g = self._file.create_group("raw")
        shape = frame.taps.shape
        g.create_dataset("taps", shape=(0,) + shape, maxshape=(None,) + shape, dtype="f4",
                         chunks=(1,) + shape)
        g.create_dataset("freq_hz", data=np.asarray(frame.freq_hz, dtype="f8"))
        g.create_dataset("theta_rad", data=np.asarray(frame.theta_rad, dtype="f8"))
        g.attrs["integration_time_s"] = float(frame.integration_time_s)
        g.attrs["tap_model"] = "c_k = B + A*cos(phi - theta_k), phi = 2*pi*f*L/c"
        self._raw_shape = shape

    def _create_depth(self, depth: DepthFrame) -> None:
        g = self._file.create_group("depth")
        hw = self.camera.shape
        for name, dt in (("radial_m", "f4"), ("amplitude", "f4"), ("intensity", "f4"), ("valid", "u1")):
            g.create_dataset(name, shape=(0,) + hw, maxshape=(None,) + hw, dtype=dt, chunks=(1,) + hw)

    # ------------------------------------------------------------------ appending
    def append(self, raw: RawFrame | None = None, depth: DepthFrame | None = None) -> None:
        """Write one frame (raw taps, depth, or both) and make it durable."""
        if raw is None and depth is None:
            raise ValueError("append needs a raw frame, a depth frame or both")
        if self._has_raw is None:
            self._has_raw, self._has_depth = raw is not None, depth is not None
            if raw is not None:
                self._create_raw(raw)
            if depth is not None:
                self._create_depth(depth)
        if (raw is not None) != self._has_raw or (depth is not None) != self._has_depth:
            raise ValueError("every frame of a session must carry the same parts (raw and/or depth)")
        meta = raw if raw is not None else depth
        assert meta is not None
        n = self.n_frames
        if raw is not None:
            if raw.taps.shape != self._raw_shape:
                raise ValueError(f"taps shape {raw.taps.shape} differs from the session's {self._raw_shape}")
            if raw.camera.shape != self.camera.shape:
                raise ValueError("frame camera size differs from the session's camera")
            ds = self._file["raw/taps"]
            ds.resize(n + 1, axis=0)
            ds[n] = raw.taps.astype(np.float32, copy=False)
        if depth is not None:
            g = self._file["depth"]
            radial = depth.radial_m
            amp = depth.amplitude if depth.amplitude is not None else np.full(radial.shape, np.nan)
            inten = depth.intensity if depth.intensity is not None else np.full(radial.shape, np.nan)
            for name, arr in (("radial_m", radial), ("amplitude", amp), ("intensity", inten),
                              ("valid", np.asarray(depth.valid, dtype=np.uint8))):
                g[name].resize(n + 1, axis=0)
                g[name][n] = arr
        fr = self._file["frames"]
        for name, value in (("timestamp_s", meta.timestamp_s), ("sequence", meta.sequence),
                            ("temperature_c", meta.temperature_c)):
            fr[name].resize(n + 1, axis=0)
            fr[name][n] = value
        self._file.flush()  # the frame's data is on disk ...
        self.n_frames = n + 1
        self._file.attrs["n_frames"] = self.n_frames
        self._file.flush()  # ... before the count that makes it visible

    def close(self) -> None:
        if self._file.id.valid:
            self._file.close()

    def __enter__(self) -> "SessionWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _text_attr(attrs: h5py.AttributeManager, name: str) -> str | None:
    if name not in attrs:
        return None
    v = attrs[name]
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace")
    if isinstance(v, np.ndarray) and v.dtype.kind in "SUO" and v.size == 1:
        v = v.reshape(()).item()
        return v.decode() if isinstance(v, bytes) else str(v)
    return str(v)


class Session:
    """A session file opened for reading. Frames are read lazily, one at a time."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise InputFileError("no such file", file=self.path, expected="a tofhil session (.h5)")
        try:
            self._file = h5py.File(self.path, "r")
        except OSError as exc:
            raise InputFileError(f"cannot be opened as HDF5 ({exc})", file=self.path,
                                 expected="an HDF5 session file") from None
        try:
            self._validate()
        except Exception:
            self._file.close()
            raise

    # ------------------------------------------------------------------ validation
    def _fail(self, field: str, message: str, expected: str) -> None:
        raise InputFileError(message, file=self.path, field=field, expected=expected)

    def _validate(self) -> None:
        f = self._file
        a = f.attrs
        fmt = _text_attr(a, "format")
        if fmt != FORMAT:
            self._fail("format", "missing" if fmt is None else f"is {fmt!r}", f"root attribute format = {FORMAT!r}")
        try:
            version = int(np.asarray(a["format_version"]).reshape(()))
        except (KeyError, TypeError, ValueError):
            self._fail("format_version", "missing or not an integer", "an integer attribute")
        if version > FORMAT_VERSION:
            self._fail("format_version", f"is {version}", f"<= {FORMAT_VERSION} (upgrade tofhil)")
        cam = _text_attr(a, "camera")
        if cam is None:
            self._fail("camera", "missing", "JSON text with width, height, fx, fy, cx, cy, dist")
        self.camera = CameraModel.from_json(cam, source=self.path)
        dev = _text_attr(a, "device") or "{}"
        try:
            self.device = json.loads(dev)
        except json.JSONDecodeError:
            self._fail("device", "is not valid JSON", "JSON text")
        self.scene_text = _text_attr(a, "scene") or ""
        self.sensor_config: dict[str, Any] | None = None
        sensor = _text_attr(a, "sensor_config")
        if sensor:
            try:
                self.sensor_config = json.loads(sensor)
            except json.JSONDecodeError:
                self._fail("sensor_config", "is not valid JSON", "JSON text of a sensor block (or no attribute)")
            if not isinstance(self.sensor_config, dict):
                self._fail("sensor_config", "is not a JSON object", "a JSON object with the sensor settings")
        self.software_version = _text_attr(a, "software_version") or ""
        self.created_utc = _text_attr(a, "created_utc") or ""
        hw = self.camera.shape
        lengths: dict[str, int] = {}
        for name in ("frames/timestamp_s", "frames/sequence"):
            if name not in f:
                self._fail(name, "missing", "a 1-D dataset [N]")
            lengths[name] = f[name].shape[0]
        self.has_raw = "raw" in f
        self.has_depth = "depth" in f
        if not self.has_raw and not self.has_depth:
            self._fail("raw", "neither raw/ nor depth/ is present", "raw/taps and/or depth/radial_m")
        if self.has_raw:
            for name in ("raw/taps", "raw/freq_hz", "raw/theta_rad"):
                if name not in f:
                    self._fail(name, "missing", "see docs/session-format.md")
            taps = f["raw/taps"]
            if taps.ndim != 5 or taps.shape[3:] != hw:
                self._fail("raw/taps", f"has shape {taps.shape}", f"[N, F, K, {hw[0]}, {hw[1]}] (camera size)")
            self.freq_hz = np.asarray(f["raw/freq_hz"][()], dtype=np.float64).ravel()
            self.theta_rad = np.asarray(f["raw/theta_rad"][()], dtype=np.float64).ravel()
            if self.freq_hz.size != taps.shape[1]:
                self._fail("raw/freq_hz", f"has {self.freq_hz.size} values", f"{taps.shape[1]} (F of raw/taps)")
            if self.theta_rad.size != taps.shape[2]:
                self._fail("raw/theta_rad", f"has {self.theta_rad.size} values", f"{taps.shape[2]} (K of raw/taps)")
            if "integration_time_s" not in f["raw"].attrs:
                self._fail("raw.integration_time_s", "missing", "a number (seconds) attribute of raw/")
            self.integration_time_s = float(np.asarray(f["raw"].attrs["integration_time_s"]).reshape(()))
            lengths["raw/taps"] = taps.shape[0]
        if self.has_depth:
            if "depth/radial_m" not in f:
                self._fail("depth/radial_m", "missing", "float32 [N, H, W]")
            for name in ("radial_m", "amplitude", "intensity", "valid"):
                key = f"depth/{name}"
                if key in f:
                    if f[key].ndim != 3 or f[key].shape[1:] != hw:
                        self._fail(key, f"has shape {f[key].shape}", f"[N, {hw[0]}, {hw[1]}]")
                    lengths[key] = f[key].shape[0]
        n = min(lengths.values())
        if "n_frames" in a:
            n = min(n, int(np.asarray(a["n_frames"]).reshape(())))
        self.n_frames = n
        self.dataset_lengths = lengths

    # ------------------------------------------------------------------ access
    @property
    def datasets(self) -> list[str]:
        names: list[str] = []
        self._file.visit(lambda k: names.append(k) if isinstance(self._file[k], h5py.Dataset) else None)
        return names

    def _frame_meta(self, i: int) -> dict[str, Any]:
        f = self._file
        temp = math.nan
        if "frames/temperature_c" in f and f["frames/temperature_c"].shape[0] > i:
            temp = float(f["frames/temperature_c"][i])
        return {"timestamp_s": float(f["frames/timestamp_s"][i]), "sequence": int(f["frames/sequence"][i]),
                "temperature_c": temp}

    def _index(self, i: int) -> int:
        if i < 0:
            i += self.n_frames
        if not 0 <= i < self.n_frames:
            raise IndexError(f"{self.path}: frame {i} out of range (session has {self.n_frames})")
        return i

    def raw_frame(self, i: int) -> RawFrame:
        if not self.has_raw:
            raise InputFileError("has no raw taps", file=self.path, field="raw/taps")
        i = self._index(i)
        return RawFrame(taps=self._file["raw/taps"][i], freq_hz=self.freq_hz, theta_rad=self.theta_rad,
                        integration_time_s=self.integration_time_s, camera=self.camera, **self._frame_meta(i))

    def depth_frame(self, i: int) -> DepthFrame:
        if not self.has_depth:
            raise InputFileError("has no depth frames", file=self.path, field="depth/radial_m")
        i = self._index(i)
        g = self._file["depth"]
        get = lambda name: g[name][i] if name in g else None  # noqa: E731
        valid = get("valid")
        return DepthFrame(distance_m=g["radial_m"][i], kind="radial", camera=self.camera,
                          amplitude=get("amplitude"), intensity=get("intensity"),
                          valid=None if valid is None else valid.astype(bool), **self._frame_meta(i))

    def raw_frames(self) -> Iterator[RawFrame]:
        for i in range(self.n_frames):
            yield self.raw_frame(i)

    def depth_frames(self) -> Iterator[DepthFrame]:
        for i in range(self.n_frames):
            yield self.depth_frame(i)

    def summary(self) -> dict[str, Any]:
        d: dict[str, Any] = {"path": str(self.path), "format_version": int(self._file.attrs["format_version"]),
                             "created_utc": self.created_utc, "software_version": self.software_version,
                             "device": self.device, "camera": self.camera.to_dict(), "n_frames": self.n_frames,
                             "has_raw": self.has_raw, "has_depth": self.has_depth,
                             "scene": bool(self.scene_text), "datasets": {k: list(self._file[k].shape) for k in self.datasets}}
        d.update(self.acquisition())
        d.pop("camera_model", None)
        return d

    def acquisition(self) -> dict[str, Any]:
        """The camera settings the session records: modulation frequencies, tap phases and
        integration time (with raw taps), the camera, and the full resolved sensor
        configuration when the writer stored one (simulated sessions); ``None`` when not."""
        d: dict[str, Any] = {"camera_model": self.camera.to_dict(), "sensor_config": self.sensor_config}
        if self.has_raw:
            d["freq_hz"] = self.freq_hz.tolist()
            d["theta_deg"] = np.degrees(self.theta_rad).round(6).tolist()
            d["integration_time_s"] = self.integration_time_s
        return d

    def close(self) -> None:
        if self._file.id.valid:
            self._file.close()

    def __enter__(self) -> "Session":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_session(path: str | Path) -> Session:
    """Open and validate a session file; errors name the file and the field."""
    return Session(path)


def copy_session_header(src: Session, dst_path: str | Path, *, force: bool = False,
                        note: str | None = None) -> SessionWriter:
    """A new writer with the same camera, device and scene as ``src`` (for derived sessions)."""
    device = dict(src.device)
    if note:
        device["derived"] = note
    return SessionWriter(dst_path, src.camera, device=device, scene_text=src.scene_text, force=force,
                         sensor_config=src.sensor_config)


def remove_partial(path: str | Path) -> None:
    """Remove a file this process created but could not finish (never a user's file)."""
    try:
        os.remove(path)
    except FileNotFoundError:
        pass
