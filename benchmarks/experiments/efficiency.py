"""Efficiency of the default budget, fixed budgets and Mitsuba's integrators on one
suite scene, in one process: the median time and relative MSE (the suite's metric,
against its cached reference) of ``seeds`` renders after a warm-up, and time x relMSE
(the error at equal time, for unbiased renders whose error falls as 1 / time) as a
ratio to the first Mitsuba integrator named.

    python benchmarks/experiments/efficiency.py point-caustic 256 /tmp/suite/refs \\
        --budgets "light_paths=4 connections=0 first_hits=light_image" --mitsuba ptracer:4

``--mitsuba NAME:K`` renders Mitsuba's NAME at K times the spp (close to equal time).
External scenes need BDPT_SHARED.
"""
import argparse
import glob
import statistics
import sys
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("spp", type=int)
    ap.add_argument("refs", help="the suite's cached references (benchmarks.run --out DIR: DIR/refs)")
    ap.add_argument("--budgets", action="append", default=[],
                    help='a fixed budget, e.g. "light_paths=0.5 connections=all"; repeatable')
    ap.add_argument("--mitsuba", action="append", default=[], help="NAME:K, e.g. ptracer:4")
    ap.add_argument("--seeds", type=int, default=6)
    a = ap.parse_args()

    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))      # this checkout
    import bdpt_drjit
    import mitsuba as mi
    from benchmarks.scenes import SCENES
    spec = SCENES[a.scene]
    width, height, _ = spec.resolution(128)
    scene = spec.load(width, height)
    ref = np.load(glob.glob("%s/%s_%dx%d_*.npy" % (a.refs, a.scene, width, height))[0])[..., :3]

    def relmse(img):
        return float(np.mean((img[..., :3] - ref) ** 2 / (ref ** 2 + 1e-2)))

    def bdpt(spp, seed, options):
        return bdpt_drjit.render(scene, spp=spp, seed=seed, max_depth=spec.max_depth, **options).image

    def mitsuba(name):
        integrator = mi.load_dict({"type": name, "max_depth": spec.max_depth})
        return lambda spp, seed, _: np.array(mi.render(scene, integrator=integrator, spp=spp, seed=seed))

    runs = [("default", bdpt, a.spp, {})]
    runs += [(b, bdpt, a.spp, {k: _value(v) for k, v in (kv.split("=") for kv in b.split())})
             for b in a.budgets]
    runs += [("%s x%s" % tuple(m.split(":")), mitsuba(m.split(":")[0]), a.spp * int(m.split(":")[1]), None)
             for m in a.mitsuba]
    rows = {}
    for name, render, spp, options in runs:
        render(spp, 999, options)                                   # kernels
        times, errors = [], []
        for seed in range(a.seeds):
            start = time.perf_counter()
            img = render(spp, seed, options)
            times.append(time.perf_counter() - start)
            errors.append(relmse(img))
        rows[name] = (statistics.median(times), statistics.median(errors))
        print("%-50s %6d spp  time %.3f s  relMSE %.4g" % ((name, spp) + rows[name]), flush=True)
    base = next((n for n, *_ in runs if n.split()[0] in ("path", "ptracer", "volpath")), "default")
    for name, (t, e) in rows.items():
        print("%-50s error at equal time / %s: %.2f"
              % (name, base, t * e / (rows[base][0] * rows[base][1])))


def _value(text: str):
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


if __name__ == "__main__":
    main()
