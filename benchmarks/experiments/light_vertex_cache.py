"""Experiment (not part of the renderer): BDPT connecting each camera vertex to M
vertices drawn from a cache of all light vertices of the pass (LVC-BDPT, Davidovic
et al. 2014) instead of to every vertex of its own light subpath.

Needs the prototype patch beside this file, applied to a checkout:

    git apply benchmarks/experiments/light-vertex-cache.patch
    python -m benchmarks.experiments.light_vertex_cache --res 128 --spp 32 --seeds 6

For each scene and M (0 = Veach's BDPT, every vertex of the paired subpath) it
prints the median time of a render, the relative variance over the seeds
(mean over pixels of var / (mean^2 + 1e-2)) and the efficiency 1 / (time x variance),
each as a ratio to M = 0.  Results: benchmarks/RESULTS.md (session 4).
"""
import argparse
import time

import drjit as dr
import mitsuba as mi
import numpy as np

from benchmarks.scenes import SCENE_LIST
from bdpt_drjit.render import Renderer, Settings


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="cornell-diffuse,glass-caustic-area,veach-bidir,cornell-light-up")
    ap.add_argument("--connections", default="0,1,2")
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--seeds", type=int, default=6)
    a = ap.parse_args()
    if "connections" not in Settings.__dataclass_fields__:
        raise SystemExit("apply benchmarks/experiments/light-vertex-cache.patch first")
    ms = [int(x) for x in a.connections.split(",")]
    for name in a.scenes.split(","):
        spec = next(s for s in SCENE_LIST if s.name == name)
        ok, why = spec.available()
        if not ok:
            print("%s: skipped (%s)" % (name, why))
            continue
        w, h, _ = spec.resolution(a.res)
        scene = spec.load(w, h)

        def render(seed, m):
            r = Renderer(scene, spp=a.spp, seed=seed, max_depth=spec.max_depth,
                         connections=m, samples_per_pass=a.spp // 2)
            while not r.done:
                r.run_pass()
            img = r.tensor()
            dr.eval(img)
            dr.sync_thread()
            return np.array(img)[..., :3]

        for m in ms:
            render(0, m)                        # compile
        runs = {m: [] for m in ms}
        for seed in range(1, a.seeds + 1):
            for m in ms:                        # interleaved: same machine state
                t0 = time.perf_counter()
                img = render(seed, m)
                runs[m].append((time.perf_counter() - t0, img))
        base = None
        for m in ms:
            imgs = np.stack([x[1] for x in runs[m]])
            mean = imgs.mean(0)
            rv = float(np.mean(imgs.var(0, ddof=1) / (mean ** 2 + 1e-2)))
            t = float(np.median([x[0] for x in runs[m]]))
            base = base or (t, rv)
            print("%-20s M=%d  time %.3f s (x%.2f)  rel.var %.3e (x%.2f)  efficiency x%.2f  mean %.5f"
                  % (name, m, t, t / base[0], rv, rv / base[1], base[0] * base[1] / (t * rv),
                     mean.mean()), flush=True)


if __name__ == "__main__":
    mi.set_variant("llvm_ad_rgb")
    main()
