"""Residual structure (eval/diagnose/structure.py): each part is found when it is there, at the
size it was made, and nothing is reported on pure noise (synthetic maps, no rendering)."""

from __future__ import annotations

import numpy as np
import pytest

from tofhil.eval.diagnose.structure import channel_structure, edge_mask

H, W = 60, 80
SIGMA = 0.5e-3  # m


def _setup(seed: int = 0):
    rng = np.random.default_rng(seed)
    usable = np.ones((H, W), bool)
    oid = np.zeros((H, W), int)
    oid[:, 60:] = 1  # a second object on the right
    depth = np.where(oid == 0, 1.0, 1.5)
    noise = rng.normal(0.0, SIGMA, (H, W))
    return rng, usable, oid, depth, noise


def _run(residual, usable, oid, depth):
    edges = edge_mask(depth, usable, oid)
    return channel_structure("depth", residual, np.full((H, W), SIGMA), usable, oid, {0: "wall", 1: "box"}, edges,
                             (W / 2 - 0.5, H / 2 - 0.5))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pure_noise_shows_nothing(seed):
    _, usable, oid, depth, noise = _setup(seed)
    assert _run(noise, usable, oid, depth) == []


def test_radial_bowl_is_found_radial_at_its_size():
    _, usable, oid, depth, noise = _setup()
    v, u = np.mgrid[0:H, 0:W]
    r2 = ((u - W / 2 + 0.5) ** 2 + (v - H / 2 + 0.5) ** 2) / (W / 2) ** 2
    bowl = 4e-3 * (r2 - r2[oid == 0].mean())
    found = _run(np.where(oid == 0, bowl, 0.0) + noise, usable, oid, depth)
    smooth = [f for f in found if f.kind == "smooth" and f.obj == "wall"]
    assert len(smooth) == 1
    inner = (oid == 0) & ~edge_mask(depth, usable, oid)
    true_rms = float(np.sqrt(np.mean((bowl[inner] - bowl[inner].mean()) ** 2)))
    assert smooth[0].rms == pytest.approx(true_rms, rel=0.1)
    assert smooth[0].extra["radial_share"] > 0.9
    assert not [f for f in found if f.obj == "box"]


def test_tilt_is_smooth_but_not_radial():
    _, usable, oid, depth, noise = _setup()
    oid[:] = 0  # one object centred on the principal point: a tilt is odd, r^2 even
    depth[:] = 1.0
    _, u = np.mgrid[0:H, 0:W]
    found = _run(5e-5 * (u - W / 2 + 0.5) + noise, usable, oid, depth)
    smooth = [f for f in found if f.kind == "smooth"]
    assert smooth and smooth[0].extra["radial_share"] < 0.3


def test_column_pattern_and_spot_and_edges():
    rng, usable, oid, depth, noise = _setup()
    cols = rng.normal(0.0, 1.5e-3, W)
    res = noise + np.where(oid == 0, cols[None, :], 0.0)
    res[20:24, 30:34] += 10e-3  # a spot inside the wall
    found = _run(res, usable, oid, depth)
    pattern = [f for f in found if f.kind == "column pattern" and f.obj == "wall"]
    assert pattern
    inner = (oid == 0) & ~edge_mask(depth, usable, oid)
    assert pattern[0].rms == pytest.approx(float(np.std(cols[np.flatnonzero(inner.any(axis=0))])), rel=0.25)
    assert not [f for f in found if f.kind == "row pattern"]
    spots = [f for f in found if f.kind == "spot"]
    assert spots and spots[0].extra["bbox_x0y0x1y1"] == [30, 20, 34, 24] and not spots[0].extra["at_outline"]

    _, usable, oid, depth, noise = _setup(5)
    mixed = noise.copy()
    e = edge_mask(depth, usable, oid) & (np.abs(np.arange(W) - 59.5) < 2)[None, :]
    mixed[e] += 0.2  # flying pixels between the two depths
    found = _run(mixed, usable, oid, depth)
    assert [f.kind for f in found] == ["edges"]
