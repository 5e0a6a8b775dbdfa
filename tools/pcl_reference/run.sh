#!/bin/sh
# Rebuild PCL's reference numbers in tests/data/pcl/ (needs Debian's libpcl-dev).
# Run from the repository root: sh tools/pcl_reference/run.sh
set -e
OUT=tests/data/pcl
BIN=${TMPDIR:-/tmp}/ndt_reference
/work/venv/bin/python tools/pcl_reference/make_clouds.py "$OUT" 2>/dev/null || python3 tools/pcl_reference/make_clouds.py "$OUT"
g++ -O2 -std=c++17 -I/usr/include/pcl-1.13 -I/usr/include/eigen3 tools/pcl_reference/ndt_reference.cpp \
    -o "$BIN" -lpcl_registration -lpcl_filters -lpcl_io -lpcl_kdtree -lpcl_search -lpcl_common
# tag  resolution  outlier_ratio  min_points
for s in "r050 0.5 0.55 6" "r025 0.25 0.55 6" "r030 0.3 0.3 10"; do
  set -- $s
  "$BIN" "$OUT/ref.pcd" "$OUT/cloud.pcd" "$2" "$3" "$4" "$OUT/pcl_$1"
done
