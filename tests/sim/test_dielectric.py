"""Glass in the twin (tofhil.sim.dielectric and the renderer's glass path loop) against closed
form: Fresnel energy conservation, the refracted link through a slab by forward ray tracing,
a plane read through a pane, the pane's two reflections of the emitter, absorption; and the
set-ups the renderer refuses."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tofhil.demod import phase_to_distance, wrapped_phase
from tofhil.errors import TofhilError
from tofhil.sim.dielectric import fresnel, slab_geometry, slab_incidence
from tofhil.sim.render import render
from tofhil.sim.scene import scene_from_dict

F_HZ = 44.0e6
CAM = {"width": 16, "height": 12, "fx": 12.0, "fy": 12.0, "cx": 7.5, "cy": 5.5, "pixel_pitch_m": 96e-6}


def pane_scene(n: float = 1.5, t: float = 0.01, z0: float = 0.3, wall_m: float | None = 1.0,
               absorption: float = 0.0, offset=(0.0, 0.0, 0.0), power: float = 1.0, glass: bool = True) -> dict:
    """Camera at the origin looking along +z; a glass pane (faces at z0 and z0 + t, 2 m wide);
    a white wall at ``wall_m``; a cos^1 emitter at ``offset``."""
    objs = []
    if wall_m is not None:
        objs.append({"name": "wall", "type": "plane", "size": [20, 20], "material": "white",
                     "pose": {"position": [0, 0, wall_m]}})
    if glass:
        objs.append({"name": "pane", "type": "box", "size": [2, 2, t], "material": "glass",
                     "pose": {"position": [0, 0, z0 + t / 2]}})
    return {"camera": dict(CAM, f_number=1.2),
            "emitter": {"power_w": power, "offset_m": list(offset), "profile": {"type": "cos_n", "n": 1}},
            "materials": {"white": {"reflectance": 0.8}, "glass": {"ior": n, "absorption_per_m": absorption}},
            "objects": objs, "sensor": {"freq_hz": [F_HZ]}}


def pixel_angles() -> np.ndarray:
    v, u = np.mgrid[0:CAM["height"], 0:CAM["width"]].astype(float)
    x, y = (u - CAM["cx"]) / CAM["fx"], (v - CAM["cy"]) / CAM["fy"]
    return np.arctan(np.hypot(x, y))


# --------------------------------------------------------------------------- Fresnel
@pytest.mark.parametrize("n1, n2", [(1.0, 1.5), (1.5, 1.0), (1.0, 2.4), (1.33, 1.0)])
def test_fresnel_conserves_energy_at_each_interface(n1: float, n2: float) -> None:
    # T from the Fresnel AMPLITUDE transmission coefficients and the beam's change of
    # cross-section, independent of how R is computed: R + T = 1 below the critical angle.
    for ci in np.linspace(0.02, 1.0, 60):
        r, ct = fresnel(ci, n1, n2)
        if r == 1.0:                                         # total internal reflection
            assert n1 > n2 and (n1 / n2) ** 2 * (1 - ci * ci) >= 1.0
            continue
        ts = 2 * n1 * ci / (n1 * ci + n2 * ct)
        tp = 2 * n1 * ci / (n2 * ci + n1 * ct)
        trans = (n2 * ct) / (n1 * ci) * 0.5 * (ts * ts + tp * tp)
        assert r + trans == pytest.approx(1.0, abs=1e-12)
        assert n1 * math.sqrt(1 - ci * ci) == pytest.approx(n2 * math.sqrt(1 - ct * ct), abs=1e-12)  # Snell


def test_fresnel_normal_incidence_brewster_and_reciprocity() -> None:
    n = 1.5
    assert fresnel(1.0, 1.0, n)[0] == pytest.approx(((n - 1) / (n + 1)) ** 2, abs=1e-15)
    # At Brewster's angle the p wave is not reflected: R = rs^2 / 2.
    tb = math.atan(n)
    r, ct = fresnel(math.cos(tb), 1.0, n)
    rs = (math.cos(tb) - n * ct) / (math.cos(tb) + n * ct)
    assert r == pytest.approx(rs * rs / 2, abs=1e-15)
    # Reciprocity: the same R from inside at the refracted angle.
    for ci in (0.3, 0.7, 0.95):
        r1, ct = fresnel(ci, 1.0, n)
        assert fresnel(ct, n, 1.0)[0] == pytest.approx(r1, abs=1e-14)


# --------------------------------------------------------------------------- the slab link
@pytest.mark.parametrize("a, thick, n, rho", [(0.5, 0.01, 1.5, 0.2), (1.0, 0.2, 2.0, 1.5), (0.1, 0.05, 1.33, 0.0),
                                              (0.3, 0.02, 1.0, 0.4)])
def test_slab_incidence_obeys_snell_and_reaches_the_emitter(a: float, thick: float, n: float, rho: float) -> None:
    s = slab_incidence(a, thick, n, rho)
    st = s / n
    reach = a * s / math.sqrt(1 - s * s) + thick * st / math.sqrt(1 - st * st)
    assert reach == pytest.approx(rho, abs=1e-12)
    if n == 1.0:                              # no glass: the straight line
        assert s == pytest.approx(rho / math.hypot(rho, a + thick), abs=1e-12)


def test_slab_irradiance_matches_forward_ray_tracing() -> None:
    # Shoot rays from a point uniformly in solid angle through the slab (Snell per ray, by
    # hand), count where they land on a plane behind it: the landing density per area,
    # times cos(theta), is the irradiance the slab link predicts (per unit intensity).
    a, thick, n = 0.4, 0.15, 1.6
    rng = np.random.default_rng(3)
    N = 2_000_000
    cmax = math.cos(math.radians(40))
    ct = rng.uniform(cmax, 1.0, N)                         # uniform in solid angle
    st = np.sqrt(1 - ct * ct)
    st_in = st / n
    rho = a * st / ct + thick * st_in / np.sqrt(1 - st_in ** 2)
    edges = np.linspace(0.0, 0.3, 16)
    counts, _ = np.histogram(rho, edges)
    omega = 2 * math.pi * (1 - cmax)
    density = counts * (omega / N) / (math.pi * np.diff(edges ** 2))   # sr per m^2 of the plane
    mid = 0.5 * (edges[1:] + edges[:-1])
    pred = []
    for r in mid:
        s = slab_incidence(a, thick, n, r)
        g, _ = slab_geometry(a, thick, n, s)
        pred.append(g * math.sqrt(1 - s * s))             # irradiance on the plane (cos theta)
    rel = density / np.array(pred) - 1
    sigma = 1 / np.sqrt(counts)
    assert np.all(np.abs(rel) < 4 * sigma + 2e-3), (rel, sigma)
    # On the axis: the slab's apparent thickness thick / n.
    assert slab_geometry(a, thick, n, 0.0)[0] == pytest.approx(1 / (a + thick / n) ** 2, rel=1e-14)


# --------------------------------------------------------------------------- renders
@pytest.fixture(scope="module")
def pane_renders() -> dict:
    return {"bare": render(scene_from_dict(pane_scene(glass=False))),
            "glass": render(scene_from_dict(pane_scene())),
            "absorbing": render(scene_from_dict(pane_scene(absorption=20.0))),
            "glints": render(scene_from_dict(pane_scene(wall_m=None)))}


def _glint_free() -> np.ndarray:
    m = np.ones((CAM["height"], CAM["width"]), bool)
    m[6, 8] = False             # the emitter's images in the pane: the image centre (7.5, 5.5) rounds to (8, 6)
    return m


def test_plane_through_a_pane_reads_the_plate_formula(pane_renders: dict) -> None:
    # Emitter at the pinhole: the light crosses the pane both ways along the camera ray, so
    # the optical path is twice the camera leg z0/cos + n t/cos_t + (D - z0 - t)/cos, and the
    # distance read (OPL / 2) is that leg; on the axis (n - 1) t farther than without glass.
    n, t, z0, D = 1.5, 0.01, 0.3, 1.0
    th = pixel_angles()
    tht = np.arcsin(np.sin(th) / n)
    leg = z0 / np.cos(th) + n * t / np.cos(tht) + (D - z0 - t) / np.cos(th)
    d = phase_to_distance(wrapped_phase(pane_renders["glass"].phasor[0, 0]), F_HZ)
    # The pane's internal double reflections (on each leg a share <= R^2 / (1 - R)^2 of the
    # power, 2 n t / cos(theta_t) longer) pull the phase by at most those shares times the phase
    # of their extra path.
    r = ((n - 1) / (n + 1)) ** 2
    k = 2 * math.pi * F_HZ / 299792458.0
    bound = 2 * r * r / (1 - r) ** 2 * math.sin(min(k * 2 * n * t * 1.2, math.pi / 2)) / (2 * k) * 1.2
    err = (d - leg)[_glint_free()]
    assert np.abs(err).max() < bound + 1e-9, (np.abs(err).max(), bound)
    bare = phase_to_distance(wrapped_phase(pane_renders["bare"].phasor[0, 0]), F_HZ)
    shift = (d - bare)[_glint_free()]
    assert np.all(np.abs(shift - (leg - D / np.cos(th))[_glint_free()]) < bound + 1e-9)
    near_axis = np.abs(shift - (n - 1) * t)[th[_glint_free()] < 0.06]
    assert near_axis.size and near_axis.max() < 2e-5 + bound     # (n-1) t = 5 mm farther


def test_transmitted_power_is_fresnel_and_the_apparent_distance(pane_renders: dict) -> None:
    # Centre-most pixels: each way through the pane transmits (1 - R)^2 (two faces), and the
    # emitter's light spreads as from (D - t + t/n) instead of D (the slab's apparent
    # thickness), the camera's view of the wall does not change (radiance is conserved).
    n, t, D = 1.5, 0.01, 1.0
    r = ((n - 1) / (n + 1)) ** 2
    th = pixel_angles()
    ratio = pane_renders["glass"].power_w / pane_renders["bare"].power_w
    pred = (1 - r) ** 4 * (D / (D - t + t / n)) ** 2
    # ... plus the pane's internal echo on each leg: on the camera's R^2 (the camera sees the
    # wall through it, the same radiance), on the emitter's R^2 spread as from D - t + 3t/n
    echo = (1 + r * r) * (1 + r * r * ((D - t + t / n) / (D - t + 3 * t / n)) ** 2)
    near = (th < 0.06) & _glint_free()
    assert np.all(np.abs(ratio[near] / (pred * echo) - 1) < 2e-4)     # (R^4 = 2.6e-6; R(theta) flat here)
    assert np.all(np.abs(ratio[near] / pred - 1) > 2e-3)               # the echoes are there


def test_absorption_attenuates_exp_minus_sigma_both_ways(pane_renders: dict) -> None:
    n, t, sigma = 1.5, 0.01, 20.0
    th = pixel_angles()
    tht = np.arcsin(np.sin(th) / n)
    ratio = pane_renders["absorbing"].power_w / pane_renders["glass"].power_w
    pred = np.exp(-sigma * 2 * t / np.cos(tht))
    m = _glint_free()
    # internal reflections cross the glass more often: their share (< R^2) is absorbed more
    assert np.all(np.abs(ratio[m] / pred[m] - 1) < 3e-3)
    assert np.all(ratio[m] < 1.0)


def test_the_pane_reflects_the_emitter_twice(pane_renders: dict) -> None:
    # No wall: the only light is the emitter's image in the pane's front face (Fresnel R at
    # normal incidence, inverse square over 2 z0) and in its back face ((1 - R)^2 R, the
    # unfolded distance 2 z0 + 2 t / n); optical paths 2 z0 and 2 z0 + 2 n t.
    n, t, z0 = 1.5, 0.01, 0.3
    r = ((n - 1) / (n + 1)) ** 2
    res = pane_renders["glints"]
    intensity = 1.0 * 2 / (2 * math.pi)                    # P (n+1) / 2 pi on the axis, cos^1 beam
    f = CAM["fx"] * CAM["pixel_pitch_m"]
    aperture = math.pi * (f / (2 * 1.2)) ** 2
    front = intensity * r * aperture / (2 * z0) ** 2
    back = intensity * (1 - r) ** 2 * r * aperture / (2 * z0 + 2 * t / n) ** 2
    k = 2 * math.pi * F_HZ / 299792458.0
    expected = front * np.exp(1j * k * 2 * z0) + back * np.exp(1j * k * (2 * z0 + 2 * n * t))
    assert res.power_w[6, 8] == pytest.approx(front + back, rel=1e-9)
    assert abs(res.phasor[0, 0, 6, 8] - expected) < 1e-9 * abs(expected)
    others = res.power_w.copy()
    others[6, 8] = 0.0
    assert np.all(others == 0.0)
    assert np.all(res.object_id == 0) and np.allclose(res.radial_m[6, 8], z0 / math.cos(pixel_angles()[6, 8]))


def test_index_one_is_no_glass() -> None:
    a = render(scene_from_dict(pane_scene(n=1.0, offset=(0.02, 0.01, 0.0))))
    b = render(scene_from_dict(pane_scene(glass=False, offset=(0.02, 0.01, 0.0))))
    np.testing.assert_allclose(a.phasor, b.phasor, rtol=1e-9, atol=0)


def test_bundled_glass_scene_renders() -> None:
    from tofhil.camera import CameraModel
    from tofhil.sim.scene import load_scene

    scene = load_scene("configs/scenes/glass_pane.yaml")
    cam = CameraModel(**CAM)
    res = render(scene, camera=cam, bounces=1, samples_per_pixel=2)
    assert np.all(np.isfinite(res.phasor)) and res.power_w.max() > 0
    assert "pane" in [o.name for o in scene.objects]


# --------------------------------------------------------------------------- refused
@pytest.mark.parametrize("change, field", [
    (lambda d: d["objects"][1].update(type="plane", size=[1, 1]), "objects[1].type"),
    (lambda d: d["materials"]["glass"].update(ior=0.5), "materials.glass.ior"),
    (lambda d: d["materials"]["glass"].update(reflectance=0.5), "materials.glass.reflectance"),
    (lambda d: d["materials"]["glass"].update(absorption_per_m=-1), "materials.glass.absorption_per_m"),
])
def test_bad_glass_names_its_field(change, field: str) -> None:
    d = pane_scene()
    change(d)
    with pytest.raises(TofhilError) as e:
        scene_from_dict(d)
    assert f"'{field}'" in str(e.value) or field in str(e.value)


def test_glass_setups_the_renderer_does_not_model_are_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    d = pane_scene(z0=-0.005)                               # the camera inside the pane
    with pytest.raises(TofhilError, match="inside the glass box"):
        render(scene_from_dict(d))
    d = pane_scene(wall_m=0.303)                            # the wall's corners inside the pane
    d["objects"][0]["size"] = [1.0, 1.0]
    with pytest.raises(TofhilError, match="reaches into the glass box"):
        render(scene_from_dict(d))
    d = pane_scene()                                        # the media kernel has no beam table
    d["emitter"]["profile"] = {"type": "table", "theta_deg": [0.0, 180.0], "relative_intensity": [1.0, 1.0]}
    with pytest.raises(TofhilError, match="compiled path loop only"):
        render(scene_from_dict(d))
    monkeypatch.setenv("TOFHIL_RENDER_WAVEFRONT", "1")
    with pytest.raises(TofhilError, match="compiled path loop only"):
        render(scene_from_dict(pane_scene()))


def test_cover_glass_scene_matches_the_benchmarks_closed_form() -> None:
    # benchmarks/glass_slab.py: a cover glass over the lens only, the emitter 15 cm beside it
    # (its leg does not cross the glass); the renderer's optical path per pixel against the
    # closed form opl_through_slab (Snell, n t / cos(theta_t), the parallel exit ray).
    from benchmarks.glass_slab import GlassSlab, opl_through_slab, tofhil_scene_without_slab
    from tofhil.camera import CameraModel

    slab = GlassSlab()
    d = tofhil_scene_without_slab(slab)
    d["camera"] = dict(CAM, pose=d["camera"]["pose"])
    d["emitter"]["profile"] = {"type": "cos_n", "n": 0}      # the compiled loop's beam: uniform ahead
    d["materials"]["glass"] = {"ior": slab.n}
    d["objects"].append({"name": "cover", "type": "box", "material": "glass",
                         "size": [2 * slab.half_width_m, 2 * slab.half_width_m, slab.t_m],
                         "pose": {"position": [0.0, 0.0, slab.z0_m + slab.t_m / 2]}})
    res = render(scene_from_dict(d))
    cam = CameraModel(**CAM)
    assert slab.covers_view(cam.rays)
    expected = opl_through_slab(slab, cam.rays) / 2
    got = phase_to_distance(wrapped_phase(res.phasor[0, 0]), F_HZ)
    # the cover's internal double reflections (share R^2/(1-R)^2, 2 n t longer) bound the error
    r = ((slab.n - 1) / (slab.n + 1)) ** 2
    assert np.abs(got - expected).max() < r * r / (1 - r) ** 2 * 2 * slab.n * slab.t_m


def test_a_pane_behind_the_camera_mirrors_the_emitter_onto_the_wall() -> None:
    # The emitter faces backward (axis -z) onto a pane behind the camera (front face at
    # z = -0.3, opaque inside: absorption 2000/m kills its back-face reflection); the wall at
    # z = 1 gets no direct light, only the emitter's mirror image at z = -0.6, with the
    # Fresnel R at each point's incidence: E = I(theta_e) R cos(theta_s) / L^2, optical path
    # camera leg + L.
    d = pane_scene(z0=-0.31, t=0.01, absorption=2000.0)
    d["emitter"]["axis"] = [0.0, 0.0, -1.0]
    res = render(scene_from_dict(d))
    v, u = np.mgrid[0:CAM["height"], 0:CAM["width"]].astype(float)
    ray = np.stack([(u - CAM["cx"]) / CAM["fx"], (v - CAM["cy"]) / CAM["fy"], np.ones_like(u)], axis=-1)
    x = ray                                                  # wall points at z = 1
    img = np.array([0.0, 0.0, -0.6])
    to_img = img - x
    L = np.linalg.norm(to_img, axis=-1)
    h = x + to_img * (1.3 / 1.6)                             # where the ray meets the face z = -0.3
    e_dir = h / np.linalg.norm(h, axis=-1, keepdims=True)
    cos_e = -e_dir[..., 2]
    refl = np.vectorize(lambda c: fresnel(c, 1.0, 1.5)[0])(1.6 / L)
    irr = (1.0 * 2 / (2 * math.pi)) * cos_e * refl * (1.6 / L) / L ** 2
    f = CAM["fx"] * CAM["pixel_pitch_m"]
    cos_a = 1 / np.linalg.norm(ray, axis=-1)
    power = 0.8 / math.pi * irr * math.pi * (f / 2.4) ** 2 * cos_a ** 4 * CAM["pixel_pitch_m"] ** 2 / f ** 2
    k = 2 * math.pi * F_HZ / 299792458.0
    opl = np.linalg.norm(x, axis=-1) + L
    np.testing.assert_allclose(res.power_w, power, rtol=1e-9)
    np.testing.assert_allclose(res.phasor[0, 0], power * np.exp(1j * k * opl), rtol=1e-9)


def test_the_rgb_cameras_image_refuses_glass() -> None:
    from tofhil.camera import CameraModel
    from tofhil.sim.rgb import render_grey

    scene = scene_from_dict(pane_scene())
    with pytest.raises(TofhilError, match="does not model glass") as e:
        render_grey(scene, CameraModel(**CAM), np.eye(4), samples=1)
    assert "objects[1].material" in str(e.value)
