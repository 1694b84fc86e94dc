"""The pilot's second look (render.Renderer._plan_second_look) against none, renders
alternating in one process: wall time of the default where the pilot chose path
tracing and the second look kept it (its cost), and the budgets each chose.

    python benchmarks/experiments/second_look.py scenes/glass-pane.xml --res 128 --spp 128
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--spp", type=int, default=128)
    ap.add_argument("--repeats", type=int, default=8)
    a = ap.parse_args()
    import bdpt_drjit                                                  # noqa: F401
    render = sys.modules["bdpt_drjit.render"]      # (bdpt_drjit.render: the function)
    share = render.SECOND_LOOK_SHARE
    scene = mi.load_file(a.scene, resx=a.res, resy=a.res)

    def run(seed: int, look: bool) -> tuple:
        render.SECOND_LOOK_SHARE = share if look else 0.0
        start = time.perf_counter()
        r = render.Renderer(scene, spp=a.spp, seed=seed, max_depth=8)
        while not r.done:
            r.run_pass()
        dr.sync_thread()
        return time.perf_counter() - start, r._second_look, str(r.budget)

    run(0, True), run(0, False)                                        # kernels
    rows = {True: [], False: []}
    for i in range(a.repeats):
        for look in ((True, False) if i % 2 == 0 else (False, True)):
            rows[look].append(run(100 + i, look))
    with_, without = (statistics.median(t for t, _, _ in rows[k]) for k in (True, False))
    print("%s %dx%d, %d spp: with the second look %.3f s (looked in %d of %d; budgets %s), "
          "without %.3f s (%s): %.3fx"
          % (a.scene, a.res, a.res, a.spp, with_, sum(x[1] for x in rows[True]), a.repeats,
             sorted({b for _, _, b in rows[True]}), without,
             sorted({b for _, _, b in rows[False]}), with_ / without))


if __name__ == "__main__":
    main()
