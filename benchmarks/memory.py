"""Does a render hold to its ``memory_budget``?  Each pass's peak memory, against the
budget and per camera lane.

    python -m benchmarks.memory                                    # Cornell box, Veach's BDPT
    python -m benchmarks.memory --scene ../shared/scenes/external/veach-bidir/scene.xml
    python -m benchmarks.memory --budget "light_paths=0.25 connections=0"

Peak memory: Dr.Jit's ``malloc_watermark`` from the pass's start, the allocator's cache
flushed before (the watermark counts cached blocks too), less what was held at the
start (the film, the scene's arrays).  ``--budget auto``: the default budget.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import drjit as dr
import mitsuba as mi

import bdpt_drjit  # noqa: F401  (selects the variant, as common.py; not imported here:
                   # it turns on the kernel history, and the tests use pass_peaks)

DEFAULT_SCENE = Path(__file__).resolve().parents[1] / "scenes" / "cornell-box.xml"


def pass_peaks(renderer) -> list:
    """(camera lanes, peak bytes above the start) of each pass of ``renderer``."""
    backend = dr.JitBackend.CUDA if mi.variant().startswith("cuda") else dr.JitBackend.LLVM
    out = []
    while not renderer.done:
        _, n_pixels, spp = renderer.plan[renderer.passes_done]
        dr.sync_thread()
        dr.flush_malloc_cache()                 # the watermark counts cached blocks too
        dr.detail.malloc_clear_statistics()
        start = dr.detail.malloc_watermark(backend)
        renderer.run_pass()
        dr.sync_thread()
        out.append((n_pixels * spp, dr.detail.malloc_watermark(backend) - start))
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default=DEFAULT_SCENE)
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--max-depth", type=int, default=8)
    ap.add_argument("--mib", type=int, default=256, help="memory_budget in MiB (default 256)")
    ap.add_argument("--budget", default="light_paths=1 connections=all",
                    help="a fixed budget (default: Veach's BDPT), or auto")
    a = ap.parse_args(argv)
    from bdpt_drjit import support
    from bdpt_drjit.render import Renderer
    scene = support.load_file(a.scene, resx=a.res, resy=a.res, max_depth=a.max_depth)
    budget = {} if a.budget == "auto" else dict(kv.split("=") for kv in a.budget.split())
    r = Renderer(scene, spp=a.spp, seed=1, max_depth=a.max_depth,
                 memory_budget=a.mib << 20, **budget)
    peaks = pass_peaks(r)
    print("%s, %dx%d, %d spp, memory_budget %d MiB, budget %s; pool capacities per light "
          "subpath %s" % (a.scene, a.res, a.res, a.spp, a.mib, r.budget, r._capacity), flush=True)
    for i, (lanes, peak) in enumerate(peaks):
        print("pass %2d: %8d lanes, peak %6.1f MiB (%.2fx the budget), %5.0f bytes per lane"
              % (i, lanes, peak / 2 ** 20, peak / (a.mib << 20), peak / lanes), flush=True)


if __name__ == "__main__":
    main()
