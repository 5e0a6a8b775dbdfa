"""Pixel binning: ``b x b`` blocks of an image averaged into one pixel, and the camera of the
binned image.

A diagnosis of a large image searches on binned data (``eval/diagnose``): the mean of a
block of pixels is what one pixel of a camera with ``b`` times fewer pixels on each axis,
and the same optics, would measure, so the twin renders that camera instead.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import replace

import numpy as np

from tofhil.camera import CameraModel


def bin_factor(shape: tuple[int, int], max_pixels: int) -> int:
    """The smallest integer bin that brings an image to at most ``max_pixels``."""
    return max(1, int(math.ceil(math.sqrt(shape[0] * shape[1] / max_pixels))))


def bin_mean(x: np.ndarray, b: int) -> np.ndarray:
    """Mean over ``b x b`` blocks of the last two axes (the ragged edge is dropped)."""
    if b == 1:
        return x
    h, w = x.shape[-2] // b * b, x.shape[-1] // b * b
    x = x[..., :h, :w]
    return x.reshape(x.shape[:-2] + (h // b, b, w // b, b)).mean(axis=(-3, -1))


def binned_camera(camera: CameraModel, b: int) -> CameraModel:
    """The camera of ``b x b`` binned pixels (the ragged edge dropped).

    The binned measurement is the *mean* of its pixels, so a binned twin pixel must collect
    the light of one pixel, not of ``b^2``: the pixel pitch is kept (the twin's flux per pixel
    goes as its solid angle ``1/(fx fy)`` times the pupil area ``(fx pitch / 2N)^2``, i.e. as
    ``pitch^2``, whatever ``fx``). Scaling the pitch by ``b`` made a 2 x 2 binned twin four
    times too bright on a camera with a pitch (a camera without one used a default pitch)."""
    if b == 1:
        return camera
    w, h = camera.width // b, camera.height // b
    f = 1.0 / b
    return replace(camera, width=w, height=h, fx=camera.fx * f, fy=camera.fy * f,
                   cx=(camera.cx + 0.5) * f - 0.5, cy=(camera.cy + 0.5) * f - 0.5)


#: Relative spread of the depths within a bin beyond which it holds two surfaces (a depth edge).
DEPTH_SPREAD = 0.05
def _blocks(x: np.ndarray, b: int) -> np.ndarray:
    """``[..., H, W]`` as ``[..., H // b, W // b, b * b]`` (the ragged edge dropped)."""
    h, w = x.shape[-2] // b * b, x.shape[-1] // b * b
    x = x[..., :h, :w].reshape(x.shape[:-2] + (h // b, b, w // b, b))
    return np.moveaxis(x, -3, -2).reshape(x.shape[:-4] + (h // b, w // b, b * b))


def one_surface(depth_m: np.ndarray, ok: np.ndarray, b: int) -> np.ndarray:
    """Bins ``[H // b, W // b]`` whose ``ok`` pixels' depths agree within :data:`DEPTH_SPREAD`
    of the nearest (a device's filtered depth: no depth edge inside)."""
    d = _blocks(np.where(ok, depth_m, np.nan), b)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN bins: no pixel to judge
        lo, hi = np.nanmin(d, axis=-1), np.nanmax(d, axis=-1)
    return np.isfinite(lo) & (hi - lo <= DEPTH_SPREAD * np.where(np.isfinite(lo), lo, 1.0))


def one_object(object_id: np.ndarray, b: int, margin_px: int = 1) -> np.ndarray:
    """Bins that one object (or the background) fills, ``margin_px`` pixels around each too:
    the mean of a bin across an outline is a mixture whose shares depend on where the outline
    lies inside it, which a binned twin does not resolve (and an outline a pixel off, as a
    pose error puts it, still crosses the bin)."""
    from scipy import ndimage

    o = _blocks(object_id, b)
    one = o.min(axis=-1) == o.max(axis=-1)
    if margin_px > 0:
        size = 2 * margin_px + 1
        same = (ndimage.maximum_filter(object_id, size=size, mode="nearest")
                == ndimage.minimum_filter(object_id, size=size, mode="nearest"))
        one &= _blocks(same, b).all(axis=-1)
    return one
