"""The merge queries' cost in the camera walk, and the hash grid's build, per pass: two
Renderers of one fixed budget, without merging and with it, their passes run in turn
in one process with Dr.Jit's kernel history on; per pass the camera walk's kernel (the
one of most operations), the light walk's (the other large one) and every launch
between them (with merging: the grid's build, merge.HashGrid.build); medians over the
passes after a warm one.

    python benchmarks/experiments/merge_walk.py                       # Cornell box 256x256, Veach's budget
    python benchmarks/experiments/merge_walk.py --scene benchmarks/scene_files/sds.xml \\
        --res 128 --spp 4 --budget "light_paths=0.25 connections=0"

``--constant-merge`` replaces the merge's body (BSDF, MIS weight) by a constant: what
is left is the query's scan of its cells' items.  The ratio of the two camera walks
is the figure to compare between trees (the load moves absolute times): run trees in
turn.  ``BDPT_VARIANT=cuda_ad_rgb`` measures the GPU.
"""
import argparse
import os
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import drjit as dr            # noqa: E402
import mitsuba as mi          # noqa: E402

mi.set_variant(os.environ.get("BDPT_VARIANT", "llvm_ad_rgb"))

from benchmarks.throughput import DEFAULT_SCENE, load_scene    # noqa: E402
from bdpt_drjit import merge                                   # noqa: E402
from bdpt_drjit.render import Renderer                         # noqa: E402


def _pass(r: Renderer) -> dict:
    """One pass's camera walk, light walk and in-between launches, in ms."""
    dr.sync_thread()
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history()
        r.run_pass()
        dr.sync_thread()
        history = dr.kernel_history()
    kernels = [i for i, e in enumerate(history) if e["type"] == dr.KernelType.JIT]
    light, cam = sorted(sorted(kernels, key=lambda i: -(history[i].get("operation_count")
                                                         or 0))[:2])
    return {"camera": history[cam]["execution_time"], "light": history[light]["execution_time"],
            "between": sum(e.get("execution_time", 0.0) for e in history[light + 1:cam]),
            "kernels": sum(history[i].get("execution_time", 0.0) for i in kernels)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=str(DEFAULT_SCENE))
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--spp", type=int, default=1, help="samples per pixel per pass")
    ap.add_argument("--passes", type=int, default=4, help="measured, after a warm one")
    ap.add_argument("--max-depth", type=int, default=8)
    ap.add_argument("--budget", default="light_paths=1 connections=all")
    ap.add_argument("--constant-merge", action="store_true")
    a = ap.parse_args()
    if a.constant_merge:
        merge._merge_one = lambda ctx, pos, active, state, v: dr.select(
            active, mi.Spectrum(1e-9), 0.0)
    scene = load_scene(a.scene, a.res, a.res, a.max_depth)
    budget = dict(kv.split("=") for kv in a.budget.split())
    renderers = {m: Renderer(scene, spp=a.spp * (a.passes + 1), seed=1, max_depth=a.max_depth,
                             samples_per_pass=a.spp, merging=m, **budget)
                 for m in (False, True)}
    runs = {m: [] for m in renderers}
    for i in range(a.passes + 1):
        for m, r in renderers.items():
            p = _pass(r)
            if i:
                runs[m].append(p)
    lanes = a.res * a.res * a.spp
    print("%s, %s, %dx%d, %d spp per pass, %s%s; medians of %d passes"
          % (mi.variant(), a.scene, a.res, a.res, a.spp, a.budget,
             ", merge body constant" if a.constant_merge else "", a.passes))
    med = {m: {k: statistics.median(p[k] for p in runs[m]) for k in runs[m][0]} for m in runs}
    for m in runs:
        print("merging=%-5s camera walk %7.1f ms (%5.0f ns/lane)  light walk %6.1f ms  "
              "between the walks %6.2f ms  all kernels %7.1f ms"
              % (m, med[m]["camera"], 1e6 * med[m]["camera"] / lanes, med[m]["light"],
                 med[m]["between"], med[m]["kernels"]))
    print("camera walk with merging / without: %.2f" % (med[True]["camera"] / med[False]["camera"]))


if __name__ == "__main__":
    main()
