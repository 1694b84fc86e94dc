"""What the decision prices against what fixed budgets cost (issue 28): the pilot's
counts of a scene times unit costs calibrated in the same process, as a ratio to path
tracing's price, beside the kernel time of renders of those budgets over `path`'s.

    python benchmarks/experiments/pricing.py camera-behind-glass --res 256 --spp 32
    BDPT_VARIANT=cuda_ad_rgb python benchmarks/experiments/pricing.py cornell-diffuse --res 1024
"""
import argparse
import statistics
import sys
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks import common as C                                     # noqa: E402,F401
import drjit as dr                                                     # noqa: E402
import mitsuba as mi                                                   # noqa: E402
from benchmarks.scenes import SCENES                                   # noqa: E402


def kernel_ms(render, seeds=3) -> float:
    """Median kernel time of ``render(seed)`` over fresh seeds, the first left out."""
    out = []
    for seed in range(seeds):
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history()
            render(seed)
            dr.sync_thread()
            out.append(sum(e.get("execution_time", 0.0) for e in dr.kernel_history()
                           if e["type"] == dr.KernelType.JIT))
    return statistics.median(out[1:])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--spp", type=int, default=32)
    a = ap.parse_args()
    from bdpt_drjit import units
    from bdpt_drjit.budgets import PATH_TRACING, Budget
    from bdpt_drjit.render import Renderer, calibrate
    spec = SCENES[a.scene]
    w, h, _ = spec.resolution(a.res)
    scene = spec.load(w, h)
    units.save = lambda *args, **kw: None               # this process's units only
    r = Renderer(scene, spp=a.spp, seed=1, max_depth=spec.max_depth)
    r.run_pass()
    costs = replace(r.pilot.costs, units=calibrate(3), path_tracer=True)
    print(costs.describe())
    print(costs.units.describe())
    path = mi.load_dict({"type": "path", "max_depth": spec.max_depth})
    path_ms = kernel_ms(lambda seed: dr.eval(mi.render(scene, integrator=path, spp=a.spp,
                                                      seed=seed)))

    def bdpt(seed, **budget):
        rr = Renderer(scene, spp=a.spp, seed=seed, max_depth=spec.max_depth, **budget)
        while not rr.done:
            rr.run_pass()
    print("%s %dx%d %d spp: path %.1f ms of kernels" % (a.scene, w, h, a.spp, path_ms))
    for ratio in (0.25, 0.5, 1.0):
        ms = kernel_ms(lambda seed: bdpt(seed, light_paths=ratio, connections=0))
        print("light_paths=%s connections=0: priced %.2fx path, took %.2fx (%.1f ms)"
              % (ratio, costs.of(Budget(ratio, 0)) / costs.of(PATH_TRACING), ms / path_ms, ms))


if __name__ == "__main__":
    main()
