"""Where a GPU render's time goes, against Mitsuba's ``path`` in the same process:
per-pass wall time split into kernel time and the rest (tracing the pass from Python,
host syncs, launches), for Veach's BDPT at a 2 GiB and at the default memory budget
(two pass sizes), the default budget, ``vcm`` (merging on), PSSMLT and MMLT (``mlt``:
its chains and mutations per second).
``veach-separate-calls`` is Veach's BDPT with one virtual call per BSDF query (an A/B
of their pairing in surface.Vertex).

    BDPT_VARIANT=cuda_ad_rgb python -m benchmarks.gpu_passes --res 1024 --spp 16
    python -m benchmarks.gpu_passes --res 128 --spp 4          # a dry run on the CPU

Each method renders once to warm its kernels, then ``--repeats`` times with new seeds,
interleaved with ``path``; reported are medians.  Kernel time per pass comes from one
further render with Dr.Jit's kernel history on.  ``--timeline`` then lists a default
render pass by pass (the plan's entry, the budget, wall and kernel time): where a
path-traced render's time goes besides Mitsuba's ``path``.
"""
from __future__ import annotations

import argparse
import statistics
import time

import drjit as dr
import mitsuba as mi

from . import common as C
from .throughput import DEFAULT_SCENE, load_scene

VEACH = {"light_paths": 1, "connections": "all"}


def _bdpt(scene, spp, seed, max_depth, **settings):
    from bdpt_drjit.render import Renderer
    r = Renderer(scene, spp=spp, seed=seed, max_depth=max_depth, **settings)
    while not r.done:
        r.run_pass()
    dr.sync_thread()
    return r


def _separate_calls(fn):
    """``fn`` with a vertex's BSDF queries made one virtual call each, as before they
    were paired (surface.Vertex.eval_and_reverse, eval_adjoint_and_pdf): an A/B."""
    from bdpt_drjit.surface import Vertex

    def run(seed):
        paired = Vertex.eval_and_reverse, Vertex.eval_adjoint_and_pdf
        Vertex.eval_and_reverse = lambda v, w, a: (*v.eval(w, a), v.reverse_pdf(w, a))
        Vertex.eval_adjoint_and_pdf = lambda v, w, a: (*v.eval_adjoint(w, a), v.pdf(w, a))
        try:
            return fn(seed)
        finally:
            Vertex.eval_and_reverse, Vertex.eval_adjoint_and_pdf = paired
    return run


def _mlt(scene, spp, seed, max_depth, multiplexed=False):
    """PSSMLT, or (``multiplexed``) MMLT: the ``mlt`` integrator."""
    from bdpt_drjit import mlt, mmlt
    kind = mmlt.MMLTRenderer if multiplexed else mlt.MLTRenderer
    r = kind(scene, seed=seed, max_depth=max_depth, mutations_per_pixel=spp)
    while not r.done:
        r.run_iteration()
    dr.sync_thread()
    return r


def _path(scene, spp, seed, max_depth):
    dr.eval(mi.render(scene, integrator=mi.load_dict({"type": "path", "max_depth": max_depth}),
                      spp=spp, seed=seed))
    dr.sync_thread()


def _timed(fn, seed):
    start = time.perf_counter()
    r = fn(seed)
    return time.perf_counter() - start, r


def _kernel_ms(fn, seed) -> float:
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history()
        fn(seed)
        dr.sync_thread()
        jit = [e for e in dr.kernel_history() if e["type"] == dr.KernelType.JIT]
    return sum(e.get("execution_time", 0.0) for e in jit)


def timeline(scene, spp, seed, max_depth) -> None:
    """A default render pass by pass, kernels warm: each pass's plan entry (pixel
    set, lanes, spp), the budget it ran, its wall time (synced) and kernel time."""
    from bdpt_drjit.render import Renderer
    r = Renderer(scene, spp=spp, seed=seed, max_depth=max_depth)
    start = time.perf_counter()
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history()
        while not r.done:
            index, before = r.passes_done, time.perf_counter()
            budget = str(r.budget)
            r.run_pass()
            dr.sync_thread()
            jit = [e for e in dr.kernel_history() if e["type"] == dr.KernelType.JIT]
            print("pass %2d %-28s %-44s %7.1f ms wall %7.1f ms kernels %3d launches"
                  % (index, r.plan[index], budget[:44], 1e3 * (time.perf_counter() - before),
                     sum(e.get("execution_time", 0.0) for e in jit), len(jit)), flush=True)
    print("whole render %.1f ms, %d passes; budget %s"
          % (1e3 * (time.perf_counter() - start), r.passes_done, r.budget), flush=True)


def measure(scene, res, spp, max_depth, repeats, methods):
    pixels = res * res
    path = lambda seed: _path(scene, spp, seed, max_depth)          # noqa: E731
    path(1)
    rows = []
    for name, fn in methods:
        fn(2)                                                        # warm
        times, path_times, passes = [], [], 0
        for i in range(repeats):
            t, r = _timed(fn, 10 + i)
            times.append(t)
            passes = getattr(r, "passes_done", None) or getattr(r, "iterations_done", 0)
            path_times.append(_timed(path, 20 + i)[0])
        t, tp = statistics.median(times), statistics.median(path_times)
        kernel = _kernel_ms(fn, 30) / 1e3
        rows.append((name, t, tp, passes, kernel))
        chains = getattr(r, "chains", 0)        # MLT: a pass is an iteration of every chain
        print("%-24s %8.3f s  path %7.3f s  ratio %6.3f  passes %4d  per pass: %7.1f ms "
              "wall, %7.1f ms kernels  samples/s %.3g%s"
              % (name, t, tp, tp / t, passes, 1e3 * t / max(passes, 1),
                 1e3 * kernel / max(passes, 1), pixels * spp / t,
                 "  %d chains, %.3g mutations/s" % (chains, chains * passes / t) if chains
                 else ""), flush=True)
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default=str(DEFAULT_SCENE))
    ap.add_argument("--res", type=int, default=1024)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--max-depth", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--methods", default="veach-2g,veach,default,vcm,pssmlt")
    ap.add_argument("--timeline", action="store_true",
                    help="then a default render pass by pass")
    a = ap.parse_args(argv)
    scene = load_scene(a.scene, a.res, a.res, a.max_depth)
    s, d = a.spp, a.max_depth
    table = {
        "veach-2g": lambda seed: _bdpt(scene, s, seed, d, memory_budget=2 << 30, **VEACH),
        "veach": lambda seed: _bdpt(scene, s, seed, d, **VEACH),
        "veach-separate-calls": _separate_calls(lambda seed: _bdpt(scene, s, seed, d, **VEACH)),
        "default": lambda seed: _bdpt(scene, s, seed, d),
        "vcm": lambda seed: _bdpt(scene, s, seed, d, merging=True, **VEACH),
        "pssmlt": lambda seed: _mlt(scene, s, seed, d),
        "mlt": lambda seed: _mlt(scene, s, seed, d, multiplexed=True),
    }
    print("%s, %s, %dx%d, %d spp, max_depth %d" % (mi.variant(), a.scene, a.res, a.res, s, d))
    measure(scene, a.res, s, d, a.repeats, [(m, table[m]) for m in a.methods.split(",")])
    if a.timeline:
        timeline(scene, s, 40, d)
    C.film_pixels(scene)


if __name__ == "__main__":
    main()
