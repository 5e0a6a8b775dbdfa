"""Bench session files (HDF5): the public contract documented in docs/session-format.md.

Writing is crash-safe frame by frame: every frame is written to all its datasets and
flushed, and only then is the root attribute ``n_frames`` raised and flushed again. A
writer killed at any instant leaves a file whose ``n_frames`` counts only frames whose
data reached the file; readers trust ``n_frames`` when present, and otherwise the shortest
per-frame dataset.

Raw taps are stored compactly: in the device's integer type when its taps are integers
(the TOFcam635's int16 DN), else float32, one frame per chunk through HDF5's shuffle and
gzip filters (built into every HDF5 library: MATLAB and h5py read them without plugins).
Readers return float taps either way (an integer store converts exactly).
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
from tofhil.errors import InputFileError, Interrupted
from tofhil.frames import DepthFrame, RawFrame
from tofhil.outputs import check_new_path, partial_path, remove_partial
from tofhil.schema import to_plain

FORMAT = "tofhil.session"
FORMAT_VERSION = 1

#: Most pixels of a session's camera (width x height), checked when a session is opened,
#: before any frame is read. The largest ToF sensors are about 1 Mpx (Azure Kinect 1024 x
#: 1024); 4096 x 4096 leaves room and keeps a float64 frame at 134 MB (a 10 kB file declaring
#: 100000 x 100000 with empty chunked datasets made ``tofhil depth`` allocate 149 GB).
MAX_SESSION_PIXELS = 4096 * 4096
#: Most values of one frame of a per-frame dataset (raw taps F x K x H x W, histograms
#: T x H x W): 2^27 values are 1 GiB as float64, the type frames are processed in.
MAX_FRAME_VALUES = 1 << 27

#: How :class:`SessionWriter` stores raw taps: ``compact`` (the default: integer taps in their
#: own type, else float32; shuffle + gzip per frame chunk) or ``float32`` (float32 without
#: filters: the layout of files written before, for tools that map the data without HDF5).
TAP_STORAGE = ("compact", "float32")
#: gzip level of compact taps: level 1 compresses the TOFcam635's 12-bit taps within a few per
#: cent of level 6 at a fraction of the CPU (benchmarks/bench_session_storage.py).
TAP_GZIP_LEVEL = 1
#: Integer types a compact session stores taps in (HDF5's standard integers, which MATLAB reads
#: as the same classes).
TAP_INTEGER_TYPES = ("int8", "uint8", "int16", "uint16", "int32", "uint32")


def tap_read_dtype(stored: np.dtype) -> np.dtype:
    """The float type a stored tap type reads as, exactly: float32 for float32 and the 8 and
    16-bit integers (every value representable), float64 for wider integers and float64."""
    stored = np.dtype(stored)
    if stored == np.float32 or (stored.kind in "iu" and stored.itemsize <= 2):
        return np.dtype(np.float32)
    return np.dtype(np.float64)




def _os_reason(exc: BaseException) -> str:
    """The operating system's reason inside an OSError (h5py buries it in its message)."""
    import re

    text = str(exc)
    m = re.search(r"error message = '([^']*)'", text)
    if m:
        return m.group(1)
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return text.splitlines()[0] if text else type(exc).__name__


#: Files whose writes failed (disk full): never closed by HDF5, see SessionWriter._abort.
BROKEN_FILES: list[Any] = []


def _drop_quietly(exc: BaseException) -> None:
    """Drop the traceback of a failed HDF5 write with stderr muted: the frames it holds keep
    HDF5 handles, and each released handle retries the write and prints the same error from
    its destructor (the writer reports it once, with the file name)."""
    import gc
    import sys

    tb = exc.__traceback__
    exc.__traceback__ = None
    try:
        sys.stderr.flush()
        saved, devnull = os.dup(2), os.open(os.devnull, os.O_WRONLY)
    except (OSError, ValueError):
        del tb
        return
    try:
        os.dup2(devnull, 2)
        del tb
        gc.collect()
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


#: Files whose writes failed (disk full): never closed by HDF5, see SessionWriter._abort.
BROKEN_FILES: list[Any] = []


