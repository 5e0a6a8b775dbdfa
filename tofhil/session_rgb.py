"""The optional ``rgb/`` group of a session: frames of a second (colour or grey) camera beside
the ToF camera, its camera model and its pose relative to the ToF camera.

Layout (docs/session-format.md, "The rgb group"):

* ``rgb/images``: uint8 ``[M, H, W, 3]`` (RGB) or float32 ``[M, H, W]`` (grey radiance), one
  image per ToF frame it was taken with (``rgb/frame_index`` ``[M]`` int64 names that frame);
* attribute ``rgb.camera``: the camera as JSON (the root ``camera`` attribute's fields);
* attribute ``rgb.tof_to_camera``: JSON 4x4 ToF-frame -> this camera's frame (m), or absent
  when not known (it is what ``tofhil calibrate-stereo`` finds).

Adding the group does not touch the ToF data; readers that do not know it ignore it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import h5py
import numpy as np

from tofhil.outputs import refuse_existing
from tofhil.camera import CameraModel
from tofhil.errors import InputFileError


@dataclass
class RGBFrames:
    images: np.ndarray                  # [M, H, W, 3] uint8 or [M, H, W] float32
    frame_index: np.ndarray             # [M] ToF frame each image goes with
    camera: CameraModel
    tof_to_camera: np.ndarray | None    # 4x4 or None


def write_rgb(path: str | Path, images: Sequence[np.ndarray], camera: CameraModel, *,
              frame_index: Sequence[int] | None = None, tof_to_camera: np.ndarray | None = None,
              force: bool = False) -> None:
    """Add (or with ``force`` replace) the ``rgb/`` group of an existing session file."""
    arr = np.stack([np.asarray(i) for i in images])
    if arr.dtype != np.uint8:
        arr = arr.astype(np.float32)
    if arr.shape[1:3] != camera.shape or (arr.ndim == 4 and arr.shape[3] != 3) or arr.ndim not in (3, 4):
        raise ValueError(f"images are {arr.shape[1:]}, camera is {camera.height}x{camera.width}")
    idx = np.arange(len(arr)) if frame_index is None else np.asarray(frame_index, dtype=np.int64)
    with h5py.File(path, "a") as f:
        if "rgb" in f:
            refuse_existing(path, force, what="already has an rgb group", field="rgb", recorded=True)
            del f["rgb"]
        g = f.create_group("rgb")
        g.create_dataset("images", data=arr)
        g.create_dataset("frame_index", data=idx)
        g.attrs["camera"] = json.dumps(camera.to_dict())
        if tof_to_camera is not None:
            g.attrs["tof_to_camera"] = json.dumps(np.asarray(tof_to_camera, dtype=float).tolist())


def read_rgb(path: str | Path) -> RGBFrames:
    """The session's ``rgb/`` group; errors name the file and the field."""
    with h5py.File(path, "r") as f:
        if "rgb" not in f or "images" not in f["rgb"]:
            raise InputFileError("has no rgb/images", file=path, field="rgb/images",
                                 expected="a session with a second camera's frames (docs/session-format.md)")
        g = f["rgb"]
        images = g["images"][()]
        idx = g["frame_index"][()] if "frame_index" in g else np.arange(len(images))
        if "camera" not in g.attrs:
            raise InputFileError("missing", file=path, field="rgb.camera", expected="the camera as JSON")
        camera = CameraModel.from_json(str(g.attrs["camera"]), source=path)
        T = None
        if "tof_to_camera" in g.attrs:
            T = np.asarray(json.loads(str(g.attrs["tof_to_camera"])), dtype=np.float64)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise InputFileError(f"has shape {T.shape}", file=path, field="rgb.tof_to_camera",
                                     expected="a 4x4 transform")
    if images.shape[1:3] != camera.shape:
        raise InputFileError(f"images are {images.shape[1]}x{images.shape[2]}, camera {camera.height}x{camera.width}",
                             file=path, field="rgb/images", expected="images of the rgb camera's size")
    return RGBFrames(images=images, frame_index=idx, camera=camera, tof_to_camera=T)
