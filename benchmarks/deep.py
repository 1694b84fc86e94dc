"""Deep scenes: BDPT against Mitsuba's ``path`` where paths are long, and kernel reuse.

    python -m benchmarks.deep                      # 256x256, both scenes, ~5 minutes
    python -m benchmarks.deep --res 128 --spp 16   # quicker
    python -m benchmarks.deep --kernels-only

Scenes: scenes/deep-box.xml (the Cornell box with albedo 0.9, max_depth 65) and
scenes/envmap-open.xml (objects under an environment map, max_depth -1).  For each:

* time at equal spp, bdpt / path, every render with a seed never used before in the
  process (what real renders meet: a kernel a new seed needs is compiled then), for
  fixed BDPT ("bdpt-power") and the default "auto" budgets;
* error at equal time: relative MSE against a 16x-spp path reference, bdpt at
  ``--spp`` and path at as many spp as fit in bdpt's time, averaged over seeds.

Kernel reuse (``--kernels-only`` runs just this): kernels compiled by a second render
with a new seed, a new spp and a new film size, counted with Dr.Jit's kernel history,
and the first render's compile time in a fresh process with an empty kernel cache.
"""
from __future__ import annotations

import argparse
import itertools
import json
import time

import numpy as np

from . import common as C
from .throughput import cold_compile

SCENES = {"deep-box": ("deep-box.xml", 65), "envmap-open": ("envmap-open.xml", -1)}
_seeds = itertools.count(1_000_003, 7919)      # never reused within a run


def load(name: str, res: int):
    from bdpt_drjit import support
    file, depth = SCENES[name]
    return support.load_file(C.ROOT / "scenes" / file, resx=res, resy=res, max_depth=depth), depth


def equal_spp(name: str, res: int, spp: int, repeats: int) -> dict:
    """Median seconds per render (compile included: fresh seeds), and the ratios."""
    scene, depth = load(name, res)
    times = {m: [] for m in ("bdpt-power", "bdpt-auto", "path")}
    for m in times:                                    # warm-up (first compile)
        C.render(C.METHODS[m], scene, spp, next(_seeds), depth)
    for _ in range(repeats):
        for m in times:
            times[m].append(C.render(C.METHODS[m], scene, spp, next(_seeds), depth).timing.wall)
    med = {m: C.median(v) for m, v in times.items()}
    return {"scene": name, "res": res, "spp": spp, "seconds": med,
            "ratio_power": med["bdpt-power"] / med["path"], "ratio_auto": med["bdpt-auto"] / med["path"]}


def equal_time(name: str, res: int, spp: int, seeds: int) -> dict:
    """Relative MSE at equal time against a path reference (16x spp, 4 seeds)."""
    scene, depth = load(name, res)
    ref = np.mean([C.render(C.METHODS["path"], scene, 16 * spp, next(_seeds), depth).image
                   for _ in range(4)], axis=0)
    out = {"scene": name, "res": res, "spp": spp}
    path_per_spp = C.render(C.METHODS["path"], scene, spp, next(_seeds), depth).timing.wall / spp
    for m in ("bdpt-power", "bdpt-auto"):
        errs, path_errs, secs = [], [], []
        for _ in range(seeds):
            r = C.render(C.METHODS[m], scene, spp, next(_seeds), depth)
            errs.append(C.rel_mse(r.image, ref))
            secs.append(r.timing.wall)
            n = max(1, int(round(r.timing.wall / path_per_spp)))
            path_errs.append(C.rel_mse(C.render(C.METHODS["path"], scene, n, next(_seeds), depth).image, ref))
        out[m] = {"rel_mse": float(np.mean(errs)), "path_rel_mse": float(np.mean(path_errs)),
                  "ratio": float(np.mean(errs) / np.mean(path_errs)), "seconds": C.median(secs)}
    return out


def kernels(res: int, spp: int) -> dict:
    """Kernels compiled by a second render: new seed, new spp, new film size."""
    import bdpt_drjit
    import drjit as dr
    out = {}
    for name in SCENES:
        scene, depth = load(name, res)
        other, _ = load(name, res + res // 2)

        def count(sc, n):
            dr.kernel_history()
            r = bdpt_drjit.render(sc, spp=n, seed=next(_seeds), max_depth=depth)
            hist = list(r.kernel_history) + dr.kernel_history()
            jit = [e for e in hist if e["type"] == dr.KernelType.JIT]
            miss = [e for e in jit if not e.get("cache_hit", 1) or e.get("cache_disk", 0)]
            return {"compiled": len(miss), "largest_ops": max([e.get("operation_count", 0) for e in miss], default=0),
                    "seconds": sum(e.get("backend_time", 0.0) for e in miss) / 1000}
        count(scene, spp)
        out[name] = {"new seed": count(scene, spp), "new spp": count(scene, spp + 3),
                     "new film size": count(other, spp)}
    return out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--res", type=int, default=256)
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--kernels-only", action="store_true")
    p.add_argument("--json", help="also write the results here")
    args = p.parse_args(argv)
    import drjit as dr
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    res = {"machine": C.machine_info() if hasattr(C, "machine_info") else {},
           "kernels": kernels(min(args.res, 64), 4)}
    C.log(json.dumps(res["kernels"], indent=1))
    cold = {m: cold_compile(m, C.ROOT / "scenes" / "cornell-box.xml", 64, 64, 4, 8)
            for m in ("bdpt-power", "path")}
    res["cold_compile"] = {m: {k: v for k, v in c.items() if k in ("first_compile", "first_wall", "error")}
                           for m, c in cold.items()}
    C.log(json.dumps(res["cold_compile"], indent=1))
    if not args.kernels_only:
        res["equal_spp"] = [equal_spp(n, args.res, args.spp, args.repeats) for n in SCENES]
        for r in res["equal_spp"]:
            C.log("%s: bdpt-power / path %.2fx, bdpt-auto / path %.2fx at %d spp (%s)"
                  % (r["scene"], r["ratio_power"], r["ratio_auto"], r["spp"], r["seconds"]))
        res["equal_time"] = [equal_time(n, args.res, args.spp, args.seeds) for n in SCENES]
        for r in res["equal_time"]:
            C.log("%s: equal-time rel. MSE / path: bdpt-power %.2f, bdpt-auto %.2f"
                  % (r["scene"], r["bdpt-power"]["ratio"], r["bdpt-auto"]["ratio"]))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(res, f, indent=1, default=str)


if __name__ == "__main__":
    main()
