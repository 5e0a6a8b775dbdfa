"""The view: a session's or a live capture's frames in the Rerun viewer, or in an ``.rrd`` file.

Per frame (timeline ``frame`` = the session's frame index, ``device_time`` = the device's
clock in seconds, and Rerun's own ``log_time``): the radial distance (``depth``, a depth image
in metres, 0 where there is no measurement), the amplitude (``amplitude``), the point cloud
unprojected with the camera's own lens model (``world/points``: ``tofhil.camera``, so a
fisheye or rational lens is exact; the viewer's pinhole at ``world/camera`` only draws the
frustum), and with a scene the twin's noise-free render (``twin/depth``, ``twin/amplitude``,
``world/twin_points``, static: the twin is rendered once) and the residual against it
(``residual/depth``: measured - twin in metres, NaN where either has no measurement;
``residual/depth_color``: the same on a fixed blue-white-red scale; ``residual/median_mm``,
``residual/rmse_mm``). Raw taps are demodulated by the core (``tofhil.depth``) as
``tofhil depth`` does.

``tofhil view`` replays a session synchronously (every frame is logged). ``tofhil capture
--view`` hands frames to :class:`LiveView`, which logs them on its own thread through a
:class:`~tofhil.app.view_sink.DroppingSink`: the capture loop never waits on the viewer, a slow
or closed viewer drops view frames, and the session gets every frame.

The Rerun SDK is an optional extra (``pip install 'tofhil[view]'``), imported only here and
only when a view is opened (:func:`require_rerun`).
"""

from __future__ import annotations

import math
import os
import sys
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tofhil.app.twin_render import TwinRender, residual_m, twin_frame, twin_frame_for_frame, twin_frame_for_session
from tofhil.app.view_sink import DroppingSink
from tofhil.camera import CameraModel
from tofhil.errors import TofhilError
from tofhil.frames import DepthFrame, RawFrame
from tofhil.progress import Progress, no_progress

#: The install line every "Rerun missing" message gives.
VIEW_EXTRA = "pip install 'tofhil[view]'"
#: The oldest Rerun SDK whose API this module follows (``set_time(..., sequence=)``, ``RrdReader``).
MIN_RERUN = (0, 41)

#: The live view's default cap on frames per second (a viewer shows no more).
DEFAULT_VIEW_RATE_HZ = 30.0
#: The share of the wall time the live view's own thread may spend on frames (the capture's
#: process shares its CPU and the GIL with it): the budget that sets the view rate below the cap.
DEFAULT_VIEW_CPU_SHARE = 0.05

#: Entity paths (read back by tests and by anyone scripting against an .rrd).
DEPTH = "depth"
AMPLITUDE = "amplitude"
POINTS = "world/points"
CAMERA = "world/camera"
TWIN_DEPTH = "twin/depth"
TWIN_AMPLITUDE = "twin/amplitude"
TWIN_POINTS = "world/twin_points"
RESIDUAL = "residual/depth"
RESIDUAL_COLOR = "residual/depth_color"
RESIDUAL_MEDIAN = "residual/median_mm"
RESIDUAL_RMSE = "residual/rmse_mm"
INFO = "info"


def require_rerun(field: str | None = None) -> Any:
    """The ``rerun`` module, or one :class:`TofhilError` naming the extra to install."""
    try:
        import rerun
    except ImportError:
        raise TofhilError("the view needs the Rerun SDK (rerun-sdk), which is not installed", field=field,
                          expected=VIEW_EXTRA) from None
    try:
        version = tuple(int(p) for p in str(rerun.__version__).split(".")[:2])
    except (AttributeError, ValueError):
        version = MIN_RERUN  # a development build: trust it
    if version < MIN_RERUN:
        raise TofhilError(f"the view needs rerun-sdk >= {'.'.join(map(str, MIN_RERUN))}, found {rerun.__version__}",
                          field=field, expected=f"{VIEW_EXTRA} --upgrade")
    return rerun


