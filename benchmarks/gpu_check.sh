#!/usr/bin/env bash
# The GPU checks of the open issues, in one run (a lent GPU machine's time is short):
# the tests under cuda_ad_rgb, then the benchmarks at 1024x1024.  Each step's output
# goes to $OUT/NAME.log (default ./gpu-out; a lent machine's $OUT returns 8 files: name 7
# steps at most) and the run goes on after a failed step.  Steps run in
# the order STEPS names them, each within its own limit and all within DEADLINE seconds
# (a lease is 15 minutes): a step that would start with under 30 s left is skipped.
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
RES=${RES:-1024}; SPP=${SPP:-128}; OUT=${OUT:-gpu-out}; DEADLINE=${DEADLINE:-540}
STEPS=${STEPS:-calibrate pricing efficiency links deferred transfer tests passes small small-first host frozen profile breakdown divergence throughput memory mlt glass}
EXT=${BDPT_SHARED:-../shared}/scenes/external
mkdir -p "$OUT"
step() {   # step NAME SECONDS COMMAND...: run within its limit and the deadline, log, report
    local name=$1 limit=$2; shift 2
    local left=$((DEADLINE - SECONDS))
    if [ "$left" -lt 30 ]; then
        echo "== $name: skipped, ${left} s left" | tee -a "$OUT/summary.txt"; return
    fi
    [ "$limit" -gt "$left" ] && limit=$left
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
passes() {   # samples per second against path (issue 29: Veach's BDPT in Veach's room and at
             # max_depth 65; the Cornell box is the frozen step's), and vcm's time per
             # sample against Veach's BDPT (issue 30's target: <= 1.5x)
    $PY -m benchmarks.gpu_passes --res "$RES" --spp 16 --repeats 2 --max-depth 7 \
        --scene "$EXT/veach-bidir/scene.xml" --methods veach,default
    $PY -m benchmarks.gpu_passes --res "$RES" --spp 4 --repeats 1 --methods veach,vcm
    $PY -m benchmarks.gpu_passes --res "$RES" --spp 4 --repeats 1 --max-depth 65 \
        --scene scenes/deep-box.xml --methods veach
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
frozen() {   # passes replaying recorded walks under CUDA (the default) against traced ones
             # (BDPT_FREEZE_CUDA=0): per-pass times at 1024x1024, and small renders
    for f in 0 1; do
        BDPT_FREEZE_CUDA=$f $PY -m benchmarks.gpu_passes --res "$RES" --spp 16 --repeats 2 \
            --methods veach,default
    done
    BDPT_FREEZE_CUDA=0 $PY -m benchmarks.small --seeds 8
}
transfer() {   # issue 28: how the calibration box's units price other scenes' walks
    for scene in cornell-diffuse camera-behind-glass veach-bidir; do
        $PY benchmarks/experiments/unit_transfer.py "$scene" --res "$RES" --spp 16
    done
}
links() {   # issue 29: Veach's BDPT with its connections in the camera walk (the default)
            # against deferred to a kernel of their own (connect.DEFERRED), samples per
            # second against path, each in its own process, the Cornell box and Veach's room
    for d in 0 1; do
        BDPT_DEFERRED_CONNECTIONS=$d $PY -m benchmarks.gpu_passes --res "$RES" --spp 16 \
            --repeats 2 --methods veach
        BDPT_DEFERRED_CONNECTIONS=$d $PY -m benchmarks.gpu_passes --res "$RES" --spp 16 \
            --repeats 2 --max-depth 7 --scene "$EXT/veach-bidir/scene.xml" --methods veach
    done
}
deferred() {   # issue 30: vcm's merge queries in the camera walk (the default) against
               # deferred to a kernel of their own (merge.DEFERRED), then with its
               # connections deferred too (connect.DEFERRED), each per sample against
               # Veach's BDPT in its own process
    for d in "0 0" "1 0" "1 1"; do
        set -- $d
        BDPT_DEFERRED_MERGES=$1 BDPT_DEFERRED_CONNECTIONS=$2 $PY -m benchmarks.gpu_passes \
            --res "$RES" --spp 4 --repeats 2 --methods veach,vcm
    done
}
efficiency() {   # issue 28: the default against path, and on the first two scenes what
                 # its decision estimated against what fixed budgets measure
    $PY -m benchmarks.efficiency --res "$RES" --spp "$SPP" --seeds 3 \
        --scenes cornell-diffuse,camera-behind-glass --budgets \
        "light_paths=0 connections=0;light_paths=0.5 connections=0;light_paths=1 connections=0"
    $PY -m benchmarks.efficiency --res "$RES" --spp "$SPP" --seeds 3 \
        --scenes cornell-light-up,veach-bidir
}
pricing() {   # issue 28: the decision's prices against fixed budgets' kernel time
    for scene in camera-behind-glass cornell-diffuse; do
        $PY benchmarks/experiments/pricing.py "$scene" --res "$RES" --spp 32
    done
}
export -f profile throughput passes breakdown divergence mlt frozen efficiency pricing deferred links transfer
export PY RES EXT SPP
declare -A LIMIT=([glass]=60 [host]=90 [pricing]=90 [calibrate]=90 [profile]=60 [throughput]=100 [passes]=120 [breakdown]=40
    [divergence]=90 [tests]=200 [frozen]=150 [deferred]=180 [links]=150 [transfer]=120 [mlt]=150 [efficiency]=160 [memory]=60
    [small]=120 [small-first]=120)
declare -A COMMAND=(
    [calibrate]="$PY -m bdpt_drjit calibrate --variant $BDPT_VARIANT"
    [tests]="$PY -m pytest -q -p no:cacheprovider -n ${JOBS:-12} --ignore tests/test_cluster.py -k 'not spectral_and_mono and not variant_switch and not specfilm'"
    [memory]="$PY -m benchmarks.memory --res $RES --mib 8192 --budget auto"
    [glass]="$PY -m benchmarks.gpu_passes --res $RES --spp 64 --repeats 2 --methods default --scene scenes/glass-pane.xml --timeline"
    [host]="$PY benchmarks/experiments/gpu_host.py --res $RES --spp 64"
    [small]="$PY -m benchmarks.small --seeds 8"
    [small-first]="$PY -m benchmarks.small --seeds 8 --first")
for name in $STEPS; do
    step "$name" "${LIMIT[$name]}" "${COMMAND[$name]:-$name}"
done
