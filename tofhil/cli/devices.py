"""CLI commands of the drivers: ``tofhil devices``, ``tofhil capture``, ``tofhil emulate``."""

from __future__ import annotations

import math
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import typer

from tofhil.cli import app, console, on_interrupt_signal, out, print_json, progress
from tofhil.cli import options as opt
from tofhil.errors import DeviceError

if TYPE_CHECKING:
    from tofhil.app.view import ViewSummary


def _parse_roi(text: str | None) -> tuple[int, int, int, int] | None:
    if text is None:
        return None
    try:
        x0, y0, x1, y1 = (int(v) for v in text.split(","))
    except ValueError:
        raise DeviceError(f"--roi {text!r}", field="--roi", expected="X0,Y0,X1,Y1 (four integers; X1, Y1 exclusive)") from None
    return x0, y0, x1, y1


def _sigterm_as_interrupt() -> None:
    """SIGTERM ends a capture like Ctrl-C: the session is closed with every frame saved.

    The same handler as Ctrl-C's: it also sets the flag the capture loop checks, since a
    KeyboardInterrupt raised inside h5py's ``__del__`` or a weakref callback is lost (a lost
    SIGTERM let a 100000-frame capture run on)."""
    signal.signal(signal.SIGTERM, on_interrupt_signal)


@app.command()
def devices(as_json: bool = typer.Option(False, "--json", help="Print JSON instead of a table.")) -> None:
    """List connected cameras and emulated devices (specs for --device)."""
    from tofhil.drivers.base import list_devices, registered_schemes

    entries = list_devices()
    if as_json:
        print_json([{"spec": e.spec, "kind": e.kind, "description": e.description} for e in entries])
        return
    for e in entries:
        out.print(f"{e.spec:28s} {e.kind:10s} {e.description}", highlight=False, markup=False)
    connected = [e for e in entries if e.kind == "connected" and not e.description.startswith("USB unavailable")]
    if not connected:
        out.print("(no camera connected)")
    out.print("schemes: " + ", ".join(sorted(registered_schemes())), highlight=False, markup=False)


