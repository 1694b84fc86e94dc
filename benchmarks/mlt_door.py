"""MMLT (``mlt``) and PSSMLT against BDPT at equal time on scenes/door-ajar.xml (issue 31).

    python -m benchmarks.mlt_door [--seconds 15] [--runs 4] [--res 64] [--ref-spp 4096]
    python -m benchmarks.mlt_door --scene scenes/cornell-box.xml --seconds 5 --plan-mpp 256

Each round renders every method once for ``--seconds`` (interleaved, so that the
machine's load falls on all alike): ``mlt`` (MMLT, mmlt.py) and ``pssmlt`` (their
bootstraps included in their time),
the default ``bdpt`` (auto budget, its pilot included), Veach's BDPT
(light_paths=1 connections=all) and Mitsuba's ``path`` (in ``--methods``; renders of
16 spp averaged); ``--mlt K=V,...`` adds pssmlt methods with other parameters (MMLT ones with
``mmlt=1`` among them, ``frozen=0`` for walks traced, not replayed; numeric values only).  Each stops after the pass or iteration that crosses
the time, with an image normalized for what it did.  The reference is the mean of 8
or more BDPT renders (``--ref-spp`` in all, at most 2048 spp each); its own noise is
estimated from their spread and reported.  relMSE = mean over pixels of (I - R)^2 / (R^2 + eps), on the luminance,
eps = (0.01 mean R)^2; MSE/mean^2 = mean of (I - R)^2 over the square of R's mean
(bright and dark pixels alike).  The reference is cached in /tmp by its parameters."""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import bdpt_drjit  # noqa: F401
import mitsuba as mi
from bdpt_drjit import frozen as walks
from bdpt_drjit import mlt, mmlt, support
from bdpt_drjit.render import Renderer


def _lum(img):
    return img[..., :3].mean(axis=-1)


def timed_bdpt(scene, seconds, seed, **settings):
    r = Renderer(scene, spp=1 << 16, seed=seed, max_depth=8, samples_per_pass=4, **settings)
    while not r.done and not (r.time >= seconds and r.at_round_end):
        r.run_pass()
    res = r.result()
    return _lum(res.image), res.time, res.spp


def timed_mlt(scene, seconds, seed, mis=True, chains=0, bootstrap=0, renderer=None, frozen=1,
              **params):
    """``frozen`` 0: the chains' walks traced, not replayed (bdpt_drjit.frozen)."""
    old, walks.ENABLED = walks.ENABLED, bool(frozen)
    try:
        return _timed_mlt(scene, seconds, seed, mis, chains, bootstrap, renderer, **params)
    finally:
        walks.ENABLED = old


def _timed_mlt(scene, seconds, seed, mis, chains, bootstrap, renderer, **params):
    kw = dict(max_depth=8, mutations_per_pixel=1 << 16, chains=chains, large_step_mis=mis,
              bootstrap_samples=bootstrap)
    r = (renderer or mlt.MLTRenderer)(scene, seed=seed, **{**kw, **params})
    while not r.done and (r.iterations_done == 0 or r.time < seconds):
        r.run_iteration()           # at least one iteration, as the CLI's --time
    res = r.result()
    return _lum(res.image), res.time, res.stats["mutations_per_pixel"]


def timed_path(scene, seconds, seed, chunk=16):
    """Mitsuba's ``path`` (max_depth 8) in renders of ``chunk`` spp, averaged, until the
    time is crossed (the first render's compilation included, as for the others)."""
    integ = mi.load_dict({"type": "path", "max_depth": 8})
    total, renders, start = None, 0, time.perf_counter()
    while renders == 0 or time.perf_counter() - start < seconds:
        img = np.array(mi.render(scene, integrator=integ, spp=chunk,
                                 seed=(seed << 16) + renders))
        total = img if total is None else total + img
        renders += 1
    return _lum(total / renders), time.perf_counter() - start, chunk * renders


REF_RENDER_SPP = 2048     # the most spp of one reference render (the 16384-spp reference's)


