"""Where BDPT's time goes, stage by stage, against Mitsuba's ``path`` in one process.

    python -m benchmarks.breakdown                       # Cornell box 256x256, 16 spp, max_depth 8
    python -m benchmarks.breakdown --max-depth -1 --repeats 5

Renders the same scene with strategy subsets of the engine and reads the kernel
execution time from Dr.Jit's kernel history (median over repeats, warm kernels):

  all              every strategy (the default render)
  pt               camera walk with s = 0 and s = 1 only (no light subpaths)
  lt               light walk with t = 1 only (camera rays, no camera walk)
  no light image   all but t = 1

Differences give the stages: the light walk without t = 1 (no light image - pt,
roughly), t = 1 (all - no light image), and the connections s, t >= 2 (all - pt - lt).
"""
from __future__ import annotations

import argparse

from . import common as C
from .throughput import DEFAULT_SCENE, load_scene

CASES = {"all": C.BDPT_POWER, "pt": C.BDPT_PT, "lt": C.BDPT_LT, "no light image": C.BDPT_NO_LT}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--max-depth", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--scene", default=str(DEFAULT_SCENE))
    args = ap.parse_args(argv)
    scene = load_scene(args.scene, args.res, args.res, args.max_depth)

    def measure(method):
        """Median kernel execution time over warm renders, and rays per sample."""
        C.render(method, scene, args.spp, 0, args.max_depth)          # compiles
        runs = [C.render(method, scene, args.spp, s + 1, args.max_depth)
                for s in range(args.repeats)]
        return C.median([r.timing.execution for r in runs]), runs[0].rays_per_sample

    rows = {name: measure(m) for name, m in CASES.items()}
    path_time, _ = measure(C.PATH)

    C.log("%s, %dx%d, %d spp, max_depth %d: kernel execution time (median of %d)"
          % (args.scene, args.res, args.res, args.spp, args.max_depth, args.repeats))
    for name, (t, rays) in rows.items():
        C.log("  bdpt %-15s %7.3f s   %5.2f rays/sample" % (name, t, rays))
    C.log("  mitsuba path         %7.3f s" % path_time)
    all_t, pt, lt, no_li = (rows[k][0] for k in ("all", "pt", "lt", "no light image"))
    C.log("stages: t = 1 %.3f s, connections s,t >= 2 about %.3f s (all - pt - lt), "
          "camera walk with s <= 1 %.3f s (%.2fx path)"
          % (all_t - no_li, all_t - pt - lt, pt, pt / path_time))


if __name__ == "__main__":
    main()
