"""Efficiency against Mitsuba's ``path`` without a reference: 1 / (relative variance
across seeds x time per render), each method's renders of fresh seeds after a warm-up,
all methods in one process, one render of each in turn.

    python -m benchmarks.efficiency                          # 256x256 on the CPU
    BDPT_VARIANT=cuda_ad_rgb python -m benchmarks.efficiency --res 1024   # on a GPU

Relative variance: the per-pixel variance of the seeds' images (luminance) over the
squared mean image plus 0.01 (the suite's relative-MSE floor), averaged over pixels.  An
image of n spp has 1/n of a sample's variance and takes n times a sample's time, so
1 / (variance x time) compares methods rendered at different spp.  The table gives each
method's efficiency as a ratio to ``path``'s (> 1: better than ``path``).
Methods: the default (``auto``) at SPP, Veach's BDPT (``light_paths=1
connections=all``) at SPP / 2, ``path`` at 2 x SPP (roughly equal time on the CPU).
``--budgets``: fixed budgets besides, each at SPP, listed under the table with the
default's decision (its table of estimated relative efficiencies): what the decision
estimates against what each budget measures.  (A fixed ``light_paths=0`` runs this
engine's camera walk; the default's path tracing runs Mitsuba's ``path``, as ``path``.)

    BDPT_VARIANT=cuda_ad_rgb python -m benchmarks.efficiency --res 1024 \
        --budgets "light_paths=0 connections=0;light_paths=0.5 connections=0"
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from . import common as C
from .scenes import SCENES

DEFAULT_SCENES = "cornell-diffuse,camera-behind-glass,cornell-light-up,veach-bidir"


def _renderers(spec, scene, spp: int, budgets: list, fixed=()):
    """The methods: (spp, render(seed) -> image); the budgets the default chose are
    appended to ``budgets`` (and its decisions, ``fixed``: budgets rendered besides,
    each a string "light_paths=0.5 connections=0")."""
    import bdpt_drjit
    import mitsuba as mi
    path = mi.load_dict({"type": "path", "max_depth": spec.max_depth})

    def bdpt(n, **budget):
        def render(seed):
            res = bdpt_drjit.render(scene, spp=n, seed=seed, max_depth=spec.max_depth, **budget)
            if not budget:
                budgets.append((res.stats["budget"], res.stats.get("decision", "")))
            return res.image[..., :3]
        return render
    extra = {b: (spp, bdpt(spp, **dict(kv.split("=") for kv in b.split()))) for b in fixed}
    return {**extra, "default": (spp, bdpt(spp)),
            "Veach's BDPT": (max(spp // 2, 1), bdpt(max(spp // 2, 1), light_paths=1,
                                                   connections="all")),
            "path": (2 * spp, lambda seed: np.array(
                mi.render(scene, integrator=path, spp=2 * spp, seed=seed))[..., :3])}


def measure(name: str, res: int, spp: int, seeds: int, fixed=()) -> dict:
    spec = SCENES[name]
    width, height, _ = spec.resolution(res)
    scene = spec.load(width, height)
    budgets = []
    methods = _renderers(spec, scene, spp, budgets, fixed)
    images = {m: [] for m in methods}
    times = {m: [] for m in methods}
    for m, (_, render) in methods.items():
        render(10 ** 6)                                  # kernels
    for seed in range(seeds):
        for m, (_, render) in methods.items():
            start = time.perf_counter()
            images[m].append(render(1 + seed))
            times[m].append(time.perf_counter() - start)
    out = {}
    for m, (n, _) in methods.items():
        lum = np.stack(images[m]).mean(axis=-1)
        rel_var = float(np.mean(lum.var(axis=0, ddof=1) / (lum.mean(axis=0) ** 2 + 1e-2)))
        t = float(np.median(times[m]))
        out[m] = {"spp": n, "time": t, "efficiency": 1.0 / (rel_var * t)}
    base = out["path"]["efficiency"]
    for m in out:
        out[m]["ratio"] = out[m]["efficiency"] / base
    return {"scene": name, "size": "%dx%d" % (width, height), "methods": out,
            "budgets": sorted(set(b for b, _ in budgets[1:])), "decision": budgets[-1][1]}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--spp", type=int, default=64, help="the default's spp (default 64)")
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--scenes", default=DEFAULT_SCENES)
    ap.add_argument("--budgets", default="", help="fixed budgets besides, ';'-separated")
    a = ap.parse_args(argv)
    fixed = [b.strip() for b in a.budgets.split(";") if b.strip()]
    import mitsuba as mi
    print("%s, %d seeds per method; efficiency / path's (> 1: better), time per render"
          % (mi.variant(), a.seeds))
    notes = []
    print("| scene | size | default | Veach's BDPT | path | the default's budget |\n"
          "|---|---|---|---|---|---|")
    for name in a.scenes.split(","):
        spec = SCENES[name]
        if spec.external and not spec.file.exists():
            print("| %s | skipped: %s not found (../shared) | | | | |" % (name, spec.file))
            continue
        r = measure(name, a.res, a.spp, a.seeds, fixed)
        cell = lambda v: "**%.2f** (%d spp, %.0f ms)" % (v["ratio"], v["spp"], 1e3 * v["time"])  # noqa: E731
        print("| %s | %s | %s | %s |" % (name, r["size"], " | ".join(
            cell(r["methods"][m]) for m in ("default", "Veach's BDPT", "path")),
            "; ".join(r["budgets"])), flush=True)
        if fixed:
            notes.append("%s: %s; the default %s" % (name, "; ".join(
                "%s %s" % (b, cell(r["methods"][b])) for b in fixed), r["decision"]))
    for line in notes:
        print("\n" + line)


if __name__ == "__main__":
    main()