def reference(scene, path, res, ref_spp, gap_start):
    """(luminance R, eps, R's own relMSE): the mean of max(8, ref_spp / 2048) BDPT renders
    (seeds 1000, 1001, ...) of ref_spp / their number spp each, cached in /tmp by its
    parameters.  A larger reference starts from a smaller one's cache of the same
    renders (16384 spp: 8 of 2048), so 65536 spp costs 24 renders more."""
    n = max(8, ref_spp // REF_RENDER_SPP)
    spp = ref_spp // n
    name = "/tmp/mlt_ref_%s_%d_%%d_%g.npy" % (Path(path).stem, res, gap_start)
    cache = Path(name % ref_spp)
    if cache.exists():
        refs = list(np.load(cache))
    else:
        refs = []
        if spp == REF_RENDER_SPP and Path(name % (8 * spp)).exists() and n > 8:
            refs = list(np.load(name % (8 * spp)))
        for k in range(len(refs), n):
            refs.append(_lum(bdpt_drjit.render(scene, spp=spp, seed=1000 + k,
                                               max_depth=8).image))
            print("reference render %d of %d" % (k + 1, n), flush=True)
        np.save(cache, np.array(refs))
    ref = np.mean(refs, axis=0)
    ref_var = np.var(refs, axis=0, ddof=1) / n
    eps = (0.01 * ref.mean()) ** 2
    return ref, eps, float(np.mean(ref_var / (ref ** 2 + eps)))


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--runs", type=int, default=4)
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--ref-spp", type=int, default=4096)
    ap.add_argument("--gap-start", type=float, default=0.45)
    ap.add_argument("--scene", default="scenes/door-ajar.xml",
                    help="another scene (its own parameters; --gap-start is door-ajar's)")
    ap.add_argument("--no-mis", action="store_true", help="pssmlt without large-step MIS")
    ap.add_argument("--chains", type=int, default=0, help="0: automatic (mlt.py)")
    ap.add_argument("--bootstrap", type=int, default=0, help="0: automatic (mlt.py)")
    ap.add_argument("--plan-mpp", type=int, default=0,
                    help="chains (where 0) as the automatic plan chooses them for a render "
                         "of this many mutations per pixel (0: unbounded, the maximum); the "
                         "bootstrap is the automatic one for those chains unless --bootstrap")
    ap.add_argument("--methods", default="mlt,pssmlt,bdpt (auto),bdpt (Veach)")
    ap.add_argument("--mlt", action="append", default=[], metavar="K=V,K=V",
                    help="a further pssmlt method with these parameters (repeatable), e.g. "
                         "chains=16384,bootstrap_samples=524288")
    args = ap.parse_args(argv)
    door = Path(args.scene).name == "door-ajar.xml"
    scene = support.load_file(args.scene, resx=args.res, resy=args.res,
                              **({"gap_start": args.gap_start} if door else {}))
    t0 = time.perf_counter()
    ref, eps, ref_err = reference(scene, args.scene, args.res, args.ref_spp, args.gap_start)
    print("reference: %d spp of bdpt in %.0f s, mean %.6g; its own relMSE ~ %.4g (in every "
          "figure below; 'less ref' subtracts it)"
          % (args.ref_spp, time.perf_counter() - t0, ref.mean(), ref_err))
    if args.plan_mpp:       # the chains of that plan; the bootstrap stays automatic
        args.chains, _ = mlt.automatic_plan(args.plan_mpp * args.res * args.res, args.chains,
                                            args.bootstrap)
    methods = {"pssmlt": lambda s: timed_mlt(scene, args.seconds, s, not args.no_mis,
                                             args.chains, args.bootstrap),
               "mlt": lambda s: timed_mlt(scene, args.seconds, s, not args.no_mis, args.chains,
                                          args.bootstrap, mmlt.MMLTRenderer),
               "bdpt (auto)": lambda s: timed_bdpt(scene, args.seconds, s),
               "bdpt (Veach)": lambda s: timed_bdpt(scene, args.seconds, s, light_paths=1,
                                                    connections="all"),
               "path": lambda s: timed_path(scene, args.seconds, s)}
    methods = {m: go for m, go in methods.items() if m in args.methods.split(",")}
    for extra in args.mlt:
        params = {k: float(v) if "." in v else int(v)
                  for k, v in (kv.split("=") for kv in extra.split(","))}
        kind = params.pop("mmlt", 0)
        methods["%s[%s]" % ("mlt" if kind else "pssmlt", extra)] = (lambda p, r: lambda s: timed_mlt(
            scene, args.seconds, s, not args.no_mis, renderer=r, **p))(
                params, mmlt.MMLTRenderer if kind else None)
    errors = {m: [] for m in methods}
    mse = {m: [] for m in methods}
    for run in range(args.runs):
        for name, go in methods.items():
            img, seconds, spp = go(run + 1)
            err = float(np.mean((img - ref) ** 2 / (ref ** 2 + eps)))
            errors[name].append(err)
            mse[name].append(float(np.mean((img - ref) ** 2) / ref.mean() ** 2))
            print("run %d %-13s %.1f s, %.0f spp/mpp, mean %.6g, relMSE %.4g, MSE/mean^2 %.4g"
                  % (run, name, seconds, spp, img.mean(), err, mse[name][-1]), flush=True)
    first = next(iter(methods)) if "bdpt (auto)" not in methods else "bdpt (auto)"
    base, base2 = np.mean(errors[first]), np.mean(mse[first])
    for name, e in errors.items():
        print("%-13s relMSE %.4g +- %.2g (%d runs), %.2fx %s; median %.4g, %.2fx; less ref "
              "%.2fx; MSE/mean^2 %.4g, %.2fx"
              % (name, np.mean(e), np.std(e, ddof=1) / np.sqrt(len(e)), len(e),
                 np.mean(e) / base, first, np.median(e), np.median(e) / np.median(errors[first]),
                 (np.mean(e) - ref_err) / (base - ref_err),
                 np.mean(mse[name]), np.mean(mse[name]) / base2))


if __name__ == "__main__":
    main()
