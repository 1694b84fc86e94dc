"""Where PSSMLT's time goes (issue 31): the bootstrap's time, time per mutation (and
the BDPT evaluation's share of an iteration) against bdpt's time per sample, and the
acceptance of small and large steps.

    python -m benchmarks.mlt_diag [SCENE] [SECONDS] [CHAINS]

64x64, max_depth 8; two pssmlt runs of SECONDS (seeds 1, 2), then the default bdpt and
Veach's BDPT for as long.  Times are wall times on whatever load the machine has."""
import sys
import time

import drjit as dr
import numpy as np

import bdpt_drjit  # noqa: F401
from bdpt_drjit import mlt, support
from bdpt_drjit.render import Renderer


def _timed(obj, name, totals):
    """Wraps obj.name to add its synchronized wall time to totals[name]."""
    f = getattr(obj, name)

    def g(*a, **k):
        dr.sync_thread()
        t = time.perf_counter()
        r = f(*a, **k)
        dr.sync_thread()
        totals[name] = totals.get(name, 0.0) + time.perf_counter() - t
        return r
    setattr(obj, name, g)


def main():
    path = sys.argv[1] if len(sys.argv) > 1 else "scenes/door-ajar.xml"
    seconds = float(sys.argv[2]) if len(sys.argv) > 2 else 8.0
    chains = int(sys.argv[3]) if len(sys.argv) > 3 else 16384
    scene = support.load_file(path, resx=64, resy=64)
    for seed in (1, 2):
        totals, times = {}, []
        r = mlt.MLTRenderer(scene, seed=seed, max_depth=8, mutations_per_pixel=1 << 16,
                            chains=chains)
        _timed(r, "evaluate", totals)
        while r.time < seconds:
            t = time.perf_counter()
            r.run_iteration()
            times.append(time.perf_counter() - t)
        small, large = r.step_acceptance()
        print("pssmlt seed %d: bootstrap %.2f s (%d samples, %d start states), %d iterations x "
              "%d chains, iteration median %.1f ms, %.2f us per mutation, evaluation %.0f%% "
              "of the iterations; acceptance small %.3f, large %.3f"
              % (seed, r.bootstrap_time, r.bootstrap_samples, r.start_states, r.iterations_done,
                 r.chains, 1e3 * np.median(times), 1e6 * np.median(times) / r.chains,
                 100 * totals["evaluate"] / sum(times), small, large))
    for kw in ({}, dict(light_paths=1, connections="all")):
        rr = Renderer(scene, spp=1 << 16, seed=5, max_depth=8, samples_per_pass=4, **kw)
        while not (rr.time >= seconds and rr.at_round_end):
            rr.run_pass()
        res = rr.result()
        print("bdpt %s: %.2f s, %d spp, %.2f us per sample"
              % (kw or "(auto)", res.time, res.spp, 1e6 * res.time / (res.spp * 64 * 64)))


if __name__ == "__main__":
    main()
