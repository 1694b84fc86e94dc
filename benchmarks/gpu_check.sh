#!/usr/bin/env bash
# The GPU checks of the open issues, in one run (a lent GPU machine's time is short):
# the tests under cuda_ad_rgb, then the benchmarks at 1024x1024.  Each step's output
# goes to $OUT (default ./gpu-out) and the run goes on after a failed step.
#   BDPT_SHARED=<shared> bash benchmarks/gpu_check.sh            # on the GPU machine
#   VARIANT=llvm_ad_rgb RES=64 SPP=8 STEPS="efficiency profile" bash benchmarks/gpu_check.sh
#                                                                # a dry run on a CPU
set -u
cd "$(dirname "$0")/.."
export BDPT_VARIANT=${VARIANT:-cuda_ad_rgb}
RES=${RES:-1024}; SPP=${SPP:-128}; OUT=${OUT:-gpu-out}
STEPS=${STEPS:-calibrate tests efficiency profile throughput}
mkdir -p "$OUT"
step() {   # step NAME SECONDS COMMAND...: run with a time limit, log, report
    local name=$1 limit=$2; shift 2
    case " $STEPS " in *" $name "*) ;; *) return ;; esac
    local start=$SECONDS
    timeout "$limit" "$@" > "$OUT/$name.log" 2>&1
    echo "== $name: exit $? in $((SECONDS - start)) s" | tee -a "$OUT/summary.txt"
    tail -n 25 "$OUT/$name.log"
}
step calibrate 120 python -m bdpt_drjit calibrate --variant "$BDPT_VARIANT"
step tests 240 python -m pytest -q -x --ignore tests/test_cluster.py \
    -k "not spectral_and_mono and not variant_switch and not specfilm and not slow"
step efficiency 240 python -m benchmarks.efficiency --res "$RES" --spp "$SPP" --seeds 3
step profile 60 python -m benchmarks.profile_pass --res "$((RES / 4))" --spp 16
step throughput 120 python -m benchmarks.throughput --no-cold --res "$((RES / 4))"