def check_display(field: str | None = "--view") -> None:
    """Refuse to spawn the viewer where it cannot open a window (Linux without X11 or
    Wayland: the viewer exits and every frame would go nowhere); ``--save`` works there."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise TofhilError("no display for the Rerun viewer (DISPLAY and WAYLAND_DISPLAY are not set)", field=field,
                          expected="a desktop session, or --save VIEW.rrd to write the view to a file and open "
                                   "it elsewhere with `rerun VIEW.rrd`")


def check_view_output(path: Path | None, force: bool, field: str = "--save") -> None:
    """Refuse a ``--save`` target before anything runs: not ``.rrd``, existing without
    ``force``, a directory, or in a missing directory (``tofhil.outputs``)."""
    if path is None:
        return
    from tofhil.outputs import check_new_path, refuse_existing

    if path.suffix.lower() != ".rrd":
        raise TofhilError("is not a .rrd file", file=path, field=field, expected="an output name ending in .rrd")
    if path.is_file():
        refuse_existing(path, force, field=field)  # a view is derived data: the plain refusal
    check_new_path(path, True)  # never a directory, a device, a missing directory


def _residual_colors(res: np.ndarray, limit_m: float) -> np.ndarray:
    """Blue (nearer than the twin) - white - red (farther) on +-``limit_m``; black without a residual."""
    t = np.clip(np.nan_to_num(res, nan=0.0) / limit_m, -1.0, 1.0)
    up, down = np.clip(t, 0.0, 1.0), np.clip(-t, 0.0, 1.0)
    rgb = np.stack([1.0 - down, 1.0 - up - down, 1.0 - up], axis=-1)  # white at 0, red at +1, blue at -1
    rgb = (rgb * 255.0 + 0.5).astype(np.uint8)
    rgb[~np.isfinite(res)] = 0
    return rgb


def _scale_step(value_m: float) -> float:
    """``value_m`` rounded up to 1, 2 or 5 x 10^n (a colour scale users can read), >= 5 mm."""
    v = max(float(value_m), 5e-3)
    e = 10.0 ** math.floor(math.log10(v))
    return next(m * e for m in (1.0, 2.0, 5.0, 10.0) if m * e >= v * (1 - 1e-9))


def _grey(amplitude: np.ndarray | None) -> np.ndarray | None:
    """Point colours from amplitude: grey scaled to its 99.5th percentile (as the camera's
    clouds), packed as Rerun's 0xRRGGBBAA (a third of the cost of an RGB array)."""
    if amplitude is None or amplitude.size == 0:
        return None
    a = np.nan_to_num(np.asarray(amplitude, dtype=np.float32), nan=0.0)
    k = int(0.995 * (a.size - 1))
    top = float(np.partition(a, k)[k])  # (the percentile without a full sort)
    g = (np.clip(a / (top if top > 0 else 1.0), 0.0, 1.0) * 255.0).astype(np.uint32)
    return (g << 24) | (g << 16) | (g << 8) | np.uint32(255)


