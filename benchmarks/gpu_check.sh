#!/usr/bin/env bash
# The GPU checks of the open issues, in one run (a lent GPU machine's time is short):
# the tests under cuda_ad_rgb, then the benchmarks at 1024x1024.  Each step's output
# goes to $OUT (default ./gpu-out) and the run goes on after a failed step.
#   BDPT_SHARED=<shared> bash benchmarks/gpu_check.sh            # on the GPU machine
#   VARIANT=llvm_ad_rgb RES=64 SPP=8 STEPS="efficiency profile" bash benchmarks/gpu_check.sh
#                                                                # a dry run on a CPU
# A machine without the Python packages gets them from wheels in .whl/ (made here by
# benchmarks/gpu_wheels.sh: all *.whl and *.zip there are unpacked into /tmp/site) and
# the external scenes from .whl/shared when BDPT_SHARED is unset.
set -u
cd "$(dirname "$0")/.."
if [ -d .whl ] && ! python3 -c "import mitsuba" 2>/dev/null; then
    python3 -c "import glob, zipfile
for f in glob.glob('.whl/*.whl') + glob.glob('.whl/*.zip'): zipfile.ZipFile(f).extractall('/tmp/site')"
    export PYTHONPATH=/tmp/site:$PWD${PYTHONPATH:+:$PYTHONPATH}
    export BDPT_SHARED=${BDPT_SHARED:-$PWD/.whl/shared}
fi
export BDPT_VARIANT=${VARIANT:-cuda_ad_rgb} PYTHONUNBUFFERED=1
PY=${PY:-python3}
RES=${RES:-1024}; SPP=${SPP:-128}; OUT=${OUT:-gpu-out}
STEPS=${STEPS:-calibrate tests frozen passes breakdown divergence efficiency profile throughput memory small small-first mlt}
EXT=${BDPT_SHARED:-../shared}/scenes/external
mkdir -p "$OUT"
step() {   # step NAME SECONDS COMMAND...: run with a time limit, log, report
    local name=$1 limit=$2; shift 2
    case " $STEPS " in *" $name "*) ;; *) return ;; esac
    local start=$SECONDS
    timeout "$limit" bash -c "$*" > "$OUT/$name.log" 2>&1
    echo "== $name: exit $? in $((SECONDS - start)) s" | tee -a "$OUT/summary.txt"
    tail -n 25 "$OUT/$name.log"
}
profile() {   # Veach's BDPT, kernel by kernel, in the Cornell box and Veach's room; vcm's
              # pass (issue 30): its camera walk with the merge queries, the grid's build
    $PY -m benchmarks.profile_pass --res "$RES" --spp 4
    $PY -m benchmarks.profile_pass --res "$RES" --spp 1 \
        --budget "light_paths=1 connections=all merging=true"
    $PY benchmarks/experiments/merge_walk.py --res "$RES" --passes 3
    $PY -m benchmarks.profile_pass --res "$RES" --spp 4 --max-depth 7 \
        --scene "$EXT/veach-bidir/scene.xml"
}
throughput() {   # samples per second against path, the same two scenes
    $PY -m benchmarks.throughput --no-cold --res "$RES" --spp 16
    $PY -m benchmarks.throughput --no-cold --res "$RES" --spp 16 --max-depth 7 \
        --scene "$EXT/veach-bidir/scene.xml"
}
passes() {   # per-pass wall and kernel time; pass sizes, vcm (issue 30's target: <= 1.5x
             # veach's time per sample) and pssmlt against path
    $PY -m benchmarks.gpu_passes --res "$RES" --spp 16 --repeats 2 --methods veach-2g,veach,veach-separate-calls,default
    $PY -m benchmarks.gpu_passes --res "$RES" --spp 4 --repeats 1 --methods veach,vcm,pssmlt
    $PY -m benchmarks.gpu_passes --res "$RES" --spp 16 --repeats 2 --max-depth 7 \
        --scene "$EXT/veach-bidir/scene.xml" --methods veach-2g,veach,veach-separate-calls,default
}
breakdown() {   # the camera walk without connections, and with neither light walk nor them
    for b in "light_paths=1 connections=0" "light_paths=0 connections=0"; do
        $PY -m benchmarks.profile_pass --res "$RES" --spp 1 --budget "$b"
    done
}
divergence() {   # the connection loop's wasted iterations per warp, and their time bound
    $PY benchmarks/experiments/connection_divergence.py cornell-diffuse --res 256
    $PY benchmarks/experiments/connection_divergence.py scenes/deep-box.xml --max-depth 65 --res 256
    $PY benchmarks/experiments/connection_divergence.py cornell-diffuse --bound 2 --spp 4 --res "$RES"
    $PY benchmarks/experiments/connection_divergence.py scenes/deep-box.xml --max-depth 65 \
        --bound 2 --spp 4 --res "$RES"
}
mlt() {   # issue 31: MMLT's chains and mutations per second against path, then its
          # equal-time error against the default bdpt on the door ajar and the box
    $PY -m benchmarks.gpu_passes --res "$RES" --spp 4 --repeats 1 --methods veach,mlt
    $PY -m benchmarks.mlt_door --ref-spp 65536 --gap-start 0.49 --seconds 10 --runs 2 \
        --methods "mlt,bdpt (auto),path"
    $PY -m benchmarks.mlt_door --ref-spp 16384 --scene scenes/cornell-box.xml --seconds 5 \
        --plan-mpp 256 --runs 2 --methods "mlt,bdpt (auto)"
}
frozen() {   # passes replaying recorded walks under CUDA (BDPT_FREEZE_CUDA=1): the
             # recording's tests, then per-pass times against traced passes
    BDPT_FREEZE_CUDA=1 $PY -m pytest -q -p no:cacheprovider tests/test_frozen.py \
        tests/test_schedule.py tests/test_kernels.py
    for f in 0 1; do
        BDPT_FREEZE_CUDA=$f $PY -m benchmarks.gpu_passes --res "$RES" --spp 16 --repeats 2 \
            --methods veach,default
    done
    BDPT_FREEZE_CUDA=1 $PY -m benchmarks.small --seeds 8
}
export -f profile throughput passes breakdown divergence mlt frozen; export PY RES EXT
step calibrate 90 $PY -m bdpt_drjit calibrate --variant "$BDPT_VARIANT"
step profile 60 profile
step throughput 100 throughput
step passes 150 passes
step breakdown 40 breakdown
step divergence 90 divergence
step tests 160 $PY -m pytest -q -p no:cacheprovider -n "${JOBS:-8}" --ignore tests/test_cluster.py \
    -k \'not spectral_and_mono and not variant_switch and not specfilm\'
step frozen 150 frozen
step mlt 150 mlt
step efficiency 110 $PY -m benchmarks.efficiency --res "$RES" --spp "$SPP" --seeds 3
step memory 60 $PY -m benchmarks.memory --res "$RES" --mib 8192 --budget auto
step small 120 $PY -m benchmarks.small --seeds 8
step small-first 120 $PY -m benchmarks.small --seeds 8 --first
