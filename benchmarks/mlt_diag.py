"""Where PSSMLT's time goes (issue 31): bootstrap share, time per mutation against
bdpt's time per sample, acceptance of small and large steps, stage times."""
import sys, time
import numpy as np
import drjit as dr
import mitsuba as mi
import bdpt_drjit  # noqa
from bdpt_drjit import mlt, pss
from bdpt_drjit.render import Renderer

scene_path = sys.argv[1] if len(sys.argv) > 1 else "scenes/door-ajar.xml"
seconds = float(sys.argv[2]) if len(sys.argv) > 2 else 8
chains = int(sys.argv[3]) if len(sys.argv) > 3 else 16384
door = "door" in scene_path
scene = mi.load_file(scene_path, resx=64, resy=64, **({"gap_start": 0.45} if door else {}))
T = {}

def timed(obj, name, key):
    f = getattr(obj, name)
    def g(*a, **k):
        dr.sync_thread(); t = time.perf_counter()
        r = f(*a, **k); dr.sync_thread()
        T[key] = T.get(key, 0) + time.perf_counter() - t
        return r
    setattr(obj, name, g)

orig_acc = pss.acceptance
LOG = []
def acc(fx, fy):
    a = orig_acc(fx, fy); LOG.append(a); return a
mlt.pss.acceptance = acc

for run in range(2):
    T.clear()
    r = mlt.MLTRenderer(scene, seed=run + 1, max_depth=8, mutations_per_pixel=1 << 16, chains=chains)
    timed(r, "evaluate", "evaluate"); timed(r, "_put", "put")
    it_t, small, large, zero_y = [], [], [], []
    while r.time < seconds:
        LOG.clear()
        t = time.perf_counter(); r.run_iteration(); it_t.append(time.perf_counter() - t)
    n = r.chains
    print("run %d: bootstrap %.2fs (%d samples, %d start states), b %.4g, %d it x %d chains, "
          "iter median %.1f ms, %.2f us/mutation, mean acceptance %.3f" % (
          run, r.bootstrap_time, r.bootstrap_samples, r.start_states, r.b, r.iterations_done, n,
          1000 * np.median(it_t), 1e6 * np.median(it_t) / n, np.mean(r.acceptance)))
    print("   stage totals (s):", {k: round(v, 2) for k, v in T.items()}, "iterations %.2f" % sum(it_t))

for kw in ({}, dict(light_paths=1, connections="all")):
    rr = Renderer(scene, spp=1 << 16, seed=5, max_depth=8, samples_per_pass=4, **kw)
    while not (rr.time >= seconds and rr.at_round_end):
        rr.run_pass()
    res = rr.result()
    print("bdpt %s: %.2f s, %d spp, %.2f us/sample" % (kw or "auto", res.time, res.spp,
                                                       1e6 * res.time / (res.spp * 64 * 64)))
