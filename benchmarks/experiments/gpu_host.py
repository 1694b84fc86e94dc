"""Where a default render's host time goes on a GPU (issue 28): renders of the glass pane
and the Cornell box pass by pass (wall, kernels, launches, kernels compiled), ``path``
alone and interleaved with them, and a profile of the pilot pass's Python.

    BDPT_VARIANT=cuda_ad_rgb python benchmarks/experiments/gpu_host.py --res 1024
"""
import argparse
import cProfile
import io
import pstats
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
import drjit as dr                                                 # noqa: E402
import mitsuba as mi                                               # noqa: E402
from benchmarks.throughput import load_scene                       # noqa: E402


def renderer(scene, spp, seed):
    from bdpt_drjit.render import Renderer
    return Renderer(scene, spp=spp, seed=seed, max_depth=8)


def timeline(scene, spp, seed, label):
    r = renderer(scene, spp, seed)
    start = time.perf_counter()
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history()
        while not r.done:
            i, before = r.passes_done, time.perf_counter()
            r.run_pass()
            dr.sync_thread()
            h = [e for e in dr.kernel_history() if e["type"] == dr.KernelType.JIT]
            miss = [e for e in h if not e["cache_hit"]]
            print("%s pass %d %-26s %-30s %7.1f ms wall %6.1f ms kernels %3d launches "
                  "%d compiled (%.1f ms)" % (label, i, r.plan[i], str(r.budget)[:30],
                  1e3 * (time.perf_counter() - before),
                  sum(e["execution_time"] for e in h), len(h), len(miss),
                  sum(e["codegen_time"] + e["backend_time"] for e in miss)), flush=True)
    print("%s whole %.1f ms" % (label, 1e3 * (time.perf_counter() - start)), flush=True)


def path(scene, spp, seed):
    start = time.perf_counter()
    dr.eval(mi.render(scene, integrator=mi.load_dict({"type": "path", "max_depth": 8}),
                      spp=spp, seed=seed))
    dr.sync_thread()
    return 1e3 * (time.perf_counter() - start)


def bdpt(scene, spp, seed):
    start = time.perf_counter()
    r = renderer(scene, spp, seed)
    while not r.done:
        r.run_pass()
    dr.sync_thread()
    return 1e3 * (time.perf_counter() - start)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--res", type=int, default=1024)
    ap.add_argument("--spp", type=int, default=64)
    a = ap.parse_args()
    for name in ("scenes/glass-pane.xml", "scenes/cornell-box.xml"):
        scene = load_scene(name, a.res, a.res, 8)
        print("==", mi.variant(), name, a.res, a.spp, flush=True)
        bdpt(scene, a.spp, 1), path(scene, a.spp, 1), bdpt(scene, a.spp, 2)
        for s in range(3):
            timeline(scene, a.spp, 50 + s, "tl%d" % s)
        print("path alone: %s ms" % ["%.0f" % path(scene, a.spp, 60 + s) for s in range(3)])
        print("bdpt alone: %s ms" % ["%.0f" % bdpt(scene, a.spp, 70 + s) for s in range(3)])
        print("interleaved bdpt/path: %s ms" % ["%.0f/%.0f" % (bdpt(scene, a.spp, 80 + s),
              path(scene, a.spp, 90 + s)) for s in range(3)], flush=True)
        flushed = []
        for s in range(3):
            dr.flush_malloc_cache()
            flushed.append(path(scene, a.spp, 100 + s))
        print("path after a flushed malloc cache: %s ms" % ["%.0f" % t for t in flushed])
        if name.endswith("glass-pane.xml"):
            pr = cProfile.Profile()
            r = renderer(scene, a.spp, 120)
            pr.enable()
            r.run_pass()
            dr.sync_thread()
            pr.disable()
            out = io.StringIO()
            pstats.Stats(pr, stream=out).sort_stats("cumulative").print_stats(30)
            print("\n".join(out.getvalue().splitlines()[:60]))
            out = io.StringIO()
            pstats.Stats(pr, stream=out).sort_stats("tottime").print_stats(20)
            print("\n".join(out.getvalue().splitlines()[:40]), flush=True)


if __name__ == "__main__":
    main()
