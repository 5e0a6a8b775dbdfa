"""The one evaluation core: every figure a report prints is computed here, once.

``core`` (residual maps, regions, per-region statistics, the depth RMSE), ``matching``
(ICP and cloud distances), ``ndt`` (3D-NDT scores, PCL-compatible), ``clouds`` (reading a
cloud from a file or a session), ``noise`` (robust spread, pooled local variance, phasor
noise in distance)."""

from tofhil.faces import lazy_face

__all__, __getattr__, __dir__ = lazy_face(__name__, {
    "evaluate": "core",
    "Evaluation": "core",
    "residual_maps": "core",
    "Region": "core",
    "region_metrics": "core",
    "stats": "core",
    "rmse": "core",
    "json_safe": "core",
    "DEPTH_RMSE": "core",
    "MAD_TO_SIGMA": "noise",
    "robust_sigma": "noise",
    "pooled_variance": "noise",
    "icp": "matching",
    "cloud_metrics": "matching",
    "ndt_score": "ndt",
    "NDTScore": "ndt",
    "load_cloud": "clouds",
})
