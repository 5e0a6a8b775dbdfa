"""Memory a render + sensor simulation needs, estimated before it starts, and the refusal
when the machine does not have it.

A camera of 8000 x 8000 pixels would otherwise allocate several GiB of ray and accumulator
arrays before anything fails, and 20000 x 20000 takes the machine down. The estimate counts
the arrays the renderer (:mod:`tofhil.sim.render`) and the sensor model
(:mod:`tofhil.sim.sensor`) allocate, per pixel ``N = H W``:

- the view: pixel rays and their world directions, pixel areas and weights (float64, with
  the temporaries of the undistortion): :data:`VIEW_BYTES_PER_PIXEL`;
- the accumulators: real and imaginary parts for direct and indirect light per rendered
  frequency x harmonic (``32 nk`` bytes), the complex phasors of the result (direct,
  indirect and their sum, ``16 nk`` each), power/ambient/distance/object maps, the
  transient histogram (8 bytes per bin, twice: accumulator and result);
- the chunk workers' buffers (bounded by the chunk size, independent of ``N``);
- the sensor, per frame: the optical signal (``16 F NH``), the fixed pattern (``16 K``),
  expected electrons, shot and read noise and the ADC (about six float64 ``[F, K]`` arrays
  alive at once) and the depth of the frame;
- the frames kept in memory (float32 taps) when the caller keeps them all;
- the scene's geometry, per triangle: its float64 tables (:class:`tofhil.sim.geometry.Geometry`)
  and one Embree BVH for each Embree scene built from the triangles -- two when the
  compiled kernels' own scene (:mod:`tofhil.sim.embree4`) sits next to embreex's
  (:data:`BVH_BYTES_PER_TRIANGLE` each, vertex and index buffers and the build's primitive
  references included).

``tests/sim/test_memory.py`` checks the estimate against a measured peak.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Mapping

from tofhil.errors import TofhilError

#: Per-pixel bytes of the view arrays a render keeps (float64 pixel rays, their world
#: directions and a float32 copy, pixel areas, cos^4 and pixel weights).
VIEW_BYTES_PER_PIXEL = 110
#: Per-pixel bytes of the render's maps (power, ambient, radial distance, object id).
MAPS_BYTES_PER_PIXEL = 44
#: Samples per render chunk (tofhil.sim.geometry.BATCH); bytes of a running chunk's buffers
#: per sample, and more per indirect bounce.
CHUNK_SAMPLES = 1 << 16
CHUNK_BYTES_PER_SAMPLE = 400
CHUNK_BYTES_PER_SAMPLE_BOUNCE = 200
#: Bytes per triangle of one Embree BVH as built for a robust triangle scene: the leaf
#: triangles (Triangle4v, 3 float32 vertices each), the nodes, the vertex and index buffers
#: and the builder's primitive references (32 B each), rounded up.
BVH_BYTES_PER_TRIANGLE = 200
#: Bytes per triangle of the float64 tables the renderer keeps (first vertex, normal, plane
#: offset, vertex normals, object index).
GEOMETRY_BYTES_PER_TRIANGLE = 140
#: Refuse a job needing more than this fraction of the memory available now.
AVAILABLE_FRACTION = 0.7

#: A ceiling the user set (``--max-memory``; None: none): a job estimated above it is refused
#: before it starts, whatever the machine has (a cluster slot's share, a laptop kept usable).
_USER_LIMIT: dict[str, int | None] = {"bytes": None}


def set_memory_limit(limit_bytes: int | None) -> None:
    """Set (or clear, with None) the user's ceiling :func:`check_memory` applies."""
    _USER_LIMIT["bytes"] = None if limit_bytes is None else int(limit_bytes)


@dataclass(frozen=True)
class MemoryEstimate:
    """Bytes a job needs at its peak, and the parts of the estimate."""

    render_bytes: int
    sensor_bytes: int
    frames_bytes: int

    @property
    def total_bytes(self) -> int:
        # The sensor runs after the render's accumulators are freed, on the render's result.
        return max(self.render_bytes, self.sensor_bytes) + self.frames_bytes