class RerunView:
    """One Rerun recording: frames logged to a spawned viewer and/or an ``.rrd`` file.

    The file is written under a hidden temporary name beside ``save`` and renamed onto it by
    :meth:`close` (``keep=True``), or removed (``keep=False``), so that no half file is left
    under the real name. Log from one thread (Rerun's time cursor is per thread)."""

    def __init__(self, *, save: Path | None = None, spawn: bool = False, name: str = "tofhil") -> None:
        if save is None and not spawn:
            raise ValueError("a view needs a viewer to spawn or a file to save")
        self.rr = rr = require_rerun()
        from tofhil.outputs import partial_path

        self.save = None if save is None else Path(save)
        self._tmp = None if self.save is None else partial_path(self.save)
        self.rec = rr.RecordingStream("tofhil", recording_id=str(uuid.uuid4()))
        sinks = []
        if spawn:
            try:
                rr.spawn(connect=False, recording=self.rec)  # the viewer process; frames go to it over gRPC
            except Exception as exc:  # no viewer executable, a port in use, ...
                raise TofhilError(f"the Rerun viewer could not be started ({type(exc).__name__}: {exc})",
                                  field="--view", expected="the viewer of rerun-sdk, or --save VIEW.rrd") from None
            sinks.append(rr.GrpcSink())
        if self._tmp is not None:
            sinks.append(rr.FileSink(str(self._tmp)))
        self.rec.set_sinks(*sinks)
        self.rec.send_recording_name(name)
        self.twin: TwinRender | None = None
        self.frames_logged = 0
        self._camera: CameraModel | None = None
        self._rays: np.ndarray | None = None   # the camera's unit rays [H, W, 3] as float32 (points per frame)
        self._residual_limit_m: float | None = None
        self._info: dict[str, str] = {}
        self._closed = False

    # ------------------------------------------------------------------ static parts
    def _log_camera(self, camera: CameraModel) -> CameraModel:
        """Log the camera once (again if it changes); return the one whose rays are cached."""
        if self._camera is not None and camera == self._camera:
            return self._camera
        rr = self.rr
        self._camera = camera
        self._rays = camera.rays.astype(np.float32)
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)  # the camera's frame is the world: x right, y down, z forward
        self.rec.log(CAMERA, rr.Pinhole(focal_length=[camera.fx, camera.fy], principal_point=[camera.cx, camera.cy],
                                        width=camera.width, height=camera.height, image_plane_distance=0.3),
                     static=True)
        # what does not change once, not per frame (a frame logs its pixels and points alone)
        self.rec.log(DEPTH, rr.DepthImage.from_fields(meter=1.0, colormap="turbo"), static=True)
        self.rec.log(POINTS, rr.Points3D.from_fields(radii=0.002), static=True)
        self.note("camera", camera.to_json())
        return camera

    def note(self, key: str, text: str) -> None:
        """A line of the static ``info`` document (camera, twin, session)."""
        self._info[key] = text
        body = "\n".join(f"- **{k}**: {v}" for k, v in self._info.items())
        self.rec.log(INFO, self.rr.TextDocument(body, media_type="text/markdown"), static=True)

    def set_twin(self, twin: TwinRender) -> None:
        """Log the twin's render (static: it is rendered once) and compare every later frame with it."""
        rr = self.rr
        self.twin = twin
        t = twin.depth
        cam = self._log_camera(t.camera)
        ok = cam.valid_mask(t.radial_m, t.valid)
        self.rec.log(TWIN_DEPTH, rr.DepthImage(np.where(ok, t.radial_m, 0.0).astype(np.float32), meter=1.0,
                                               colormap="turbo"), static=True)
        if t.amplitude is not None:
            self.rec.log(TWIN_AMPLITUDE, rr.Image(np.asarray(t.amplitude, dtype=np.float32)), static=True)
        assert self._rays is not None
        pts = self._rays[ok] * t.radial_m[ok].astype(np.float32)[:, None]
        self.rec.log(TWIN_POINTS, rr.Points3D(pts, colors=[255, 140, 0], radii=0.002), static=True)
        self.note("twin", f"{twin.scene}: {twin.note}")

    # ------------------------------------------------------------------ frames
    def log_frame(self, index: int, raw: RawFrame | None = None, depth: DepthFrame | None = None) -> None:
        """Log frame ``index`` (a session's frame number): depth (demodulated from ``raw`` when
        no depth is given), amplitude, the cloud, and the residual against the twin."""
        if depth is None:
            if raw is None:
                raise ValueError("a frame needs raw taps or depth")
            from tofhil.depth import depth_from_raw

            depth = depth_from_raw(raw)
        rr, rec = self.rr, self.rec
        cam = self._log_camera(depth.camera)
        rec.set_time("frame", sequence=int(index))
        if math.isfinite(depth.timestamp_s):
            rec.set_time("device_time", duration=float(depth.timestamp_s))
        radial = np.asarray(depth.radial_m)
        ok = cam.valid_mask(radial, depth.valid)
        radial32 = np.where(ok, radial, 0.0).astype(np.float32)  # 0: Rerun's "no measurement"
        rec.log(DEPTH, rr.DepthImage(radial32))
        if depth.amplitude is not None:
            rec.log(AMPLITUDE, rr.Image(np.asarray(depth.amplitude, dtype=np.float32)))
        assert self._rays is not None
        pts = self._rays[ok] * radial32[ok][:, None]  # the camera's own lens model (tofhil.camera rays)
        amp = None if depth.amplitude is None else np.asarray(depth.amplitude)[ok]
        rec.log(POINTS, rr.Points3D(pts, colors=_grey(amp)))
        if self.twin is not None:
            self._log_residual(depth)
        self.frames_logged += 1

    def _log_residual(self, depth: DepthFrame) -> None:
        rr, rec = self.rr, self.rec
        assert self.twin is not None
        res = residual_m(depth, self.twin.depth)
        finite = res[np.isfinite(res)]
        if self._residual_limit_m is None and finite.size:
            # one scale for the whole session (colours comparable over time): the first frame's 99th percentile
            self._residual_limit_m = _scale_step(float(np.percentile(np.abs(finite), 99)))
            self.note("residual", f"measured - twin radial distance; colours: blue nearer, red farther than the twin, "
                                  f"+-{self._residual_limit_m * 1e3:g} mm")
        rec.log(RESIDUAL, rr.Image(res))
        rec.log(RESIDUAL_COLOR, rr.Image(_residual_colors(res, self._residual_limit_m or 0.05)))
        if finite.size:
            rec.log(RESIDUAL_MEDIAN, rr.Scalars(float(np.median(finite)) * 1e3))
            rec.log(RESIDUAL_RMSE, rr.Scalars(float(np.sqrt(np.mean(finite.astype(np.float64) ** 2))) * 1e3))

    # ------------------------------------------------------------------ end
    def close(self, keep: bool = True, timeout_s: float = 10.0) -> str | None:
        """Flush and end the recording; the file is renamed onto ``save`` (``keep``) or removed.
        Returns an error text when flushing failed (e.g. a viewer that went away), else None."""
        if self._closed:
            return None
        self._closed = True
        from tofhil.outputs import remove_partial

        problem = None
        try:
            self.rec.flush(timeout_sec=timeout_s)
        except Exception as exc:  # a closed viewer: the gRPC sink cannot deliver; the file sink still can
            problem = f"{type(exc).__name__}: {exc}"
        try:
            self.rec.disconnect()  # ends the sinks: the file gets its footer
        except Exception as exc:
            problem = problem or f"{type(exc).__name__}: {exc}"
        if self._tmp is not None and self.save is not None:
            if keep and self._tmp.is_file():
                os.replace(self._tmp, self.save)
            else:
                remove_partial(self._tmp)
        return problem


