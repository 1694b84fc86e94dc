"""One pass, kernel by kernel, against Mitsuba's ``path`` on the same samples: what a
wavefront BDPT pass launches, how large its kernels are, what they take and what it
keeps in memory per lane.

    python -m benchmarks.profile_pass                      # Veach's BDPT, Cornell box 256x256, 16 spp
    python -m benchmarks.profile_pass --budget "light_paths=0.25 connections=0" --res 512

Each run is warm (the same kind of pass rendered once before, with another seed) and read
from Dr.Jit's kernel history: every launch (JIT kernels, memsets, copies, reductions),
each JIT kernel's lanes, operations and execution time, and the backend's peak memory
(``dr.detail.malloc_watermark``) per lane of the pass.  ``BDPT_VARIANT=cuda_ad_rgb``
profiles the GPU.
"""
from __future__ import annotations

import argparse
from collections import Counter

import drjit as dr
import mitsuba as mi

from . import common as C
from .throughput import DEFAULT_SCENE, load_scene


def _profiled(run) -> dict:
    """Kernel history and peak memory of ``run()`` (warm: run once before)."""
    run()
    dr.sync_thread()
    dr.flush_malloc_cache()
    dr.detail.malloc_clear_statistics()
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history()
        lanes = run()
        dr.sync_thread()
        history = dr.kernel_history()
    backend = dr.JitBackend.CUDA if mi.variant().startswith("cuda") else dr.JitBackend.LLVM
    jit = [e for e in history if e["type"] == dr.KernelType.JIT]
    # The two largest kernels are the walks (light, camera); what runs between them is
    # the hash grid's build where the pass merges (merge.HashGrid.build).
    kernels = [i for i, e in enumerate(history) if e["type"] == dr.KernelType.JIT]
    walks = sorted(sorted(kernels, key=lambda i: -(history[i].get("operation_count") or 0))[:2])
    between = history[walks[0] + 1:walks[1]] if len(walks) == 2 else []
    return {"lanes": lanes, "launches": Counter(e["type"].name for e in history), "jit": jit,
            "between_ms": sum(e.get("execution_time", 0.0) for e in between),
            "between": len(between),
            "ms": sum(e.get("execution_time", 0.0) for e in jit),
            "peak": dr.detail.malloc_watermark(backend)}


def _report(name: str, p: dict) -> None:
    kinds = ", ".join("%d %s" % (n, k) for k, n in sorted(p["launches"].items()))
    print("%s: %d lanes, %.1f ms of kernels, %s; peak memory %.0f bytes per lane"
          % (name, p["lanes"], p["ms"], kinds, p["peak"] / p["lanes"]))
    for e in p["jit"]:
        print("    kernel %8d lanes %6d ops %9.3f ms  %.1f ns per lane"
              % (e["size"], e.get("operation_count") or 0, e["execution_time"],
                 1e6 * e["execution_time"] / max(e["size"], 1)))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default=DEFAULT_SCENE)
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--max-depth", type=int, default=8)
    ap.add_argument("--budget", default="light_paths=1 connections=all",
                    help='a fixed budget (default: Veach\'s BDPT)')
    a = ap.parse_args(argv)
    from bdpt_drjit.render import Renderer
    scene = load_scene(a.scene, a.res, a.res, a.max_depth)
    budget = dict(kv.split("=") for kv in a.budget.split())
    seed = [0]

    r = Renderer(scene, spp=2 * a.spp, seed=1, max_depth=a.max_depth, samples_per_pass=a.spp,
                 **budget)

    def bdpt_pass():                # the renderer's passes: warm, then profiled
        _, n_pixels, spp = r.plan[r.passes_done]   # the memory budget may split a.spp
        r.run_pass()
        return n_pixels * spp

    path = mi.load_dict({"type": "path", "max_depth": a.max_depth})

    def path_pass():
        seed[0] += 1
        dr.eval(mi.render(scene, integrator=path, spp=a.spp, seed=seed[0]))
        return C.film_pixels(scene) * a.spp

    print("%s, %s, %dx%d, %d spp, max_depth %d, %s" % (mi.variant(), a.scene, a.res, a.res,
                                                       a.spp, a.max_depth, a.budget))
    bdpt = _profiled(bdpt_pass)
    _report("bdpt pass", bdpt)
    print("    between the walks (with merging: the hash grid's build): %.2f ms in %d launches"
          % (bdpt["between_ms"], bdpt["between"]))
    rays, stored = r.rays / (r.pixels * r.spp), r._vertices_per_path
    from bdpt_drjit.vertices import RECORD_BYTES
    print("    %.1f rays per sample; %.2f stored light vertices per light subpath, %d bytes "
          "each" % (rays, stored, RECORD_BYTES))
    mitsuba = _profiled(path_pass)
    _report("Mitsuba's path", mitsuba)
    print("bdpt / path: %.2fx kernel time, %.1fx launches, %.1fx peak memory"
          % (bdpt["ms"] / mitsuba["ms"], sum(bdpt["launches"].values())
             / max(sum(mitsuba["launches"].values()), 1), bdpt["peak"] / max(mitsuba["peak"], 1)))


if __name__ == "__main__":
    main()
