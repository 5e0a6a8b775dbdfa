"""Write the docs' figures of the Azure Kinect recording coloured with its factory calibration:
the coloured cloud and the misalignment at the mug's depth edges (docs/images/), and print the
figures. Run: python benchmarks/kinect_edge_alignment.py [RECORDING.mkv]"""

from __future__ import annotations

import base64
import json
import sys
from pathlib import Path


from tofhil.drivers.importers.k4a_color import read_depth_with_color
from tofhil.eval.rgb.colorize import colorize_points
from tofhil.eval.rgb.report import cloud_view, figure_cloud, figure_edges
from tofhil.eval.rgb.edge_alignment import edge_alignment

ROOT = Path(__file__).resolve().parents[1]


def main(path: Path) -> None:
    inp = read_depth_with_color(path)
    z, valid, rays, t, ccam, rgb = inp.z_m, inp.valid, inp.pixel_to_ray, inp.tof_to_color, inp.color_camera, inp.rgb
    pts = inp.points()
    col = colorize_points(pts, t, ccam, rgb)
    res = edge_alignment(z, valid, rays, t, ccam, rgb)
    out = ROOT / "docs" / "images"
    out.mkdir(exist_ok=True)
    for name, uri in (("kinect_mug_cloud.png", figure_cloud(cloud_view(pts[col.visible], col.colors[col.visible]),
                                                             "Azure Kinect depth coloured (factory calibration)")),
                      ("kinect_mug_edges.png", figure_edges(rgb, res))):
        (out / name).write_bytes(base64.b64decode(uri.split(",", 1)[1]))
    print(json.dumps(res.to_dict(), indent=1))
    for kw in ({"search_px": 10}, {"search_px": 25}, {"search_px": 30}, {"sigma_px": 1.0}, {"sigma_px": 2.5},
               {"jump_m": 0.4}):
        r = edge_alignment(z, valid, rays, t, ccam, rgb, **kw)
        print(kw, f"left {r.left.median_px:+.2f} right {r.right.median_px:+.2f} shift {r.shift_px:+.2f} "
                  f"spread {r.spread_px:+.2f} slope {r.slope:.2f} (left {r.slope_left:.2f}, right {r.slope_right:.2f})")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT.parent / "shared" / "data" / "real" / "azure_kinect" / "recording.mkv")
