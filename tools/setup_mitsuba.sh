#!/usr/bin/env bash
# Set up Mitsuba 3 + mitransient for benchmarks/bench_vs_mitsuba.py (optional: CI does not).
#
# Mitsuba's CPU variants (llvm_ad_mono, ...) JIT-compile through Dr.Jit, which loads LLVM >= 19
# at run time. Debian bookworm ships only LLVM 14/15 as installed packages, but its archive has
# libllvm19: we download the .deb and unpack it into a private folder (no system install, no
# root needed for dpkg -x), then point DRJIT_LIBLLVM_PATH at libLLVM.so.19.1.
#
# Usage (with the project's venv active, e.g. `. .venv/bin/activate`):
#   bash tools/setup_mitsuba.sh [DEST]        # DEST defaults to ~/.cache/tofhil/llvm19
#   export DRJIT_LIBLLVM_PATH=DEST/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1   (printed at the end)
# The benchmark also looks in the default DEST when DRJIT_LIBLLVM_PATH is not set.
set -euo pipefail

DEST="${1:-${HOME}/.cache/tofhil/llvm19}"
PY="${PYTHON:-python}"

echo "== 1/3 Python packages (into $(command -v "$PY"))"
"$PY" -m pip install -q "mitsuba>=3.6" "mitransient>=1.3"

echo "== 2/3 libllvm19 from the distribution's archive, unpacked into $DEST"
mkdir -p "$DEST"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
if ! (cd "$tmp" && apt-get download libllvm19 >/dev/null 2>&1); then
    echo "   apt-get download failed; refreshing the package lists (needs root) and retrying"
    apt-get update -qq
    (cd "$tmp" && apt-get download libllvm19)
fi
dpkg -x "$tmp"/libllvm19_*.deb "$DEST"
LIB="$(find "$DEST" -name 'libLLVM.so.19*' -type f | head -n 1)"
if [ -z "$LIB" ]; then
    echo "error: libLLVM.so.19* not found under $DEST after unpacking" >&2
    exit 2
fi
# libLLVM's own dependencies (libz3, libxml2, libedit, libffi, ...) must come from the system.
missing="$(ldd "$LIB" | awk '/not found/ {print $1}')"
if [ -n "$missing" ]; then
    echo "   libLLVM.so.19 needs libraries this system lacks: $missing"
    echo "   install them with apt-get (e.g. apt-get install libz3-4 libxml2 libedit2 libffi8) and rerun"
    exit 2
fi

echo "== 3/3 check: Mitsuba's llvm_ad_mono variant and mitransient import"
DRJIT_LIBLLVM_PATH="$LIB" "$PY" - <<'EOF'
import mitsuba as mi
mi.set_variant("llvm_ad_mono")
import mitransient  # noqa: F401  (registers the transient integrators)
print(f"   mitsuba {mi.__version__}, mitransient {mitransient.__version__}, variant {mi.variant()}: ok")
EOF

echo
echo "Done. Before running the benchmark:"
echo "  export DRJIT_LIBLLVM_PATH=$LIB"
echo "  python benchmarks/bench_vs_mitsuba.py --quick"