@app.command()
def capture(device: str = typer.Option(..., "--device", help="emulator[:SCENE], usb, usb:BUS:ADDR, serial:PORT, ..."),
            frames: int = typer.Option(10, "--frames", parser=opt.count(1, 10_000_000),
                                       help="Number of good frames to write."),
            out_path: Path = typer.Option(..., "--out", parser=opt.new_file, help="Session file to write (.h5)."),
            integration_time_us: Optional[float] = typer.Option(None, "--integration-time-us",
                                                                parser=opt.finite(0.0, 1e6, lo_open=True, unit="us"),
                                                                help="Integration time in microseconds."),
            mod_freq_hz: Optional[float] = typer.Option(None, "--mod-freq-hz", parser=opt.finite(0.0, 1e10, lo_open=True,
                                                                                                unit="Hz"),
                                                        help="Modulation frequency in Hz."),
            mode: str = typer.Option("dcs", "--mode", help="dcs (raw taps) or distance (depth + amplitude)."),
            channel: Optional[int] = typer.Option(None, "--channel", parser=opt.count(0, 15),
                                                  help="Modulation channel (0..15)."),
            min_amplitude: Optional[float] = typer.Option(None, "--min-amplitude", parser=opt.finite(0.0, unit="DN"),
                                                          help="Minimum amplitude (DN)."),
            roi: Optional[str] = typer.Option(None, "--roi", help="X0,Y0,X1,Y1 sensor pixels, half-open (X1, Y1 exclusive; TOFcam635: multiples of 4)."),
            faults: Optional[str] = typer.Option(None, "--faults",
                                                 help="Emulator only: inject faults, e.g. crc@3,disconnect@6."),
            seed: Optional[int] = typer.Option(None, "--seed", parser=opt.count(0, 2**63 - 1, what="a seed"),
                                               help="Emulated devices only: the noise seed (default: a fresh one "
                                                    "per capture). Recorded in the session's device header as "
                                                    "emulator_seed, so a capture can be repeated exactly."),
            view: bool = typer.Option(False, "--view", help="Show the frames live in the Rerun viewer (spawned; "
                                      "pip install 'tofhil\\[view]'). The capture never waits on it: a slow "
                                      "viewer drops view frames, never camera frames."),
            save_view: Optional[Path] = typer.Option(None, "--save", parser=opt.new_file,
                                                     help="Write the view to this .rrd file (headless without "
                                                          "--view; with it, as well)."),
            scene: Optional[str] = typer.Option(None, "--scene", help="With --view/--save: the twin's scene (file "
                                                "or bundled name): its render and the live residual (measured - twin)."),
            view_rate: float = typer.Option(30.0, "--view-rate", parser=opt.finite(0.0, 1e4, unit="frames/s"),
                                            help="With --view/--save: at most this many view frames per second, "
                                                 "and no more than keep the view's thread under 5 % of the time "
                                                 "(0: every frame the viewer keeps up with). The session gets every frame."),
            force: bool = typer.Option(False, "--force", help="Overwrite OUT (and the --save file) if it exists.")) -> None:
    """Capture frames from a device into a session file (progress bar, summary at the end)."""
    from tofhil.drivers.base import CaptureSettings, create_driver
    from tofhil.drivers.capture import capture as run_capture

    live_scene = _check_view_options(view, save_view, scene, out_path, force)  # before the device is touched
    if mode not in ("dcs", "distance"):
        raise DeviceError(f"--mode {mode!r}", field="--mode", expected="dcs or distance")
    settings = CaptureSettings(mode=mode, mod_freq_hz=mod_freq_hz, channel=channel, min_amplitude=min_amplitude,
                               integration_time_s=None if integration_time_us is None else integration_time_us * 1e-6,
                               roi=_parse_roi(roi))
    driver = create_driver(device)
    scene_text = ""
    emulator = getattr(driver, "emulator", None)
    if faults:
        if emulator is None:
            raise DeviceError("faults can only be injected into the emulator", field="--faults",
                              expected="--device emulator[:SCENE]")
        from tofhil.drivers.tofcam635.faults import FaultPlan

        emulator.faults = FaultPlan.parse(faults)
    if emulator is not None:
        scene_text = emulator.source.scene_text()
    device_extra = _seed_emulated(driver, emulator, seed)
    _sigterm_as_interrupt()
    live = None
    ended_cleanly = False
    try:
        with driver:
            if view or save_view is not None:
                from tofhil.app.view import LiveView

                live = LiveView(save=save_view, spawn=view, scene=live_scene, name=out_path.name,
                                max_rate_hz=view_rate or None)
            ticks = iter(range(frames))
            bar = progress(ticks, frames, f"capturing {device}")  # the bar prints it literally
            offer = live.offer if live is not None else None

            def on_frame(frame: object) -> None:
                if offer is not None:
                    offer(frame)  # never waits: a full view queue drops the view frame
                next(bar, None)

            summary = run_capture(driver, out_path, frames, settings, force=force, scene_text=scene_text,
                                  on_frame=on_frame, device_extra=device_extra)
            if summary.frames_written == frames:
                next(bar, None)  # the bar advances on the next request: complete it
            bar.close()
        ended_cleanly = True  # (interrupted or device lost included: the session keeps its frames, the view too)
    finally:
        view_summary = live.close(keep=ended_cleanly) if live is not None else None
    out.print(f"frames written {summary.frames_written}/{summary.requested}, dropped {summary.dropped}, "
              f"reconnects {summary.reconnects}, {summary.frames_per_s:.1f} frames/s -> {summary.path}",
              highlight=False, markup=False)
    if view_summary is not None:
        _print_view_summary(view_summary)
    if summary.ended_early == "interrupted":
        kept = f"kept in {summary.path}" if summary.frames_written else "kept (no file written)"
        console.print(f"interrupted: {summary.frames_written} frames {kept}", highlight=False, markup=False, soft_wrap=True)
        sys.exit(130)
    if summary.end_of_recording:  # docs/importers.md: reading past the end ends a capture cleanly
        console.print(f"note: the recording ended after {summary.frames_written} of {summary.requested} frames",
                      highlight=False, markup=False, soft_wrap=True)
        return
    if summary.ended_early:
        console.print(f"session ended early: {summary.ended_early}", highlight=False, markup=False, soft_wrap=True)
        sys.exit(3)


def _seed_emulated(driver: object, emulator: object, seed: int | None) -> dict[str, int]:
    """Seed an emulated device's noise: ``seed``, or a fresh one, so that two captures of the
    same bench differ as two real captures do (they were bit-identical); returned as the
    device-header entry that records it."""
    host_scene = getattr(driver, "host_scene", None) if getattr(driver, "host", False) else None
    seeded = emulator if emulator is not None else (host_scene if hasattr(host_scene, "seed") else None)
    if seeded is None:
        if seed is not None:
            raise DeviceError("a noise seed only applies to an emulated device", field="--seed",
                              expected="--device emulator[:SCENE] or depthai-sim:SCENE")
        return {}
    import secrets

    import numpy as np

    seed = secrets.randbelow(2**63) if seed is None else seed
    if emulator is not None:
        emulator.rng = np.random.default_rng(seed)  # type: ignore[attr-defined]
    else:
        host_scene.seed = seed  # type: ignore[union-attr]
    return {"emulator_seed": seed}


