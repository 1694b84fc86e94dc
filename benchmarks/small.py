"""Small renders: the default budget's error at equal time against Mitsuba's ``path``
where a render's fixed cost (its pilot pass, the walks' tracing) weighs most.

    python -m benchmarks.small                 # 32 spp: Cornell box 128x128, glass pane 64x64,
                                               # Veach's bidirectional room 128x128 (../shared)
    python -m benchmarks.small --busy          # the same beside a CPU-bound job
    python -m benchmarks.small --first         # each render as a process's first of its
                                               # scene (no pilot of an earlier one reused)
    python -m benchmarks.small --scenes camera-behind-glass --res 256 --spp 64
                                               # another size: where the default
                                               # path-traces, its time over path's

Per scene, after a warm-up render of each: ``seeds`` renders of the default at SPP and
of ``path`` at SPP, one of each in turn, each timed around the render and its image.
Efficiency ratio = median(relMSE x time) of the default over path's (relMSE: the
suite's, against a reference: path at 4096 spp for the project scenes, cached in
benchmarks/results/small-refs; the scene's Tungsten render for Veach's room); below 1
the default wins at equal time.  ``--busy`` runs a CPU-bound process (one busy loop
per core) during the measurements.
"""
from __future__ import annotations

import argparse
import multiprocessing
import statistics
import time
from dataclasses import replace

import numpy as np

from . import common as C
from .scenes import SCENES

CASES = [("cornell-diffuse", 128), ("camera-behind-glass", 64), ("veach-bidir", 128)]
REF_SPP = 4096


def _busy() -> None:
    while True:
        pass


def _reference(spec, scene, width: int, height: int, factor: int) -> np.ndarray:
    if spec.reference == "exr":
        return spec.exr_reference(factor)[..., :3]
    cache = C.RESULTS / "small-refs" / ("%s_%dx%d_%d.npy" % (spec.name, width, height, REF_SPP))
    if not cache.exists():
        C.log("reference: %s path %d spp" % (spec.name, REF_SPP))
        cache.parent.mkdir(parents=True, exist_ok=True)
        parts = [C.render(C.PATH, scene, 256, 10 ** 6 + i, spec.max_depth).image[..., :3]
                 for i in range(REF_SPP // 256)]
        np.save(cache, np.mean(parts, axis=0))
    return np.load(cache)


def measure(name: str, res: int, spp: int, seeds: int, first: bool = False) -> dict:
    spec = SCENES[name]
    width, height, factor = spec.resolution(res)
    scene = spec.load(width, height)
    ref = _reference(spec, scene, width, height, factor)
    auto = replace(C.BDPT_AUTO, options=(("reuse_pilot", False),)) if first else C.BDPT_AUTO
    rows = {m.name: [] for m in (auto, C.PATH)}
    for m in (auto, C.PATH):
        C.render(m, scene, spp, 999, spec.max_depth)                   # kernels
    for seed in range(seeds):
        for m in (auto, C.PATH) if seed % 2 == 0 else (C.PATH, auto):
            start = time.perf_counter()
            out = C.render(m, scene, spp, 1 + seed, spec.max_depth)
            rows[m.name].append((time.perf_counter() - start, C.rel_mse(out.image[..., :3], ref)))
    stats = {k: (statistics.median(t for t, _ in v), statistics.median(e for _, e in v),
                 statistics.median(t * e for t, e in v)) for k, v in rows.items()}
    return {"scene": name, "size": "%dx%d" % (width, height), "spp": spp, "stats": stats,
            "ratio": stats["bdpt-auto"][2] / stats["path"][2]}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--busy", action="store_true", help="beside a CPU-bound job")
    ap.add_argument("--first", action="store_true",
                    help="no render reuses the pilot of an earlier one (render._ReusedPilot)")
    ap.add_argument("--scenes", help="comma-separated (default: %s)" % ",".join(n for n, _ in CASES))
    ap.add_argument("--res", type=int, help="the film's width for every scene (default: "
                    "each scene's size above)")
    a = ap.parse_args(argv)
    cases = [(n, a.res or r) for n, r in CASES if not a.scenes or n in a.scenes.split(",")]
    busy = [multiprocessing.Process(target=_busy, daemon=True)
            for _ in range(multiprocessing.cpu_count())] if a.busy else []
    for p in busy:
        p.start()
    try:
        print("| scene | size | spp | default: time, relMSE | path: time, relMSE | "
              "relMSE x time / path's | time / path's |\n|---|---|---|---|---|---|---|")
        for name, res in cases:
            if SCENES[name].external and not SCENES[name].file.exists():
                print("| %s | skipped: %s not found (../shared) | | | | | |" % (name, SCENES[name].file))
                continue
            r = measure(name, res, a.spp, a.seeds, a.first)
            (tb, eb, _), (tp, ep, _) = r["stats"]["bdpt-auto"], r["stats"]["path"]
            print("| %s | %s | %d | %.1f ms, %.4g | %.1f ms, %.4g | **%.2f** | %.2f |"
                  % (name, r["size"], r["spp"], 1e3 * tb, eb, 1e3 * tp, ep, r["ratio"], tb / tp),
                  flush=True)
    finally:
        for p in busy:
            p.terminate()


if __name__ == "__main__":
    main()
