"""A colour camera beside the ToF camera: coloured point clouds with occlusion (``colorize``),
how well colour lines up with depth at edges (``edge_alignment``) and the report (``report``)."""

from tofhil.faces import lazy_face

__all__, __getattr__, __dir__ = lazy_face(__name__, {
    "colorize_points": "colorize",
    "write_ply": "colorize",
    "edge_alignment": "edge_alignment",
    "write_colorize_report": "report",
})
