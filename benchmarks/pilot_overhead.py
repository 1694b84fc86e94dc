"""The pilot's share of a default ("auto" budget) render: each pass and the decision
timed, on the Cornell box; "net" subtracts what the chosen budget would have spent on
the pilot round's samples (1 spp of the image), which the image keeps.  Then the whole cost
of choosing: the default's time against a render fixed to the budget it chose last,
same seed, next to it (pilot, re-decisions and the shorter passes they need).

    python -m benchmarks.pilot_overhead            # 256x256, 64 spp, 3 renders
"""
from __future__ import annotations

import argparse
import time

import drjit as dr

from bdpt_drjit import support

from . import common as C


def timed_render(scene, spp: int, seed: int) -> dict:
    """Seconds per pass and of the decision of one render, wrapped around the
    renderer's own stages."""
    import importlib
    import bdpt_drjit
    render_mod = importlib.import_module("bdpt_drjit.render")
    from bdpt_drjit import optimizer
    passes, decide, pilot_spp = [], [], []
    run_pass, choose = render_mod.Renderer._render_pass, optimizer.Pilot.decide

    def timed_pass(self, index, *args):
        t = time.perf_counter()
        run_pass(self, index, *args)
        dr.sync_thread()
        passes.append(time.perf_counter() - t)
        if index < getattr(self, "_pilot_round", optimizer.Pilot.PASSES):
            # The pilot's round (on a large film a second pass gives the pixels the
            # pilot pass left their samples): its samples per pixel of the film.
            # (getattr: checkouts older than _pilot_round, for A/B runs.)
            pilot_spp.append(self.plan[index][1] * self.plan[index][2] / self.pixels)

    def timed_decide(self, *args):
        t = time.perf_counter()
        out = choose(self, *args)
        decide.append(time.perf_counter() - t)
        return out

    render_mod.Renderer._render_pass, optimizer.Pilot.decide = timed_pass, timed_decide
    try:
        t = time.perf_counter()
        res = bdpt_drjit.render(scene, spp=spp, seed=seed, max_depth=8)
        total = time.perf_counter() - t
    finally:
        render_mod.Renderer._render_pass, optimizer.Pilot.decide = run_pass, choose
    fixed = dict(item.split("=") for item in res.stats["budget"].split())
    t = time.perf_counter()
    bdpt_drjit.render(scene, spp=spp, seed=seed, max_depth=8, **fixed)
    fixed_time = time.perf_counter() - t
    pilot = sum(passes[:len(pilot_spp)])
    # The pilot's samples are part of the image: its net overhead is what it took
    # beyond what the chosen budget spends on as many samples (the rest's rate).
    net = pilot - sum(pilot_spp) * sum(passes[len(pilot_spp):]) / max(spp - sum(pilot_spp), 1)
    return {"total": total, "pilot": pilot, "decide": sum(decide), "budget": res.stats["budget"],
            "share": pilot / total, "net": net / total, "fixed": fixed_time,
            "passes": len(passes)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()
    scene = support.load_file(C.ROOT / "scenes" / "cornell-box.xml", resx=a.res, resy=a.res)
    timed_render(scene, a.spp, 1)                       # warm-up: kernels
    for i in range(a.repeats):
        r = timed_render(scene, a.spp, 1000 + i)
        C.log("render %.3f s, pilot passes %.3f s (of which the decision %.3f s): %.1f%%, "
              "net of the samples they give %.1f%%; budget %s; %d passes; fixed to that "
              "budget %.3f s (auto / fixed %.3f)"
              % (r["total"], r["pilot"], r["decide"], 100 * r["share"], 100 * r["net"], r["budget"],
                 r["passes"], r["fixed"], r["total"] / r["fixed"]))


if __name__ == "__main__":
    main()