def estimate_bytes(*, width: int, height: int, render_freqs: int, harmonics: int, sensor_freqs: int, taps: int,
                   samples_per_pixel: int = 1, bounces: int = 0, separate_direct: bool = False,
                   transient_bins: int = 0, kept_frames: int = 0, signal_effects: bool = False,
                   threads: int = 2, triangles: int = 0, bvhs: int = 2) -> MemoryEstimate:
    """The estimate (see the module docstring) from the job's sizes; ``bvhs`` is the number
    of Embree scenes built from the ``triangles``."""
    n = int(width) * int(height)
    spp = max(int(samples_per_pixel), 1)
    nk = int(render_freqs) * int(harmonics)
    # Complex result arrays: the total always; direct and indirect when kept separately or
    # when indirect light is traced (total = direct + indirect is then a third array).
    n_complex = 3 if (separate_direct or bounces > 0) else 1
    # Chunks as the renderer cuts them: an even number of at most CHUNK_SAMPLES samples each,
    # ``threads`` of them running at once.
    n_chunks = 2 * -(-n * spp // (2 * CHUNK_SAMPLES))
    chunk_pixels = -(-n // n_chunks)
    running = min(threads, n_chunks)
    chunks = running * chunk_pixels * (spp * (CHUNK_BYTES_PER_SAMPLE + CHUNK_BYTES_PER_SAMPLE_BOUNCE * bounces)
                                       + 32 * nk + 8 * transient_bins)
    geometry = int(triangles) * (GEOMETRY_BYTES_PER_TRIANGLE + int(bvhs) * BVH_BYTES_PER_TRIANGLE)
    fixed = n * (VIEW_BYTES_PER_PIXEL + MAPS_BYTES_PER_PIXEL) + geometry
    # While tracing: accumulators and chunk buffers; at the end: accumulators and results.
    tracing = fixed + n * (32 * nk + 8 * transient_bins) + chunks
    finishing = fixed + n * (32 * nk + 16 * nk * n_complex + 16 * transient_bins)
    render = max(tracing, finishing)
    kept = fixed + n * (16 * nk * n_complex + 8 * transient_bins)
    fk = int(sensor_freqs) * int(taps)
    # Optical signal (copied by signal-stage effects), fixed pattern, about four float64
    # [F, K] arrays alive at once in the noise and ADC chain, the float32 taps, the depth.
    signal = n * 16 * int(sensor_freqs) * int(harmonics) * (3 if signal_effects else 1)
    sensor = kept + signal + n * (16 * taps + 32 * fk + 4 * fk + 40 * sensor_freqs)
    frames = int(kept_frames) * n * 4 * fk
    return MemoryEstimate(int(render), int(sensor), int(frames))


def available_bytes() -> int | None:
    """``MemAvailable`` from /proc/meminfo (bytes), or None where it cannot be read."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def _gib(b: float) -> str:
    """A size as people read it: GiB from 1 GiB up, MiB below (a 10 MB render is not 0.01 GiB)."""
    return f"{b / 2 ** 30:.2f} GiB" if b >= 2 ** 30 else f"{b / 2 ** 20:.1f} MiB"


def check_memory(estimate: MemoryEstimate, *, what: str = "the render", field: str = "camera",
                 source: str | None = None, available: int | None = None) -> None:
    """Refuse (a :class:`TofhilError` naming the scene and the camera) when the estimate
    exceeds the user's ceiling (:func:`set_memory_limit`) or :data:`AVAILABLE_FRACTION` of the
    memory available. ``TOFHIL_MEMORY_LIMIT_BYTES`` in the environment replaces the available
    memory (for tests and batch systems)."""
    ceiling = _USER_LIMIT["bytes"]
    if ceiling is not None and estimate.total_bytes > ceiling:
        raise TofhilError(f"{what} needs about {_gib(estimate.total_bytes)} of memory, above --max-memory "
                          f"{_gib(ceiling)}", file=source, field=field,
                          expected="a higher --max-memory, or a smaller camera, fewer frequencies, harmonics, "
                                   "transient bins or frames")
    env = os.environ.get("TOFHIL_MEMORY_LIMIT_BYTES")
    if available is None and env:
        try:
            available = int(float(env))
        except ValueError:
            available = None
    if available is None:
        available = available_bytes()
    if available is None:
        return
    need = estimate.total_bytes
    allowed = AVAILABLE_FRACTION * available
    if need > allowed:
        raise TofhilError(f"{what} needs about {_gib(need)} of memory; {_gib(available)} is available "
                          f"(at most {AVAILABLE_FRACTION:.0%} of it is used)", file=source, field=field,
                          expected="a smaller camera (width x height), fewer frequencies, harmonics, "
                                   "transient bins or frames")


def scene_triangles(scene: Any) -> int:
    """Triangles the scene's objects are built from (:func:`tofhil.sim.geometry.object_mesh`),
    counted without building them."""
    total = 0
    for obj in scene.objects:
        if obj.type in ("plane", "board"):
            total += 2
        elif obj.type == "box":
            total += 12
        elif obj.type == "sphere":
            total += 20 * 4 ** int(obj.params["subdivisions"])   # icosphere
        elif obj.type == "cylinder":
            total += 4 * int(obj.params["sections"])              # side quads and two fans
        else:
            total += len(getattr(obj.mesh, "faces", ()))
    return total


def bvh_count() -> int:
    """Embree scenes a geometry holds: embreex's, and the compiled kernels' own when that
    binding loads (:attr:`tofhil.sim.geometry.Geometry.direct`)."""
    from tofhil.sim import embree4

    return 2 if embree4.library() is not None else 1


def render_memory(scene: Any, render_kwargs: Mapping[str, Any], *, frames_kept: int = 0,
                  signal_effects: bool = False) -> MemoryEstimate:
    """The estimate for rendering ``scene`` with ``render`` arguments ``render_kwargs`` (as
    :func:`tofhil.sim.twin.render_arguments` gives them) and exposing its frames."""
    cam = render_kwargs.get("camera") or scene.camera
    spp = render_kwargs.get("samples_per_pixel") or scene.render.samples_per_pixel
    bounces = render_kwargs.get("bounces")
    bounces = scene.render.bounces if bounces is None else bounces
    tb = render_kwargs.get("transient_bins")
    bins = 0 if tb is None else (int(tb) if isinstance(tb, int) else max(len(tb) - 1, 0))
    freqs = render_kwargs.get("freq_hz")
    n_render = len(scene.sensor.freq_hz) if freqs is None else len(freqs)
    return estimate_bytes(width=cam.width, height=cam.height, render_freqs=n_render,
                          harmonics=len(render_kwargs.get("harmonics", (1,))),
                          sensor_freqs=len(scene.sensor.freq_hz), taps=scene.sensor.taps,
                          samples_per_pixel=int(spp), bounces=int(bounces),
                          separate_direct=bool(render_kwargs.get("separate_direct", False)),
                          transient_bins=bins, kept_frames=frames_kept, signal_effects=signal_effects,
                          triangles=scene_triangles(scene), bvhs=bvh_count())


_LIBC: Any = None


def release_free_memory() -> None:
    """Give the C heap's free pages back to the system (glibc's ``malloc_trim``; nothing
    elsewhere). Frame-sized arrays below glibc's (self-raising) mmap threshold come from the
    heap, and their pages stay resident after they are freed when other blocks sit around
    them: a diagnosis at 512 x 512 carried 40-90 MB of such pages from one fit into the next.
    Called between fits, where nothing frame-sized is alive but what is kept."""
    global _LIBC
    if _LIBC is None:
        try:
            import ctypes

            _LIBC = ctypes.CDLL("libc.so.6").malloc_trim
        except (OSError, AttributeError):
            _LIBC = False
    if _LIBC:
        _LIBC(0)
