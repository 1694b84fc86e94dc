"""Where MMLT's error on the door ajar comes from, and the film position's small steps
(issue 31; benchmarks/RESULTS.md, "Metropolis light transport").

    python -m benchmarks.mlt_steps trace [--gap-start 0.49] [--seconds 30] [--seeds 1,2]
    python -m benchmarks.mlt_steps steps [--scene scenes/cornell-box.xml] [--iterations 300]
        [--seeds 1,2,3] [--kind mlt|pssmlt] [--chains 16384] [--bootstrap 1048576]
        [--film 0.1,0.05 --film 0.0625,0.015625 ...]

``trace``: `mlt` with its automatic plan for ``--seconds`` (as mlt_door): the bootstrap's
time, chains, start states and b_k shares, time per iteration, acceptances, and relMSE
after 1, 16, 64 and 256 iterations and at the end, also with the image rescaled to the
reference's mean (the share of the bootstrap's noise in b).  ``steps``: a fixed number
of iterations per variant of the film position's step sizes (pss.FILM_S1_PIXELS in
pixels, pss.FILM_S2 of the side; 0.0625,0.015625 at 64x64 are Kelemen's 1/1024 to 1/64,
the other numbers' steps), the same seeds for each: the cost is the same, so the
comparison does not depend on the machine's load.  64x64, max_depth 8; the references
are mlt_door's (``--ref-spp``, 16384 unless given; cached in /tmp)."""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import bdpt_drjit  # noqa: F401
from bdpt_drjit import mlt, mmlt, pss, support
from benchmarks.mlt_door import _lum, reference


def _error(img, ref, eps) -> float:
    return float(np.mean((img - ref) ** 2 / (ref ** 2 + eps)))


def trace(scene, ref, eps, seconds, seeds):
    for seed in seeds:
        r = mmlt.MMLTRenderer(scene, seed=seed, max_depth=8, mutations_per_pixel=1 << 16)
        print("seed %d: bootstrap %.2f s of %d samples, %d chains on %d start states, b_k / b %s"
              % (seed, r.bootstrap_time, r.bootstrap_samples, r.chains, r.start_states,
                 np.round(r.b_plain / r.b, 3).tolist()))
        times, marks = [], []
        while r.iterations_done == 0 or r.time < seconds:
            t = time.perf_counter()
            r.run_iteration()
            times.append(time.perf_counter() - t)
            if r.iterations_done in (1, 16, 64, 256) or r.time >= seconds:
                img = _lum(r.tensor().numpy())
                marks.append((r.iterations_done, r.time, _error(img, ref, eps),
                              _error(img * ref.mean() / img.mean(), ref, eps),
                              img.mean() / ref.mean()))
        print("  %d iterations, median %.1f ms (%.2f us per mutation); acceptance small %.3f, "
              "large %.3f" % (r.iterations_done, 1e3 * np.median(times),
                              1e6 * np.median(times) / r.chains, *r.step_acceptance()))
        for m in marks:
            print("  iteration %5d at %5.1f s: relMSE %.4f, rescaled to the reference's mean "
                  "%.4f (mean ratio %.4f)" % m)


def steps(scene, ref, eps, args):
    cls = mmlt.MMLTRenderer if args.kind == "mlt" else mlt.MLTRenderer
    errors = {v: [] for v in args.film}
    for seed in args.seeds:
        for variant in args.film:
            pss.FILM_S1_PIXELS, pss.FILM_S2 = (float(v) for v in variant.split(","))
            r = cls(scene, seed=seed, max_depth=8, mutations_per_pixel=1 << 16,
                    chains=args.chains, bootstrap_samples=args.bootstrap)
            for _ in range(args.iterations):
                r.run_iteration()
            errors[variant].append(_error(_lum(r.tensor().numpy()), ref, eps))
            print("seed %d film steps %-16s acceptance small %.3f, relMSE %.4f"
                  % (seed, variant, r.step_acceptance()[0], errors[variant][-1]), flush=True)
    for variant, e in errors.items():
        print("film steps %-16s relMSE median %.4f, mean %.4f" % (variant, np.median(e), np.mean(e)))


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("mode", choices=("trace", "steps"))
    ap.add_argument("--scene", default="scenes/door-ajar.xml")
    ap.add_argument("--gap-start", type=float, default=0.49)
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--seeds", type=lambda v: [int(x) for x in v.split(",")], default=[1, 2])
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--kind", choices=("mlt", "pssmlt"), default="mlt")
    ap.add_argument("--chains", type=int, default=16384)
    ap.add_argument("--bootstrap", type=int, default=1 << 20)
    ap.add_argument("--ref-spp", type=int, default=16384, help="the reference's (mlt_door's)")
    ap.add_argument("--film", action="append", default=[], metavar="S1_PIXELS,S2")
    args = ap.parse_args(argv)
    args.film = args.film or ["0.0625,0.015625", "%g,%g" % (pss.FILM_S1_PIXELS, pss.FILM_S2)]
    door = Path(args.scene).name == "door-ajar.xml"
    gap = args.gap_start if door else 0.45
    scene = support.load_file(args.scene, resx=64, resy=64, **({"gap_start": gap} if door else {}))
    ref, eps, _ = reference(scene, args.scene, 64, args.ref_spp, gap)
    if args.mode == "trace":
        trace(scene, ref, eps, args.seconds, args.seeds)
    else:
        steps(scene, ref, eps, args)


if __name__ == "__main__":
    main()