def _quiet_hdf5_destructors() -> None:
    """After a failed write every HDF5 handle released retries the write and reports the same
    error from its destructor; the writer has already reported it once, with the file name."""
    import sys

    previous = sys.unraisablehook
    if getattr(previous, "_tofhil_quiet", False):
        return

    def hook(unraisable: Any) -> None:
        if isinstance(unraisable.exc_value, RuntimeError) and "errno" in str(unraisable.exc_value):
            return
        previous(unraisable)

    def excepthook(exc_type: Any, exc: Any, tb: Any) -> None:  # Cython destructors print via this too
        if isinstance(exc, RuntimeError) and "errno" in str(exc):
            return
        previous_excepthook(exc_type, exc, tb)

    previous_excepthook = sys.excepthook
    hook._tofhil_quiet = True  # type: ignore[attr-defined]
    sys.unraisablehook = hook
    sys.excepthook = excepthook


class SessionWriter:
    """Append frames to a new session file as they arrive.

    >>> with SessionWriter("s.h5", camera, device={"model": "emulator"}) as w:
    ...     w.append(raw_frame)

    A capture (``derived=False``, the default) writes the file itself: whatever stops it,
    every completed frame stays. A ``derived`` output (depth, a correction, a simulation:
    re-creatable from its inputs) is written to a hidden temporary file beside it and renamed
    into place when closed without error: an error removes it (nothing is left behind, an
    existing file replaced with ``--force`` stays as it was), and an interrupt (Ctrl-C) keeps
    the completed frames, raising :class:`tofhil.errors.Interrupted` that says how many.
    """

    def __init__(self, path: str | Path, camera: CameraModel, *, device: dict[str, Any] | None = None,
                 scene_text: str = "", force: bool = False, extra_attrs: dict[str, Any] | None = None,
                 derived: bool = False, sensor_config: Mapping[str, Any] | None = None,
                 histogram_attrs: Mapping[str, Any] | None = None, tap_storage: str = "compact",
                 tap_dtype: str | np.dtype | None = None) -> None:
        """``tap_storage``: see :data:`TAP_STORAGE`. ``tap_dtype`` (compact only): store the
        taps in this integer type even when frames hand them over as floats (a copy of an
        integer session: its reader's floats are exact integers); every frame's taps must
        then be integers in its range. Without it the first frame's taps decide: an integer
        array keeps its type, anything else is float32."""
        if tap_storage not in TAP_STORAGE:
            raise ValueError(f"tap_storage {tap_storage!r} is not one of {', '.join(TAP_STORAGE)}")
        if tap_dtype is not None and np.dtype(tap_dtype).name not in TAP_INTEGER_TYPES + ("float32",):
            raise ValueError(f"tap_dtype {np.dtype(tap_dtype)} is not one of {', '.join(TAP_INTEGER_TYPES)}, float32")
        self.tap_storage = tap_storage
        self._tap_dtype = None if tap_dtype is None else np.dtype(tap_dtype)
        self.path = Path(path)
        # Attributes of the histograms/ group of a direct-ToF session (bin_width_s, t0_s, ...).
        self._histogram_attrs = dict(histogram_attrs or {})
        self._has_histograms: bool | None = None
        check_new_path(self.path, force)
        if camera.width * camera.height > MAX_SESSION_PIXELS:  # no reader would open it
            raise InputFileError(f"camera of {camera.width} x {camera.height} pixels", file=self.path,
                                 field="camera", expected=f"at most {MAX_SESSION_PIXELS:,} pixels (4096 x 4096)")
        self.camera = camera
        self.n_frames = 0
        self.derived = derived
        self._datasets: dict[str, Any] = {}
        self._held: list[Any] = []
        self._raw_shape: tuple[int, ...] | None = None
        self._has_raw: bool | None = None
        self._has_depth: bool | None = None
        self._write_path = partial_path(self.path) if derived else self.path
        try:
            self._file = h5py.File(self._write_path, "w")
        except OSError as exc:
            raise InputFileError(f"cannot be written ({_os_reason(exc)})", file=self.path) from None
        try:
            self._write_header(device, scene_text, extra_attrs, sensor_config)
        except BaseException as exc:
            self._abort()
            if isinstance(exc, OSError):
                raise InputFileError(f"cannot be written ({_os_reason(exc)})", file=self.path) from None
            raise

    def _write_header(self, device: dict[str, Any] | None, scene_text: str,
                      extra_attrs: dict[str, Any] | None, sensor_config: Mapping[str, Any] | None) -> None:
        camera = self.camera
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
        fr = self._hold(self._file.create_group("frames"))
        self._hold(fr.create_dataset("timestamp_s", shape=(0,), maxshape=(None,), dtype="f8", chunks=(1024,)))
        self._hold(fr.create_dataset("sequence", shape=(0,), maxshape=(None,), dtype="i8", chunks=(1024,)))
        self._hold(fr.create_dataset("temperature_c", shape=(0,), maxshape=(None,), dtype="f4", chunks=(1024,)))
        self._file.flush()

    # ------------------------------------------------------------------ datasets
    def _create_raw(self, frame: RawFrame) -> None:
        g = self._hold(self._file.create_group("raw"))
        shape = frame.taps.shape
        filters: dict[str, Any] = {}
        dtype = np.dtype(np.float32)
        if self.tap_storage == "compact":
            # One frame per chunk as before (a frame is complete or absent after a crash),
            # shuffled (the high bytes of 12-bit DN are nearly constant) and deflated.
            filters = {"shuffle": True, "compression": "gzip", "compression_opts": TAP_GZIP_LEVEL}
            given = np.dtype(frame.taps.dtype)
            if self._tap_dtype is not None:
                dtype = self._tap_dtype
            elif given.kind in "iu" and given.name in TAP_INTEGER_TYPES:
                dtype = np.dtype(given.name)        # the device's type, native byte order
        self._hold(g.create_dataset("taps", shape=(0,) + shape, maxshape=(None,) + shape, dtype=dtype,
                                    chunks=(1,) + shape, **filters))
        self._tap_store = dtype
        self._hold(g.create_dataset("freq_hz", data=np.asarray(frame.freq_hz, dtype="f8")))
        self._hold(g.create_dataset("theta_rad", data=np.asarray(frame.theta_rad, dtype="f8")))
        g.attrs["integration_time_s"] = float(frame.integration_time_s)
        for key in ("saturation_dn", "saturation_low_dn"):  # the ADC's clip levels (TapLimits)
            if frame.meta.get(key) is not None:
                g.attrs[key] = float(frame.meta[key])
        g.attrs["tap_model"] = "c_k = B + A*cos(phi - theta_k), phi = 2*pi*f*L/c"
        self._raw_shape = shape

    def _create_depth(self, depth: DepthFrame) -> None:
        g = self._hold(self._file.create_group("depth"))
        hw = self.camera.shape
        parts = [("radial_m", "f4"), ("amplitude", "f4"), ("intensity", "f4"), ("valid", "?")]
        if depth.confidence is not None:
            parts.append(("confidence", "f4"))  # the device's own confidence, as the device gives it
        self._has_confidence = depth.confidence is not None
        # the modulation frequencies the device measured the depth at, when it says (a depth-only
        # capture keeps what a raw one records in raw/freq_hz)
        if depth.meta.get("freq_hz") is not None:
            g.attrs["freq_hz"] = np.atleast_1d(np.asarray(depth.meta["freq_hz"], dtype="f8"))
        for name, dt in parts:
            self._hold(g.create_dataset(name, shape=(0,) + hw, maxshape=(None,) + hw, dtype=dt, chunks=(1,) + hw))

    def _create_histograms(self, histogram: Mapping[str, np.ndarray]) -> None:
        if "counts" not in histogram:
            raise ValueError("a histogram frame needs its 'counts' [T, H, W]")
        g = self._hold(self._file.create_group("histograms"))
        for name, arr in histogram.items():
            shape = np.shape(arr)
            self._hold(g.create_dataset(name, shape=(0,) + shape, maxshape=(None,) + shape, dtype="f4",
                                        chunks=(1,) + shape))
        for k, v in self._histogram_attrs.items():
            g.attrs[k] = v
        self._histogram_shapes = {k: np.shape(v) for k, v in histogram.items()}

    # ------------------------------------------------------------------ appending
    def append(self, raw: RawFrame | None = None, depth: DepthFrame | None = None,
               histogram: Mapping[str, np.ndarray] | None = None) -> None:
        """Write one frame (raw taps, depth, a direct-ToF histogram, or several) and make it
        durable. ``histogram`` maps dataset names under ``histograms/`` to this frame's arrays
        (``counts`` [T, H, W] at least)."""
        try:
            self._append(raw, depth, histogram)
        except (OSError, RuntimeError) as exc:  # disk full, file size limit, I/O error: name the file
            if isinstance(exc, RuntimeError) and "errno" not in str(exc):
                raise  # not a write failure (h5py reports those as RuntimeError with an errno)
            self._broken = True
            reason = _os_reason(exc)
            _drop_quietly(exc)
            raise InputFileError(f"cannot be written ({reason}); {self.n_frames} frame(s) completed",
                                 file=self.path) from None

    def _hold(self, obj: Any) -> Any:
        """Keep an HDF5 handle for the writer's life (see :meth:`_dataset`)."""
        self._held.append(obj)
        return obj

    def _dataset(self, name: str) -> Any:
        """One handle per dataset for the writer's life: a released handle makes HDF5 write
        its cached metadata from a destructor, where a disk-full error cannot be caught."""
        ds = self._datasets.get(name)
        if ds is None:
            ds = self._datasets[name] = self._file[name]
        return ds

    def _append(self, raw: RawFrame | None, depth: DepthFrame | None,
                histogram: Mapping[str, np.ndarray] | None = None) -> None:
        if raw is None and depth is None:
            raise ValueError("append needs a raw frame, a depth frame or both")
        if self._has_histograms is None:
            self._has_histograms = histogram is not None
            if histogram is not None:
                self._create_histograms(histogram)
        if (histogram is not None) != self._has_histograms:
            raise ValueError("every frame of a session must carry the same parts (histograms or not)")
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
        for name, arr in (histogram or {}).items():
            if np.shape(arr) != self._histogram_shapes.get(name):
                raise ValueError(f"histograms/{name} is {np.shape(arr)}, the session's {self._histogram_shapes.get(name)}")
            ds = self._dataset(f"histograms/{name}")
            ds.resize(n + 1, axis=0)
            ds[n] = np.asarray(arr, dtype=np.float32)
        if raw is not None:
            if raw.taps.shape != self._raw_shape:
                raise ValueError(f"taps shape {raw.taps.shape} differs from the session's {self._raw_shape}")
            if raw.camera.shape != self.camera.shape:
                raise ValueError("frame camera size differs from the session's camera")
            taps = self._taps_to_store(raw.taps)
            ds = self._dataset("raw/taps")
            ds.resize(n + 1, axis=0)
            ds[n] = taps
        if depth is not None:
            radial = depth.radial_m
            amp = depth.amplitude if depth.amplitude is not None else np.full(radial.shape, np.nan)
            inten = depth.intensity if depth.intensity is not None else np.full(radial.shape, np.nan)
            parts = [("radial_m", radial), ("amplitude", amp), ("intensity", inten),
                     ("valid", np.asarray(depth.valid, dtype=bool))]
            if getattr(self, "_has_confidence", False):
                conf = depth.confidence if depth.confidence is not None else np.full(radial.shape, np.nan)
                parts.append(("confidence", conf))
            for name, arr in parts:
                ds = self._dataset(f"depth/{name}")
                ds.resize(n + 1, axis=0)
                ds[n] = arr
        for name, value in (("timestamp_s", meta.timestamp_s), ("sequence", meta.sequence),
                            ("temperature_c", meta.temperature_c)):
            ds = self._dataset(f"frames/{name}")
            ds.resize(n + 1, axis=0)
            ds[n] = value
        self._file.flush()  # the frame's data is on disk ...
        self.n_frames = n + 1
        self._file.attrs["n_frames"] = self.n_frames
        self._file.flush()  # ... before the count that makes it visible

    def _taps_to_store(self, taps: np.ndarray) -> np.ndarray:
        """The frame's taps in the stored type; an integer store takes only exact integers in
        its range (a float tap would be rounded: refused, naming the frame)."""
        store = self._tap_store
        if store.kind == "f":
            return np.asarray(taps).astype(store, copy=False)
        a = np.asarray(taps)
        if a.dtype == store:
            return a
        info = np.iinfo(store)
        with np.errstate(invalid="ignore"):
            ok = a.dtype.kind in "iu" or bool(np.all(np.isfinite(a)) and np.all(a == np.rint(a)))
        if not ok or a.min(initial=0) < info.min or a.max(initial=0) > info.max:
            raise ValueError(f"frame {self.n_frames}: raw taps are not {store} integers "
                             f"(the session stores taps as {store}; values {a.min()}..{a.max()}, "
                             f"dtype {a.dtype})")
        return a.astype(store)

    def close(self) -> None:
        """Finish the file (a derived output is renamed into place)."""
        if getattr(self, "_broken", False):
            self._abort()
            return
        if self._file.id.valid:
            try:
                # A Ctrl-C between a frame's data flush and its count leaves the count one short:
                # the frame is complete, so the file says what the writer (and the message) says.
                if int(self._file.attrs.get("n_frames", 0)) != self.n_frames:
                    self._file.attrs["n_frames"] = self.n_frames
                self._file.close()
            except (OSError, RuntimeError) as exc:
                self._abort()
                raise InputFileError(f"cannot be written ({_os_reason(exc)})", file=self.path) from None
            if self.derived:
                os.replace(self._write_path, self.path)

    def _abort(self) -> None:
        """Close without finishing; a derived output, or a file holding no frame, is removed."""
        if getattr(self, "_broken", False):
            # After a failed write HDF5 cannot close the file cleanly (it retries the write,
            # reports from destructors, may crash): keep the handle alive, unlink the file.
            BROKEN_FILES.append(self._file)
        else:
            try:
                if self._file.id.valid:
                    self._file.close()
            except Exception:  # the error being reported matters more than a failed close
                pass
        if self.derived or self.n_frames == 0:
            remove_partial(self._write_path)

    def __enter__(self) -> "SessionWriter":
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: object) -> None:
        if exc_type is None:
            self.close()
            return
        interrupted = issubclass(exc_type, KeyboardInterrupt)
        if self.n_frames == 0 or (self.derived and not interrupted):
            self._abort()
        else:
            self.close()  # the completed frames are a valid, shorter session
        if interrupted and not isinstance(exc, Interrupted):
            raise Interrupted(self.path, self.n_frames) from None


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
        if self.path.is_dir():
            raise InputFileError("is a directory", file=self.path, expected="a tofhil session file (.h5)")
        if not self.path.is_file():
            what = "no such file" if not self.path.exists() else "is not a regular file"
            raise InputFileError(what, file=self.path, expected="a tofhil session (.h5)")
        try:
            self._file = h5py.File(self.path, "r")
        except OSError as exc:
            raise InputFileError(f"cannot be opened as HDF5 ({_os_reason(exc)})", file=self.path,
                                 expected="an HDF5 session file") from None
        try:
            self._validate()
        except InputFileError:
            self._file.close()
            raise
        except Exception as exc:  # a malformed file h5py or numpy chokes on: still the file's fault
            self._file.close()
            raise InputFileError(f"is malformed ({type(exc).__name__}: {exc})", file=self.path,
                                 expected="the layout of docs/session-format.md") from None

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
        except (KeyError, TypeError, ValueError, OverflowError):  # inf -> OverflowError
            self._fail("format_version", "missing or not an integer", "an integer attribute")
        if version > FORMAT_VERSION:
            self._fail("format_version", f"is {version}", f"<= {FORMAT_VERSION} (upgrade tofhil)")
        cam = _text_attr(a, "camera")
        if cam is None:
            self._fail("camera", "missing", "JSON text with width, height, fx, fy, cx, cy, dist")
        self.camera = CameraModel.from_json(cam, source=self.path)
        if self.camera.width * self.camera.height > MAX_SESSION_PIXELS:
            self._fail("camera", f"declares {self.camera.width} x {self.camera.height} pixels",
                       f"a camera of at most {MAX_SESSION_PIXELS:,} pixels (4096 x 4096)")
        dev = _text_attr(a, "device") or "{}"
        try:
            self.device = json.loads(dev)
        except json.JSONDecodeError:
            self._fail("device", "is not valid JSON", "JSON text")
        if not isinstance(self.device, dict):
            self._fail("device", f"is JSON {type(self.device).__name__}", "a JSON object")
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
            if name not in f or not isinstance(f[name], h5py.Dataset):
                self._fail(name, "missing", "a 1-D dataset [N]")
            if f[name].ndim != 1 or f[name].dtype.kind not in "iuf":
                self._fail(name, f"has shape {f[name].shape} and type {f[name].dtype}", "a 1-D numeric dataset [N]")
            lengths[name] = f[name].shape[0]
        self.has_raw = "raw" in f
        self.has_depth = "depth" in f
        if not self.has_raw and not self.has_depth:
            self._fail("raw", "neither raw/ nor depth/ is present", "raw/taps and/or depth/radial_m")
        for name in ("raw/taps", "histograms/counts"):
            ds = f.get(name)
            if isinstance(ds, h5py.Dataset) and ds.ndim >= 1 and math.prod(ds.shape[1:]) > MAX_FRAME_VALUES:
                self._fail(name, f"has frames of shape {ds.shape[1:]}",
                           f"at most {MAX_FRAME_VALUES:,} values a frame (1 GiB as float64)")
        if self.has_raw:
            self._validate_raw(hw)
            lengths["raw/taps"] = f["raw/taps"].shape[0]
        self.has_histograms = "histograms" in f
        if self.has_histograms:
            self._validate_histograms(hw)
            lengths["histograms/counts"] = f["histograms/counts"].shape[0]
        if self.has_depth:
            if "depth/radial_m" not in f:
                self._fail("depth/radial_m", "missing", "float32 [N, H, W]")
            for name in ("radial_m", "amplitude", "intensity", "valid", "confidence"):
                key = f"depth/{name}"
                if key in f:
                    if not isinstance(f[key], h5py.Dataset) or f[key].dtype.kind not in "fiub":
                        self._fail(key, "is not a numeric dataset", "real numbers [N, H, W]")
                    if f[key].ndim != 3 or f[key].shape[1:] != hw:
                        self._fail(key, f"has shape {f[key].shape}", f"[N, {hw[0]}, {hw[1]}]")
                    lengths[key] = f[key].shape[0]
            self.depth_freq_hz = None
            if "freq_hz" in f["depth"].attrs:
                fr = np.atleast_1d(np.asarray(f["depth"].attrs["freq_hz"], dtype=np.float64)).ravel()
                if fr.size == 0 or not (np.all(np.isfinite(fr)) and np.all(fr > 0)):
                    self._fail("depth.freq_hz", f"is {fr.tolist()}", "positive finite modulation frequencies in Hz")
                self.depth_freq_hz = fr
        n = min(lengths.values())
        if "n_frames" in a:
            try:
                declared = np.asarray(a["n_frames"]).reshape(())
                if declared.dtype.kind not in "iu" or int(declared) < 0:
                    raise ValueError
            except (TypeError, ValueError):
                self._fail("n_frames", f"is {a['n_frames']!r}", "a non-negative integer (completed frames)")
            n = min(n, int(declared))
        self.n_frames = n
        self.dataset_lengths = lengths

    def _validate_raw(self, hw: tuple[int, int]) -> None:
        """raw/: taps real numbers ``[N, F, K, H, W]``, F positive finite frequencies, K >= 3
        equally spaced finite phases, a sane integration time and clip levels."""
        from tofhil.demod import estimator_weights

        f = self._file
        for name in ("raw/taps", "raw/freq_hz", "raw/theta_rad"):
            if name not in f or not isinstance(f[name], h5py.Dataset):
                self._fail(name, "missing", "see docs/session-format.md")
        taps = f["raw/taps"]
        if taps.dtype.kind not in "fiu":
            self._fail("raw/taps", f"has type {taps.dtype}", "real numbers (float32 DN); complex or "
                       "text taps are not correlation samples")
        if taps.ndim != 5 or taps.shape[3:] != hw:
            self._fail("raw/taps", f"has shape {taps.shape}", f"[N, F, K, {hw[0]}, {hw[1]}] (camera size)")
        freq, theta = f["raw/freq_hz"], f["raw/theta_rad"]
        for name, ds in (("raw/freq_hz", freq), ("raw/theta_rad", theta)):
            if ds.dtype.kind not in "fiu":
                self._fail(name, f"has type {ds.dtype}", "real numbers (float64)")
        self.freq_hz = np.asarray(freq[()], dtype=np.float64).ravel()
        self.theta_rad = np.asarray(theta[()], dtype=np.float64).ravel()
        if self.freq_hz.size != taps.shape[1]:
            self._fail("raw/freq_hz", f"has {self.freq_hz.size} values", f"{taps.shape[1]} (F of raw/taps)")
        if self.theta_rad.size != taps.shape[2]:
            self._fail("raw/theta_rad", f"has {self.theta_rad.size} values", f"{taps.shape[2]} (K of raw/taps)")
        if not (np.all(np.isfinite(self.freq_hz)) and np.all(self.freq_hz > 0)):
            self._fail("raw/freq_hz", f"is {self.freq_hz.tolist()}", "positive finite modulation frequencies in Hz")
        if self.freq_hz.size == 0:
            self._fail("raw/freq_hz", "is empty", "at least one modulation frequency")
        if not np.all(np.isfinite(self.theta_rad)):
            self._fail("raw/theta_rad", f"is {self.theta_rad.tolist()}", "finite phases in radians")
        if self.theta_rad.size < 3:
            self._fail("raw/taps", f"has K={self.theta_rad.size} taps per frequency",
                       "K >= 3 equally spaced phases (a 2-tap A/B readout is stored as its canonical "
                       "taps: both sub-frames, tofhil.demod.differential_to_taps)")
        try:
            estimator_weights(self.theta_rad)
        except ValueError as exc:
            self._fail("raw/theta_rad", str(exc), "K equally spaced phases over 2 pi")
        g = f["raw"]
        if "integration_time_s" not in g.attrs:
            self._fail("raw.integration_time_s", "missing", "a number (seconds) attribute of raw/")
        self.integration_time_s = self._number_attr(g.attrs, "raw.integration_time_s", "integration_time_s",
                                                    "a positive number of seconds (NaN if unknown)",
                                                    allow_nan=True, positive=True)
        self.tap_limits_meta: dict[str, float] = {}
        for key in ("saturation_dn", "saturation_low_dn"):
            if key in g.attrs:
                self.tap_limits_meta[key] = self._number_attr(g.attrs, f"raw.{key}", key,
                                                              "a finite number of DN (the ADC's clip level)")

    def _validate_histograms(self, hw: tuple[int, int]) -> None:
        """histograms/ (direct ToF): counts ``[N, T, H, W]`` real numbers, bin width > 0 and
        the first bin's time (attributes)."""
        f = self._file
        if "histograms/counts" not in f or not isinstance(f["histograms/counts"], h5py.Dataset):
            self._fail("histograms/counts", "missing", "float32 [N, T, H, W] counts per bin")
        c = f["histograms/counts"]
        if c.dtype.kind not in "fiu":
            self._fail("histograms/counts", f"has type {c.dtype}", "real numbers (counts)")
        if c.ndim != 4 or c.shape[2:] != hw or c.shape[1] < 2:
            self._fail("histograms/counts", f"has shape {c.shape}", f"[N, T >= 2, {hw[0]}, {hw[1]}] (camera size)")
        g = f["histograms"]
        for key in ("bin_width_s", "t0_s"):
            if key not in g.attrs:
                self._fail(f"histograms.{key}", "missing", "a number (seconds) attribute of histograms/")
        self.bin_width_s = self._number_attr(g.attrs, "histograms.bin_width_s", "bin_width_s",
                                             "a positive number of seconds", positive=True)
        self.t0_s = self._number_attr(g.attrs, "histograms.t0_s", "t0_s", "a finite number of seconds")
        self.histogram_meta = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in g.attrs.items()}

    def _number_attr(self, attrs: h5py.AttributeManager, field: str, key: str, expected: str, *,
                     allow_nan: bool = False, positive: bool = False) -> float:
        try:
            v = np.asarray(attrs[key])
            if v.size != 1 or v.dtype.kind not in "fiub":
                raise ValueError
            x = float(v.reshape(()))
        except (TypeError, ValueError, OverflowError):
            self._fail(field, f"is {attrs[key]!r}", expected)
        if math.isnan(x):
            if not allow_nan:
                self._fail(field, "is NaN", expected)
        elif not math.isfinite(x) or (positive and x <= 0):
            self._fail(field, f"is {x!r}", expected)
        return x

    # ------------------------------------------------------------------ access
    @property
    def stored_tap_dtype(self) -> np.dtype | None:
        """The type ``raw/taps`` is stored in (None without raw taps): what a copy of the taps
        passes as ``SessionWriter(tap_dtype=...)`` to stay as compact when it is an integer."""
        return np.dtype(self._file["raw/taps"].dtype) if self.has_raw else None

    @property
    def integer_tap_dtype(self) -> np.dtype | None:
        """:attr:`stored_tap_dtype` when it is one of :data:`TAP_INTEGER_TYPES`, else None."""
        dt = self.stored_tap_dtype
        return dt if dt is not None and dt.name in TAP_INTEGER_TYPES else None

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
            if getattr(self, "has_histograms", False):
                raise InputFileError("is a direct-ToF session: it holds histograms and depth, no raw taps",
                                     file=self.path, field="raw/taps",
                                     expected="a correlation-ToF session with raw/taps")
            raise InputFileError("has no raw taps", file=self.path, field="raw/taps")
        i = self._index(i)
        try:
            taps = self._file["raw/taps"][i]
            meta = self._frame_meta(i)
        except (OSError, ValueError, TypeError) as exc:  # a damaged chunk, an unreadable filter
            raise InputFileError(f"frame {i} cannot be read ({_os_reason(exc)})", file=self.path,
                                 field="raw/taps") from None
        if taps.dtype != np.float32 and taps.dtype != np.float64:
            taps = taps.astype(tap_read_dtype(taps.dtype))  # integer DN: exact in the float type
        return RawFrame(taps=taps, freq_hz=self.freq_hz, theta_rad=self.theta_rad,
                        integration_time_s=self.integration_time_s, camera=self.camera,
                        meta=dict(self.tap_limits_meta), **meta)

    def depth_frame(self, i: int) -> DepthFrame:
        if not self.has_depth:
            raise InputFileError("has no depth frames", file=self.path, field="depth/radial_m",
                                 expected="a session with depth (tofhil import, or tofhil depth on raw taps)")
        i = self._index(i)
        g = self._file["depth"]
        get = lambda name: g[name][i] if name in g else None  # noqa: E731
        try:
            valid = get("valid")
            parts = {name: get(name) for name in ("radial_m", "amplitude", "intensity", "confidence")}
            meta = self._frame_meta(i)
        except (OSError, ValueError, TypeError) as exc:
            raise InputFileError(f"frame {i} cannot be read ({_os_reason(exc)})", file=self.path,
                                 field="depth") from None
        return DepthFrame(distance_m=parts["radial_m"], kind="radial", camera=self.camera,
                          amplitude=parts["amplitude"], intensity=parts["intensity"],
                          confidence=parts["confidence"],
                          valid=None if valid is None else valid.astype(bool), **meta)

    def requested_depth_frame(self, frame: int, field: str = "--frame") -> DepthFrame:
        """Depth frame ``frame`` as a user asked for it (negative counts from the end): a
        session without depth or an index outside it is a user error naming ``field``."""
        if self.has_depth and not -self.n_frames <= frame < self.n_frames:
            raise InputFileError(f"has no frame {frame} ({self.n_frames} frames)", file=self.path, field=field,
                                 expected=f"a frame index in 0..{self.n_frames - 1}")
        return self.depth_frame(frame)

    def histogram_frame(self, i: int) -> dict[str, np.ndarray]:
        """Frame ``i``'s direct-ToF datasets under ``histograms/`` (``counts`` [T, H, W], ...)."""
        if not self.has_histograms:
            raise InputFileError("has no histograms (not a direct-ToF session)", file=self.path,
                                 field="histograms/counts", expected="a session written from a direct_tof scene")
        i = self._index(i)
        g = self._file["histograms"]
        try:
            return {k: g[k][i] for k in g if isinstance(g[k], h5py.Dataset)}
        except (OSError, ValueError, TypeError) as exc:
            raise InputFileError(f"frame {i} cannot be read ({_os_reason(exc)})", file=self.path,
                                 field="histograms") from None

    def histogram_edges_s(self) -> np.ndarray:
        """The histogram's bin edges (s after the pulse's emission)."""
        T = self._file["histograms/counts"].shape[1]
        return self.t0_s + self.bin_width_s * np.arange(T + 1)

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
                             "has_histograms": self.has_histograms,
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


def open_session(path: str | Path, *, need_frames: bool = False) -> Session:
    """Open and validate a session file; errors name the file and the field.

    ``need_frames``: a command that works on frames (depth, compare, export, import) refuses a
    session holding none, with one line, instead of writing an empty result and succeeding."""
    s = Session(path)
    if need_frames and s.n_frames == 0:
        s.close()
        raise InputFileError("holds no complete frame", file=s.path, field="n_frames",
                             expected="a session with at least one frame")
    return s


def copy_session_header(src: Session, dst_path: str | Path, *, force: bool = False,
                        note: str | None = None, device_extra: dict[str, Any] | None = None) -> SessionWriter:
    """A new ``derived`` writer with the same camera, device and scene as ``src``;
    ``device_extra`` adds keys to the device header (e.g. the tap calibration applied)."""
    device = dict(src.device)
    if note:
        device["derived"] = note
    device.update(device_extra or {})
    return SessionWriter(dst_path, src.camera, device=device, scene_text=src.scene_text, force=force,
                         derived=True, sensor_config=src.sensor_config)


