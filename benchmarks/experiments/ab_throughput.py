"""A/B throughput of two checkouts of this engine against Mitsuba's path, one process
per run (interleave runs of A and B: this machine's load comes and goes).

    git worktree add /tmp/ab-old <commit>
    for r in 1 2 3; do for e in /tmp/ab-old .; do
        python benchmarks/experiments/ab_throughput.py $e scenes/cornell-box.xml 256 16 8 3
    done; done

Prints one JSON line per run: samples/s of full BDPT (light_paths=1 connections=all)
and of the default budget, each as a ratio to path's (medians of ``repeats`` renders
with fresh seeds, compile time excluded), and the kernels each BDPT render compiled.
"""
import json
import sys
import time

import numpy as np


def timed(render, seed):
    """Wall seconds minus the compile time of kernels compiled inside, and how many."""
    import drjit as dr
    dr.kernel_history()
    t = time.perf_counter()
    render(seed)
    dr.sync_thread()
    wall = time.perf_counter() - t
    jit = [e for e in dr.kernel_history() if e["type"] == dr.KernelType.JIT]
    compiled = [e for e in jit if not e.get("cache_hit", 1) or e.get("cache_disk", 0)]
    return wall - sum(e.get("backend_time", 0) for e in compiled) / 1000, len(compiled)


def main():
    sys.path.insert(0, sys.argv[1])          # the checkout to measure, before importing it
    import bdpt_drjit
    import drjit as dr
    import mitsuba as mi
    scene_file, res, spp, md = sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
    repeats = int(sys.argv[6]) if len(sys.argv) > 6 else 3
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    scene = mi.load_file(scene_file, resx=res, resy=res, optimize=False)   # as support.load_file
    full = lambda s: bdpt_drjit.render(scene, spp=spp, seed=s, max_depth=md, light_paths=1,  # noqa: E731
                                       connections="all")
    auto = lambda s: bdpt_drjit.render(scene, spp=spp, seed=s, max_depth=md)  # noqa: E731
    path = lambda s: np.array(mi.render(scene, integrator=mi.load_dict(  # noqa: E731
        {"type": "path", "max_depth": md}), spp=spp, seed=s))
    for f in (full, auto, path):
        f(1000)                                            # warm-up
    out = {"full": [], "auto": [], "path": [], "compiled": []}
    for i in range(repeats):
        t, n = timed(full, 2000 + i)
        out["full"].append(t)
        out["compiled"].append(n)
        out["auto"].append(timed(auto, 3000 + i)[0])
        out["path"].append(timed(path, 2000 + i)[0])
    p = np.median(out["path"])
    print(json.dumps({"engine": sys.argv[1], "full_ratio": p / np.median(out["full"]),
                      "auto_ratio": p / np.median(out["auto"]), "compiled": out["compiled"]}))


if __name__ == "__main__":
    main()
