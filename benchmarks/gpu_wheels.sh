#!/usr/bin/env bash
# Fill .whl/ for a GPU machine that has Python 3.12 but no package index (gpu_check.sh
# unpacks it there): Mitsuba's wheel stripped to the cuda_ad_rgb, llvm_ad_rgb and
# scalar_rgb modules (the whole wheel is over the 64 MiB a lent machine takes), Dr.Jit's
# and OpenEXR's, and the external scenes the GPU checks render (Veach's room, the
# Cornell box).  Needs a package index here.
#   bash benchmarks/gpu_wheels.sh [SHARED]        # SHARED: ../shared by default
set -euo pipefail
cd "$(dirname "$0")/.."
SHARED=${1:-${BDPT_SHARED:-../shared}}
PY=${PY:-python3}
MITSUBA=$($PY -c "import mitsuba; print(mitsuba.__version__)")
DRJIT=$($PY -c "import drjit; print(drjit.__version__)")
tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT
$PY -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
    --platform manylinux_2_17_x86_64 -d "$tmp" "mitsuba==$MITSUBA" "drjit==$DRJIT" OpenEXR
mkdir -p .whl "$tmp/m"
rm -f .whl/*.whl .whl/*.zip
cp "$tmp"/drjit-*.whl "$tmp"/openexr-*.whl .whl/
(cd "$tmp/m" && $PY -m zipfile -e "$tmp"/mitsuba-*.whl . \
    && rm -rf mitsuba/include mitsuba/cmake mitsuba/pkgconfig mitsuba/mitsuba_stubs \
              mitsuba/python/test mitsuba/data/srgb.coeff \
    && find mitsuba -maxdepth 1 -name '*.pyi' -delete \
    && find mitsuba -maxdepth 1 -name '*_ad_*.so' ! -name 'cuda_ad_rgb.*' \
            ! -name 'llvm_ad_rgb.*' -delete \
    && find mitsuba -maxdepth 1 -name 'scalar_*.so' ! -name 'scalar_rgb.*' -delete \
    && $PY -m zipfile -c "$OLDPWD/.whl/mitsuba-stripped.zip" mitsuba mitsuba-*.dist-info)
mkdir -p .whl/shared/scenes/external
for s in veach-bidir cornell-box; do
    rm -rf ".whl/shared/scenes/external/$s"
    cp -r "$SHARED/scenes/external/$s" .whl/shared/scenes/external/
done
du -sh .whl
