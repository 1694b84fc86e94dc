"""The pilot's estimates against measured variance (issue 28): per budget, the pilot's
summed relative second moment and price (the mean over 8 pilots), beside the relative
variance per sample that renders of it measure across seeds (light_paths=0: Mitsuba's
path, which the default's path tracing runs).

    python benchmarks/experiments/moments.py cornell-diffuse --res 64 --spp 16 --seeds 24
"""
import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks import common as C                                     # noqa: E402,F401
import mitsuba as mi                                                   # noqa: E402
import numpy as np                                                     # noqa: E402
from benchmarks.scenes import SCENES                                   # noqa: E402

BUDGETS = ["light_paths=0 connections=0", "light_paths=0.25 connections=0",
           "light_paths=0.5 connections=0", "light_paths=1 connections=0"]


def pilot_estimates(scene, max_depth) -> dict:
    """Budget: (mean moment, mean price) over 8 pilots of a 64-spp render."""
    from bdpt_drjit.render import Renderer
    rows = {b: [] for b in BUDGETS}
    for seed in range(1, 9):
        r = Renderer(scene, spp=64, seed=seed, max_depth=max_depth)
        r.run_pass()
        for b, cost, moment, _ in r.pilot.first.table:
            rows.get(str(b), []).append((moment, cost))
    return {b: np.mean(v, axis=0) for b, v in rows.items()}


def luminances(scene, budget: str, spp: int, seeds: int, max_depth: int) -> list:
    import bdpt_drjit
    if budget == BUDGETS[0]:
        path = mi.load_dict({"type": "path", "max_depth": max_depth})
        return [np.array(mi.render(scene, integrator=path, spp=spp, seed=s))[..., :3].mean(-1)
                for s in range(seeds)]
    kw = dict(kv.split("=") for kv in budget.split())
    return [bdpt_drjit.render(scene, spp=spp, seed=s, max_depth=max_depth,
                              **kw).image[..., :3].mean(-1) for s in range(seeds)]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--seeds", type=int, default=24)
    a = ap.parse_args()
    spec = SCENES[a.scene]
    w, h, _ = spec.resolution(a.res)
    scene = spec.load(w, h)
    estimates = pilot_estimates(scene, spec.max_depth)
    images = {b: luminances(scene, b, a.spp, a.seeds, spec.max_depth) for b in BUDGETS}
    mean = np.mean([np.mean(v, axis=0) for v in images.values()], axis=0)
    floor = 1e-2 * np.mean(mean) ** 2         # optimizer.DARK's floor
    for b in BUDGETS:
        variance = np.var(np.stack(images[b]), axis=0, ddof=1) * a.spp
        relative = np.mean(variance / np.maximum(mean ** 2, floor))
        moment, cost = estimates[b]
        print("%-32s pilot: moment %.3f, price %.3g s;  measured: relative variance per "
              "sample %.3f" % (b, moment, cost, relative))


if __name__ == "__main__":
    main()
