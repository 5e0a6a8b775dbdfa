"""scene-from-capture of a noisy capture of the bundled wall (issue 34's walkthrough): one wall
is one plane with the beam it has (it was a 1927-pixel plane, a 17273-pixel mesh, two
reflectances and a cos^0 beam where the scene's is cos^2: the RANSAC threshold was below the
noise)."""

from __future__ import annotations

from pathlib import Path

from tofhil.sim.from_capture import scene_from_capture
from tofhil.sim.pipeline import simulate_session
from tofhil.sim.scene import load_scene


def test_a_noisy_wall_is_one_plane_with_its_beam(tmp_path: Path) -> None:
    capture = simulate_session(load_scene("wall"), tmp_path / "wall.h5", frames=1, seed=4, noise=True)
    notes: list[str] = []
    scene_from_capture(capture, tmp_path / "twin.yaml", progress=notes.append)
    twin = load_scene(tmp_path / "twin.yaml")
    planes = [o for o in twin.objects if o.name.startswith("plane")]   # written as their outlines
    assert len(planes) == 1, notes
    assert len(planes[0].mesh.faces) > 0
    rest = [o for o in twin.objects if not o.name.startswith("plane")]
    assert sum(len(o.mesh.faces) for o in rest) < 100, notes             # was 22929 triangles
    assert twin.emitter.profile.kind == "cos_n" and abs(twin.emitter.profile.n - 2.0) < 0.3, notes