# ---------------------------------------------------------------------- replay a session
def view_session(session_path: str | Path, *, scene: Any = None, save: Path | None = None, spawn: bool = False,
                 progress: Progress = no_progress) -> "ViewSummary":
    """Log every frame of a session (and with ``scene`` the twin's render of it and the
    residual); an ``.rrd`` is left only when every frame was logged."""
    from tofhil.session import open_session

    session_path = Path(session_path)
    with open_session(session_path) as s:
        n = s.n_frames
        use_depth = s.has_depth
        if not use_depth and not s.has_raw:
            raise TofhilError("has neither depth nor raw taps to show", file=session_path, field="depth/radial_m")
    twin = None if scene is None else twin_frame_for_session(scene, session_path)  # before the file exists
    view = RerunView(save=save, spawn=spawn, name=session_path.name)
    ok = False
    try:
        view.note("session", f"{session_path.name} ({n} frames)")
        if twin is not None:
            view.set_twin(twin)
        with open_session(session_path) as s:
            for i in progress(range(n), n, f"viewing {session_path.name}"):
                if use_depth:
                    view.log_frame(i, depth=s.depth_frame(i))
                else:
                    view.log_frame(i, raw=s.raw_frame(i))
        ok = True
    finally:
        problem = view.close(keep=ok)
    return ViewSummary(offered=n, shown=view.frames_logged, saved=save if ok else None,
                       twin=None if twin is None else f"{twin.scene}: {twin.note}", error=problem)


# ---------------------------------------------------------------------- the live view of a capture
@dataclass
class ViewSummary:
    """What a view showed: frames offered, logged, dropped, the file written, notes."""

    offered: int
    shown: int
    saved: Path | None = None
    twin: str | None = None
    #: Why the view stopped or could not flush (the capture is not affected), else None.
    error: str | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def dropped(self) -> int:
        return self.offered - self.shown

    def line(self) -> str:
        """``view dropped N of M frames`` and where it went."""
        where = f" -> {self.saved}" if self.saved is not None else ""
        return f"view dropped {self.dropped} of {self.offered} frames{where}"


