"""Veach's BDPT with its connections in the camera walk against deferred to a kernel of
their own (connect.DEFERRED), in one process, renders alternating, with Mitsuba's
``path`` beside them (issue 29).

    python benchmarks/experiments/links_ab.py cornell-diffuse --res 256 --spp 16 --repeats 6

Prints the medians of wall time per render and the samples per second over ``path``'s.
"""
import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks import common as C                                     # noqa: E402,F401
import drjit as dr                                                     # noqa: E402
import mitsuba as mi                                                   # noqa: E402
from benchmarks.scenes import SCENES                                   # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=6)
    a = ap.parse_args()
    from bdpt_drjit import connect
    from bdpt_drjit.render import Renderer
    spec = SCENES[a.scene]
    w, h, _ = spec.resolution(a.res)
    scene, depth = spec.load(w, h), spec.max_depth
    path = mi.load_dict({"type": "path", "max_depth": depth})

    def bdpt(seed: int, deferred: bool) -> float:
        connect.DEFERRED = deferred
        start = time.perf_counter()
        r = Renderer(scene, spp=a.spp, seed=seed, max_depth=depth, light_paths=1,
                     connections="all")
        while not r.done:
            r.run_pass()
        dr.sync_thread()
        return time.perf_counter() - start

    def path_time(seed: int) -> float:             # 4x the spp, per a.spp
        start = time.perf_counter()
        dr.eval(mi.render(scene, integrator=path, spp=4 * a.spp, seed=seed))
        dr.sync_thread()
        return (time.perf_counter() - start) / 4

    bdpt(0, False), bdpt(0, True), path_time(0)             # kernels
    times = {False: [], True: []}
    paths = []
    for i in range(a.repeats):
        for deferred in ((False, True) if i % 2 == 0 else (True, False)):
            times[deferred].append(bdpt(100 + i, deferred))
        paths.append(path_time(100 + i))
    inline, deferred = (statistics.median(times[d]) for d in (False, True))
    p = statistics.median(paths)
    print("%s %dx%d, %d spp: in the walk %.3f s, deferred %.3f s (%.3fx), path %.3f s; "
          "samples/s over path's %.3f and %.3f"
          % (a.scene, w, h, a.spp, inline, deferred, deferred / inline, p, p / inline,
             p / deferred))


if __name__ == "__main__":
    main()