def _check_view_options(view: bool, save: Path | None, scene: str | None, out_path: Path, force: bool) -> object:
    """The view's options, checked before the device is touched: the Rerun extra, the
    --save file, the twin's scene (returned loaded, or None)."""
    if scene is not None and not (view or save is not None):
        raise DeviceError("--scene is only used by the view", field="--scene", expected="--view or --save VIEW.rrd")
    if not (view or save is not None):
        return None
    from tofhil.app.view import check_display, check_view_output, require_rerun

    require_rerun(field="--view" if view else "--save")
    if view:
        check_display()
    if save is not None and save.resolve() == out_path.resolve():
        raise DeviceError("the view file must differ from the session", field="--save")
    check_view_output(save, force)
    if scene is None:
        return None
    from tofhil.sim.scene import load_scene

    return load_scene(scene)  # a malformed scene is one line now, not a note after the capture


def _print_view_summary(summary: "ViewSummary") -> None:
    """``view dropped N of M frames [-> FILE]`` on stdout; why the view stopped, on stderr."""
    out.print(summary.line(), highlight=False, markup=False, soft_wrap=True)  # one line, for scripts
    for note in summary.notes:
        console.print(f"view: {note}", highlight=False, markup=False, soft_wrap=True)
    if summary.error:
        console.print(f"view stopped: {summary.error} (the capture was not affected)",
                      highlight=False, markup=False, soft_wrap=True)


@app.command()
def emulate(scene: Optional[str] = typer.Option(None, "--scene", help="Scene file/name, or wall:METRES "
                                                "(default: bundled bench_demo, else a wall at 1 m)."),
            pty: bool = typer.Option(False, "--pty", help="Serve on a pseudo-terminal (prints PORT=... first)."),
            faults: Optional[str] = typer.Option(None, "--faults", help="Inject faults, e.g. crc@3,timeout=0.05."),
            seed: Optional[int] = typer.Option(None, "--seed", parser=opt.count(0, 2**63 - 1, what="a seed"),
                                               help="Noise seed (default: a fresh one, printed)."),
            frame_rate: Optional[float] = typer.Option(None, "--frame-rate", parser=opt.finite(0.0, 1e4, lo_open=True, unit="frames/s"),
                                                       help="Limit frames/s (> 0; default: as fast as possible).")) -> None:
    """Run the TOFcam635 emulator until stopped (Ctrl-C or SIGTERM)."""
    from tofhil.drivers.tofcam635.emulator import Epc635Emulator
    from tofhil.drivers.tofcam635.faults import FaultPlan
    from tofhil.sim.sources import source_from_spec
    from tofhil.drivers.tofcam635.pty import PtyServer

    if frame_rate is not None and not (math.isfinite(frame_rate) and frame_rate > 0):
        raise DeviceError(f"--frame-rate {frame_rate:g}", field="--frame-rate",
                          expected="a finite number of frames per second > 0 (omit it for as fast as possible)")
    if not pty:
        raise DeviceError("only the pseudo-terminal transport can be served from the command line",
                          field="--pty", expected="--pty (in-process use: --device emulator)")
    if seed is None:  # fresh noise per run, as a real camera's; the seed is printed to repeat it
        import secrets

        seed = secrets.randbelow(2**63)
    emulator = Epc635Emulator(source_from_spec(scene), faults=FaultPlan.parse(faults) if faults else None,
                              seed=seed, frame_interval_s=1.0 / frame_rate if frame_rate else 0.0)
    # Render both modulation frequencies now (a scene render takes seconds), so that no client
    # request waits for one: the vendor client gives up after 0.2 s.
    from tofhil.drivers.tofcam635 import protocol as P
    from tofhil.drivers.tofcam635.profile import canonical_phases

    for freq in P.MOD_FREQ_CODES.values():
        emulator.source.taps(freq, 125e-6, canonical_phases(emulator.profile))
    _sigterm_as_interrupt()
    server = PtyServer(emulator).start()
    print(f"PORT={server.port}", flush=True)
    console.print(f"emulating TOFcam635 ({emulator.source.description}) on {server.port}, noise seed {seed}; "
                  "Ctrl-C to stop",
                  highlight=False, markup=False)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
    if server.error is not None:
        raise DeviceError(f"pty server failed: {server.error}", field="--pty")
