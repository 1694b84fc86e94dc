"""What the decision prices a budget at (optimizer.Costs, from a ``vcm`` render's pilot
counts and this machine's calibrated unit costs) against what it renders in: fixed
budgets, with and without merging, on one of SmallVCM's boxes (benchmarks.smallvcm),
interleaved per seed after a warm-up; medians of wall and kernel seconds (Dr.Jit's
kernel history), each as a ratio to the first budget's.

    python benchmarks/experiments/merge_price.py lg_c 128 5

The merging budget renders at ``--radius`` (world units; the decision's candidates
merge at the pilot's radius or a quarter of it, Budget.radius_scale).  Its many small
passes (merge.PASS_LANES) launch more kernels than the others, so its ratio grows with
the machine's load: note the load average printed.
"""
import argparse
import os
import statistics
import sys
import time
from pathlib import Path

BUDGETS = ({"light_paths": 0.25, "connections": 0},
           {"light_paths": 0.25, "connections": 0, "merging": True},
           {"light_paths": 0.5, "connections": 1})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", help="bs_c, lg_c or bs_p (benchmarks.smallvcm)")
    ap.add_argument("spp", type=int)
    ap.add_argument("seeds", type=int)
    ap.add_argument("--radius", type=float, default=0.01)
    a = ap.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))      # this checkout
    import drjit as dr
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    import bdpt_drjit
    from bdpt_drjit.budgets import Budget
    from bdpt_drjit.render import Renderer
    from benchmarks import smallvcm
    scene = smallvcm.build_scene(a.scene)

    pilot = Renderer(scene, spp=a.spp, seed=1, max_depth=10, merging=True)
    while not pilot.done:
        pilot.run_pass()
    costs = pilot.pilot.costs
    fixed = [Budget(b["light_paths"], b["connections"], merging=b.get("merging", False),
                    radius_scale=a.radius / pilot.merge_radius) for b in BUDGETS]
    priced = [costs.of(b) / costs.of(fixed[0]) for b in fixed]

    def run(seed, settings):
        extra = {"radius": a.radius} if settings.get("merging") else {}
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history()
            start = time.perf_counter()
            bdpt_drjit.render(scene, spp=a.spp, seed=seed, max_depth=10, **settings, **extra)
            wall = time.perf_counter() - start
            kernel = sum(e.get("execution_time", 0.0) for e in dr.kernel_history()
                         if e["type"] == dr.KernelType.JIT) / 1000.0
        return wall, kernel

    for settings in BUDGETS:
        run(0, settings)                                                # kernels
    times = [([], []) for _ in BUDGETS]
    for seed in range(1, a.seeds + 1):
        order = range(len(BUDGETS)) if seed % 2 else reversed(range(len(BUDGETS)))
        for i in order:
            for column, value in zip(times[i], run(seed, BUDGETS[i])):
                column.append(value)
    print("%s, %d spp, %d seeds, load average %.1f at the end; counts: %s; units: %s"
          % (a.scene, a.spp, a.seeds, os.getloadavg()[0], costs.describe(), costs.units.describe()))
    wall0, kernel0 = (statistics.median(c) for c in times[0])
    for b, p, (wall, kernel) in zip(fixed, priced, times):
        w, k = statistics.median(wall), statistics.median(kernel)
        print("  %-60s priced %.2f  wall %.2f s (%.2f)  kernels %.2f s (%.2f)"
              % (b, p, w, w / wall0, k, k / kernel0))


if __name__ == "__main__":
    main()
