"""Calibration from captures: the camera (intrinsics, distortion, stereo extrinsics, ``camera``)
and the taps (per-tap offset and gain, ``taps``; side files that name their format,
``side_files``). Board detection and pose are in the core (``tofhil.targets``)."""

from tofhil.faces import lazy_face

__all__, __getattr__, __dir__ = lazy_face(__name__, {
    "calibrate_camera": "camera",
    "calibrate_sessions": "camera",
    "CameraCalibration": "camera",
    "calibrate_stereo": "camera",
    "calibrate_stereo_sessions": "camera",
    "StereoCalibration": "camera",
    "TapCalibration": "taps",
    "calibrate_taps": "taps",
})