def _warm_up(rr: Any, scene: Any = None) -> None:
    """Run once, before the capture, what costs most the first time: Rerun's archetype
    conversions (~0.4 s), the demodulation kernels' load from numba's cache (~0.5 s) and with
    a scene the renderer's (a render of a few pixels). All of it holds the GIL; on the viewer
    thread it would slow the capture loop at its start (the twin's real render there runs in
    the renderer's GIL-free kernels)."""
    from tofhil.depth import depth_from_raw

    if scene is not None:
        cam = scene.camera
        twin_frame(scene, camera=cam.scaled(min(1.0, 8.0 / max(cam.width, cam.height))))

    cam = CameraModel(width=2, height=2, fx=2.0, fy=2.0, cx=0.5, cy=0.5)
    theta = np.arange(4) * (np.pi / 2)
    for freqs in ((20e6,), (10e6, 20e6)):  # the one-frequency kernel and the general one
        taps = np.ones((len(freqs), 4, 2, 2), np.float32)
        depth_from_raw(RawFrame(taps=taps, freq_hz=np.array(freqs), theta_rad=theta, integration_time_s=1e-3, camera=cam))
    z = np.zeros((2, 2), np.float32)
    rr.DepthImage(z), rr.Image(z), rr.Image(np.zeros((2, 2, 3), np.uint8)), rr.Scalars(0.0)
    rr.Points3D(np.zeros((2, 3), np.float32), colors=np.zeros(2, np.uint32), radii=0.002)


