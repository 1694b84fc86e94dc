"""A/B of the default ("auto") budget of two checkouts of this engine on one suite
scene: time and relative MSE against the suite's cached reference, one process per run
(interleave runs of A and B: this machine's load comes and goes).

    git worktree add /tmp/ab-old <commit>
    python -m benchmarks.run ... --out /tmp/suite     # once: caches the references
    for r in 1 2; do for e in . /tmp/ab-old; do
        python benchmarks/experiments/ab_default.py $e cornell-diffuse 256 4 /tmp/suite/refs
    done; done

Prints one JSON line per run: the median time of ``renders`` renders with seeds 1000,
1001, ... (after one warm-up render), their mean relative MSE (the suite's metric), the
efficiency 1 / (time x error), the budgets the renders ended with, Mitsuba's ``path``
at the same spp and seeds in the same process (median time, and the ratio), and the
kernels either compiled after the warm-up (Dr.Jit's kernel history).  External scenes
need BDPT_SHARED; without a cached reference they use the scene's own EXR reference.
"""
import glob
import json
import statistics
import sys
import time


def main(repo: str, name: str, spp: int, renders: int, refs: str) -> None:
    sys.path.insert(0, repo)
    import numpy as np
    from benchmarks.scenes import SCENES
    import bdpt_drjit
    import drjit as dr
    import mitsuba as mi
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    spec = SCENES[name]
    width, height, factor = spec.resolution(128)
    scene = spec.load(width, height)
    cached = glob.glob("%s/%s_%dx%d_*.npy" % (refs, name, width, height))
    ref = (np.load(cached[0]) if cached else np.asarray(spec.exr_reference(factor)))[..., :3]
    path = mi.load_dict({"type": "path", "max_depth": spec.max_depth})
    bdpt_drjit.render(scene, spp=spp, seed=1, max_depth=spec.max_depth)       # kernels
    dr.eval(mi.render(scene, integrator=path, spp=spp, seed=1))
    dr.kernel_history()
    times, path_times, errors, budgets = [], [], [], set()
    for k in range(renders):
        start = time.perf_counter()
        res = bdpt_drjit.render(scene, spp=spp, seed=1000 + k, max_depth=spec.max_depth)
        times.append(time.perf_counter() - start)
        img = res.image[..., :3]
        errors.append(float(np.mean((img - ref) ** 2 / (ref ** 2 + 1e-2))))
        budgets.add(res.stats["budget"])
        start = time.perf_counter()
        dr.eval(mi.render(scene, integrator=path, spp=spp, seed=1000 + k))
        dr.sync_thread()
        path_times.append(time.perf_counter() - start)
    compiled = [e for e in dr.kernel_history()
                if e["type"] == dr.KernelType.JIT and not e.get("cache_hit", 1)]
    t, err = statistics.median(times), statistics.mean(errors)
    print(json.dumps({"repo": repo, "scene": name, "spp": spp, "time": t, "relmse": err,
                      "efficiency": 1.0 / (t * err), "budgets": sorted(budgets),
                      "path_time": statistics.median(path_times),
                      "time_over_path": t / statistics.median(path_times),
                      "kernels_compiled": len(compiled)}))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5])
