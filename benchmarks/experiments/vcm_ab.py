"""Interleaved A/B of the default bdpt and ``vcm`` (merging=True, budgets auto), with
Mitsuba's ``path`` at K times the spp: for each seed the three in turn (the A/B order
alternating), after a warm-up; medians of time and relative MSE (the suite's metric,
against its cached reference), and relMSE x time as ratios.

    python benchmarks/experiments/vcm_ab.py cornell-diffuse 32 4 8 REFS

REFS: the suite's cached references (``benchmarks.run --out DIR``: DIR/refs), a file
``SCENE_*.npy`` per scene (for Veach's room: ``SCENES["veach-bidir"].exr_reference(8)``
saved there).  External scenes need BDPT_SHARED.
"""
import glob
import statistics
import sys
import time
from pathlib import Path

import numpy as np


def main() -> None:
    name, spp, k, seeds, refs = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))      # this checkout
    import bdpt_drjit
    import mitsuba as mi
    from benchmarks.scenes import SCENES
    spec = SCENES[name]
    w, h, _ = spec.resolution(128)
    scene = spec.load(w, h)
    ref = np.load(glob.glob("%s/%s_*.npy" % (refs, name))[0])[..., :3]
    path = mi.load_dict({"type": "path", "max_depth": spec.max_depth})
    runs = {"bdpt": lambda s: bdpt_drjit.render(scene, spp=spp, seed=s, max_depth=spec.max_depth).image,
            "vcm": lambda s: bdpt_drjit.render(scene, spp=spp, seed=s, max_depth=spec.max_depth,
                                               merging=True).image,
            "path": lambda s: np.array(mi.render(scene, integrator=path, spp=spp * k, seed=s))}
    for render in runs.values():
        render(999)                                                  # kernels
    rows = {n: ([], []) for n in runs}
    for s in range(seeds):
        for n in (["bdpt", "vcm", "path"] if s % 2 == 0 else ["vcm", "bdpt", "path"]):
            start = time.perf_counter()
            img = runs[n](s)
            rows[n][0].append(time.perf_counter() - start)
            rows[n][1].append(float(np.mean((img[..., :3] - ref) ** 2 / (ref ** 2 + 1e-2))))
    med = {n: (statistics.median(t), statistics.median(e)) for n, (t, e) in rows.items()}
    (tp, ep), (tb, eb), (tv, ev) = med["path"], med["bdpt"], med["vcm"]
    for n, (t, e) in med.items():
        print("%s %-5s %5d spp  time %.3f s  relMSE %.4g  relMSE x time / path's %.3f"
              % (name, n, spp * (k if n == "path" else 1), t, e, t * e / (tp * ep)))
    print("%s vcm / bdpt: time %.3f, relMSE %.3f, relMSE x time %.3f"
          % (name, tv / tb, ev / eb, tv * ev / (tb * eb)))


if __name__ == "__main__":
    main()