class LiveView:
    """The view of a running capture: :meth:`offer` is the capture's frame observer (it never
    waits), the frames are logged on the sink's thread; with ``scene`` the twin is rendered
    there once, for the first frame's camera and acquisition settings (frames that arrive
    meanwhile are dropped from the view, not from the session).

    How many frames the view takes: at most ``max_rate_hz`` per second (default 30: a viewer
    shows no more), and no more than keep the viewer thread's own CPU time under
    ``cpu_share`` of the wall time (default 5 %; the SDK's threads that encode and write the
    recording take about as much again): every view frame costs the capture's process CPU,
    and the budget follows the frame size and the machine instead of a fixed rate.
    ``max_rate_hz=None`` takes every frame the viewer keeps up with (no cap, no budget). A
    frame that comes sooner, or finds the queue full, is dropped from the view."""

    def __init__(self, *, save: Path | None = None, spawn: bool = False, scene: Any = None, name: str = "capture",
                 maxsize: int = 2, max_rate_hz: float | None = DEFAULT_VIEW_RATE_HZ,
                 cpu_share: float = DEFAULT_VIEW_CPU_SHARE) -> None:
        if max_rate_hz is not None and not (math.isfinite(max_rate_hz) and max_rate_hz > 0):
            raise TofhilError(f"{max_rate_hz:g}", field="--view-rate", expected="a finite number of frames/s > 0")
        _warm_up(require_rerun(), scene)  # before the file exists: a scene that fails to render leaves nothing
        self.view = RerunView(save=save, spawn=spawn, name=name)
        self.scene = scene
        self.notes: list[str] = []
        self._index = 0
        self._period_s = 0.0 if max_rate_hz is None else 1.0 / max_rate_hz
        self._share = None if max_rate_hz is None else float(cpu_share)
        self._interval_s = self._period_s  # written by the viewer thread (the CPU budget), read by offer()
        self._cost_s: float | None = None  # the viewer thread's CPU time per frame (moving average)
        self._last_s = -math.inf
        self._rate_dropped = 0
        self._twin_tried = scene is None
        self._sink: DroppingSink[tuple[int, RawFrame | None, DepthFrame | None]] = DroppingSink(self._show, maxsize=maxsize)

    def offer(self, frame: Any) -> None:
        """Hand a capture frame (``tofhil.drivers.base.Frame``, or a RawFrame / DepthFrame) to
        the viewer without waiting: it keeps its session index; dropped if it comes sooner than
        the view rate allows or the viewer is behind."""
        index = self._index
        self._index += 1
        now = time.monotonic()
        if now - self._last_s < self._interval_s:
            self._rate_dropped += 1
            return
        raw = frame if isinstance(frame, RawFrame) else getattr(frame, "raw", None)
        depth = frame if isinstance(frame, DepthFrame) else getattr(frame, "depth", None)
        if self._sink.offer((index, raw, depth)):
            self._last_s = now

    def _show(self, item: tuple[int, RawFrame | None, DepthFrame | None]) -> None:
        index, raw, depth = item
        if not self._twin_tried:
            self._twin_tried = True
            try:
                self.view.set_twin(twin_frame_for_frame(self.scene, raw if raw is not None else depth))
            except Exception as exc:  # the view goes on without the twin; the capture never notices
                self.notes.append(f"twin not shown: {type(exc).__name__}: {exc}")
        t0 = time.thread_time()
        self.view.log_frame(index, raw=raw, depth=depth)
        if self._share is not None:
            cost = time.thread_time() - t0
            self._cost_s = cost if self._cost_s is None else 0.8 * self._cost_s + 0.2 * cost
            self._interval_s = max(self._period_s, self._cost_s / self._share)

    def close(self, keep: bool = True, timeout_s: float = 30.0) -> ViewSummary:
        """Let the viewer log what is queued, end the recording (the file renamed onto its name
        when ``keep``), and say how many frames the view dropped."""
        stats = self._sink.close(timeout_s)
        problem = stats.error
        if stats.timed_out:
            problem = problem or f"the viewer did not finish within {timeout_s:g} s"
            keep = False  # it may still be writing: no file under the real name
        flush_problem = self.view.close(keep=keep, timeout_s=3.0)  # a viewer that went away: do not wait long
        saved = self.view.save if keep and self.view.save is not None and self.view.save.is_file() else None
        twin = self.view.twin
        notes = list(self.notes)
        if self._rate_dropped or stats.dropped:
            rate = "" if self._share is None else (
                f" (at most {1.0 / self._period_s:g}/s, and {self._share:.0%} of the time: "
                f"{1.0 / max(self._interval_s, 1e-9):.0f}/s at the end)")
            notes.append(f"{self._rate_dropped} frame(s) above the view rate{rate}, "
                         f"{stats.dropped} while the viewer was busy")
        return ViewSummary(offered=self._index, shown=stats.consumed, saved=saved,
                           twin=None if twin is None else f"{twin.scene}: {twin.note}",
                           error=problem or flush_problem, notes=notes)


# ---------------------------------------------------------------------- a diagnosis's maps
def _map_is_depth(name: str) -> bool:
    return name.startswith(("depth_", "signature_depth_"))


def log_diagnosis_maps(maps: dict[str, np.ndarray], save: Path, *, verdict: str = "") -> list[str]:
    """Each map of a diagnosis (residuals before and after, signatures, what is left above noise,
    the defects) as an image under ``diagnosis/<name>`` in an ``.rrd``: the float values as they
    are (``diagnosis/<name>/values``, NaN where a pixel has none) and, for the depth maps
    (metres), blue - white - red on the 99th percentile of their size. Returns the entities."""
    view = RerunView(save=save, spawn=False, name="diagnosis")
    rr, logged = view.rr, []
    try:
        if verdict:
            view.note("verdict", verdict)
        for name, m in sorted(maps.items()):
            a = np.asarray(m, dtype=np.float32)
            if a.ndim != 2:
                continue
            view.rec.log(f"diagnosis/{name}/values", rr.Image(a), static=True)
            logged.append(f"diagnosis/{name}/values")
            if _map_is_depth(name) and np.isfinite(a).any():
                limit = float(np.nanpercentile(np.abs(a), 99)) or 1e-3
                view.rec.log(f"diagnosis/{name}/colour", rr.Image(_residual_colors(a.astype(np.float64), limit)),
                             static=True)
                logged.append(f"diagnosis/{name}/colour")
    except BaseException:
        view.close(keep=False)
        raise
    problem = view.close(keep=True)
    if problem:
        raise TofhilError(f"the view file could not be written ({problem})", file=save, field="--view-save")
    return logged
