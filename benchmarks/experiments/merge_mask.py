"""What a per-pixel merge mask (Grittmann et al. 2022) would gain over the global
merging decision, predicted from a ``vcm`` render's pilot moments (issue 30).

    python benchmarks/experiments/merge_mask.py [--scenes bs_c,lg_c,bs_p,sds,cornell-diffuse,veach-bidir]
        [--seeds 32] [--blur 4,16,24]
    python benchmarks/experiments/merge_mask.py --scenes sds --renders REFS --seeds 12
        --budget light_paths=0.25,connections=0 --scale 1 --blur 4,16,24

Per scene and seed a ``Renderer(merging=True)`` runs its pilot pass; its decision's
inputs (optimizer.Pilot._decide) are kept and each candidate's relative moment is
summed per pixel instead of over the film (``pixel_moments``: the same kernel as
MomentSamples.relative_moments, scattered by pixel; the pixels sum to the decision's
figure, checked), with the missed-path bias N B per pixel for the candidates without
merging (optimizer.missed_bias, per pixel).

A mask is exact in this model: a path's pixel is a property of the path (every
technique that samples it, the light image's t = 1 included, puts it in the same
pixel), so a per-pixel merging rate eta(p) gives each pixel the moment that merging
everywhere (p in the mask) or nowhere gives it.  (The weights: the camera walk knows
its pixel and uses eta(p) in its chains; a light subpath does not, and carries its
d_vc's merging part apart, d_vc being affine in h(eta) (mis.after_scatter), until a
connection names the camera sample's pixel or a t = 1 splat the pixel it lands in.)
Its cost: the budget without merging, plus the grid's build (and the stored vertices
if the budget does not connect) once any pixel merges, plus the queries in
proportion to the masked share of camera samples.

For each pair (a budget with light subpaths, its merging twin at each radius) the best
mask of k pixels holds the k of most negative m_on - m_off; scanning k gives the best
mask exactly.  Figures, as efficiency ratios (global's cost x moment over the mask's;
> 1: the mask gains):

  oracle   decided and evaluated on the mean of all seeds' per-pixel moments (the
           task's per-pixel minimum; optimistic: a per-pixel minimum of noisy
           moments is biased low);
  k seeds  decided on the mean of k seeds' moments (k pilots' worth of samples; the
           mask on them box-blurred, optimizer.BLUR), evaluated on the mean of the
           other seeds' moments, against the global decision made and evaluated the
           same way (median, mean, min and max over the groups of k seeds).  k = 1 is what
           the pilot knows; a render's re-decisions add about one pilot's samples
           each (optimizer.Pilot.moment_every).

Both over the best pair (the global decision's best candidate against the best mask of
any pair) and for the pair of the pilot's chosen budget.  ``--blur``: the mask's box
filter radii to try.  ``--renders REFS``: the same from real renders' per-pixel errors
(``rendered``).  Results: benchmarks/RESULTS.md, "A per-pixel merge mask".
"""
import argparse
import statistics
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

SCENES = ("bs_c", "lg_c", "bs_p", "sds", "cornell-diffuse", "veach-bidir")
SPP = {"bs_c": 512, "lg_c": 512, "bs_p": 512}      # render spp for N B (the rest: 32)


def pixel_moments(samples, rates, means, splats, pixels):
    """Per candidate (rows of ``rates``) and pixel, the summed relative moment of a pass
    that merges (optimizer.MomentSamples.relative_moments, merging=True), per camera
    sample of the pass: shape (candidates, pixels)."""
    import drjit as dr
    import mitsuba as mi
    from bdpt_drjit import optimizer as O
    from bdpt_drjit.vertices import gather
    f64 = dr.float64_array_t(mi.Float)
    groups = []
    for items, valid, weight in [(samples._camera_side(), None, samples.every)] + (
            [] if splats is None else [splats]):
        if valid is not None:
            items = gather(items, dr.compress(valid))
        if dr.width(items.f2) == 0:
            continue
        mean2 = means.squared(items.pixel, dr.sqrt(items.f2 + items.f2_pairs))
        groups.append((f64(items.f2 / mean2 * weight), f64(items.u_pt), f64(items.u_lt),
                       f64(items.u_vm), items.pixel, f64(items.f2_pairs / mean2 * weight),
                       f64(items.query)))
    dropped = O.outliers(groups, pixels)
    out = np.zeros((len(rates), pixels))
    for relative, u_pt, u_lt, u_vm, pixel, pairs, query in groups:
        out_pixel = dr.gather(mi.Bool, dropped, pixel)
        relative = dr.select(out_pixel, 0.0, relative)
        pairs = dr.select(out_pixel, 0.0, pairs)
        u_con = dr.maximum(1.0 - u_pt - u_lt - u_vm, 0.0)
        without = O._without_merges(relative, u_vm, query, O._missed(query, u_pt, u_lt, u_vm))
        for c, (r, k, first_hits, v) in enumerate(rates.tolist()):
            share = u_pt + r * u_lt + k * u_con + (v * u_vm if v > 0 else 0.0)
            if first_hits:
                share = dr.select(u_lt > 0, r * u_lt, share)
            share = dr.maximum(share, 1e-9)
            if v > 0:
                moment = relative / share + pairs * dr.square(v / share)
            else:
                moment = without[0] / dr.maximum(without[1] * share, 1e-9)
            acc = dr.zeros(f64, pixels)
            dr.scatter_reduce(dr.ReduceOp.Add, acc, moment, pixel)
            out[c] += acc.numpy()
    return out / samples.lanes


def pixel_bias(samples, means, shape, spp):
    """optimizer.missed_bias per pixel, times the render's spp and over the pixels (so
    that the pixels sum to the decision's N B)."""
    import drjit as dr
    from bdpt_drjit import optimizer as O
    from bdpt_drjit.vertices import gather
    h, w = shape
    items = samples._camera_side()
    miss = dr.compress(O._missed(items.query, items.u_pt, items.u_lt, items.u_vm))
    if dr.width(miss) == 0:
        return np.zeros(h * w)
    items = gather(items, miss)
    value = np.sqrt(np.maximum((items.f2 + items.f2_pairs).numpy(), 0.0))
    pixel = items.pixel.numpy().astype(np.int64)
    every = samples.every
    s = np.bincount(pixel, value * every, h * w).reshape(h, w)
    q = np.bincount(pixel, value * value * every, h * w).reshape(h, w)
    k2 = float((2 * O.BLUR + 1) ** 2)
    n = samples.lanes / float(h * w) * k2
    square = np.maximum((_blur(s, O.BLUR) * k2) ** 2 - _blur(q, O.BLUR) * k2, 0.0) / n ** 2
    mean2 = np.maximum(np.square(means.blurred.numpy().reshape(h, w)), means.floor)
    return (spp * square / mean2).ravel() / (h * w)


def pilot_moments(scene, spp, seed, max_depth):
    """One pilot pass: (candidates, per-pixel moments (C, pixels), Costs, chosen budget,
    film shape)."""
    from bdpt_drjit import optimizer as O
    from bdpt_drjit.render import Renderer
    r = Renderer(scene, spp=spp, seed=seed, max_depth=max_depth, merging=True)
    pilot, kept = r.pilot, {}
    original = pilot._decide

    def capture(cands, samples, splats, mean, spp_, rates, kept_=(), filled=None):
        rr, k, eta = rates
        rows = np.array([[c.light_ratio / rr, c.kappa(1, pilot.costs.stored_per_path) / k
                          if k else 0.0, float(c.light_first_hits), pilot._merge_rate(c, eta)]
                         for c in cands])
        means = O.PilotMeans.of(mean, spp_, filled)
        m = pixel_moments(samples, rows, means, splats, mean.shape[0] * mean.shape[1])
        bias = pixel_bias(samples, means, mean.shape, pilot.spp) if eta > 0 else 0.0
        total = samples.relative_moments(rows, means, splats, True) / samples.lanes
        assert np.allclose(m.sum(1), total, rtol=1e-3, atol=1e-9), (m.sum(1), total)
        m[[not c.merging for c in cands]] += bias
        kept.update(cands=list(cands), m=m, shape=mean.shape)
        return original(cands, samples, splats, mean, spp_, rates, kept_, filled)

    pilot._decide = capture
    r.run_pass()
    return kept["cands"], kept["m"], pilot.costs, pilot.first.budget, kept["shape"]


def _blur(image, radius):
    """optimizer._blur (on the device) of a NumPy image (H, W)."""
    import mitsuba as mi
    from bdpt_drjit import optimizer as O
    return np.array(O._blur(mi.Float64(image.ravel()), image.shape, radius)).reshape(image.shape)


def blur(m, shape):
    """The box filter of the pilot's means, of radius BLUR_RADIUS (``--blur``)."""
    return _blur(m.reshape(shape), BLUR_RADIUS).ravel()


BLUR_RADIUS = 4         # optimizer.BLUR


def pairs(cands):
    """(index without merging, index with merging) per merging candidate."""
    off = {(c.light_ratio, c.connections, c.light_first_hits): i
           for i, c in enumerate(cands) if not c.merging}
    return [(off[(c.light_ratio, c.connections, c.light_first_hits)], i)
            for i, c in enumerate(cands) if c.merging]


def split_cost(costs, off, on):
    """(cost without merging, merging's fixed cost, its queries' cost at full share)."""
    from bdpt_drjit.optimizer import QUERY_STEPS
    eta = on.light_ratio * costs.merge_eta * on.radius_scale ** 2
    queries = (QUERY_STEPS * costs.merges + costs.merge_items * eta) * costs.units.merge_step
    base = costs.of(off)
    return base, costs.of(on) - base - queries, queries


def best_mask(decide_off, decide_on, fixed_costs):
    """The mask of least cost x moment under the moments used to decide: a bool per
    pixel (cost = base + [any] fixed + share x queries)."""
    base, fixed, queries = fixed_costs
    d = decide_on - decide_off
    order = np.argsort(d)
    moment = decide_off.sum() + np.concatenate([[0.0], np.cumsum(d[order])])
    k = np.arange(len(d) + 1)
    cost = base + (k > 0) * fixed + queries * k / len(d)
    best = int(np.argmin(cost * moment))
    mask = np.zeros(len(d), dtype=bool)
    mask[order[:best]] = True
    return mask


def mask_efficiency(mask, off, on, fixed_costs):
    """cost x moment of ``mask`` under moments (off, on) per pixel."""
    base, fixed, queries = fixed_costs
    moment = np.where(mask, on, off).sum()
    return (base + mask.any() * fixed + queries * mask.mean()) * moment


def analyse(cands, runs, costs, chosen, shape, sizes=(1, 2, 4, 8)):
    """Per set of pairs (all; the chosen budget's): the oracle (ratio, share) and per
    k in ``sizes`` the held-out ratios (median, mean, min, max over the groups of k
    seeds, and the median mask share): the mask and the global decision from k seeds' mean
    moments (the mask's blurred), evaluated on the mean of all the other seeds'."""
    prs = pairs(cands)
    off = replace(chosen, merging=False, radius_scale=1.0)
    mine = [p for p in prs if cands[p[0]].light_ratio == off.light_ratio
            and cands[p[0]].connections == off.connections
            and cands[p[0]].light_first_hits == off.light_first_hits]
    mean = lambda rs: np.mean(rs, axis=0)
    out = {}
    for key, ps in (("all", prs), ("chosen", mine)):
        if not ps:
            continue
        rows = [ratio(cands, costs, ps, mean(runs), mean(runs), None)]
        for k in sizes:
            if 2 * k > len(runs):
                continue
            held = [ratio(cands, costs, ps, mean(runs[g:g + k]), mean(runs[:g] + runs[g + k:]), shape)
                    for g in range(0, len(runs) - k + 1, k)]
            rows.append((k, statistics.median(r for r, _ in held), statistics.mean(r for r, _ in held),
                         min(r for r, _ in held), max(r for r, _ in held),
                         statistics.median(sh for _, sh in held)))
        out[key] = rows
    return out


def ratio(cands, costs, ps, decide, evaluate, shape):
    """Efficiency of the global decision over the mask's (> 1: the mask gains), both
    decided on the moments ``decide`` (blurred where ``shape`` is given, for the mask)
    and evaluated on ``evaluate``; and the mask's share of the pixels.  Among the
    pairs ``ps`` (all pairs: every candidate for the global decision)."""
    split = {p: split_cost(costs, cands[p[0]], cands[p[1]]) for p in ps}
    every = [i for i in range(len(cands))] if ps == pairs(cands) else sorted({q for p in ps for q in p})
    g = min(every, key=lambda i: costs.of(cands[i]) * decide[i].sum())
    options = [(costs.of(cands[g]) * decide[g].sum(), None, None)]
    sm = (lambda x: blur(x, shape)) if shape is not None else (lambda x: x)
    for a, b in ps:
        mask = best_mask(sm(decide[a]), sm(decide[b]), split[(a, b)])
        options.append((mask_efficiency(mask, decide[a], decide[b], split[(a, b)]), mask, (a, b)))
    _, mask, p = min(options, key=lambda o: o[0])
    glob = costs.of(cands[g]) * evaluate[g].sum()
    if mask is None:
        return 1.0, 0.0
    return glob / mask_efficiency(mask, evaluate[p[0]], evaluate[p[1]], split[p]), mask.mean()


def load(name):
    from benchmarks import smallvcm
    from benchmarks.scenes import SCENES as S
    if name in ("bs_c", "lg_c", "bs_p"):
        return smallvcm.build_scene(name), smallvcm.MAX_DEPTH
    spec = S[name]
    w, h, _ = spec.resolution(128)
    return spec.load(w, h), spec.max_depth


def render_error(scene, depth, spp, settings, ref, seed):
    """(seconds, per-pixel relative squared error against ``ref``: the suite's metric
    before its mean) of one render."""
    import time
    import bdpt_drjit
    start = time.perf_counter()
    img = np.asarray(bdpt_drjit.render(scene, spp=spp, seed=seed, max_depth=depth,
                                       **settings).image)[..., :3]
    seconds = time.perf_counter() - start
    return seconds, np.mean((img - ref) ** 2 / (ref ** 2 + 1e-2), axis=-1).ravel()


def rendered(name, refs, off, scale, seeds, radii=(BLUR_RADIUS,)):
    """The mask's gain on real renders (``--renders``): the budget ``off`` and its
    merging twin at ``scale`` x the auto radius, fixed, interleaved per seed after a
    warm-up; per pixel the relative squared error.  The mask and the global choice are
    decided on half the seeds (the mask's errors blurred) and evaluated on the other
    half; merging's time (the two renders' difference) is split into a fixed part and
    the queries' as the pilot's counted costs split it (``split_cost``), and a mask
    pays the queries' part by its share."""
    import glob
    from bdpt_drjit.render import Renderer
    ref = np.load(glob.glob("%s/%s_*.npy" % (refs, name))[0])[..., :3]
    scene, depth = load(name)
    spp = SPP.get(name, 32)
    radius = scale * Renderer(scene, spp=1, max_depth=depth, merging=True).merge_radius
    settings = (off, dict(off, merging=True, radius=radius))
    for budget in settings:
        render_error(scene, depth, spp, budget, ref, 999)                  # kernels
    runs = ([], [])
    for s in range(seeds):
        for i in ((0, 1) if s % 2 == 0 else (1, 0)):
            runs[i].append(render_error(scene, depth, spp, settings[i], ref, s))
    t_off, t_on = (statistics.median(t for t, _ in r) for r in runs)
    cands, _, costs, _, _ = pilot_moments(scene, spp, 1, depth)
    b_off = next(c for c in cands if not c.merging and c.light_ratio == off["light_paths"]
                 and str(c.connections) == str(off["connections"]) and not c.light_first_hits)
    _, fixed, queries = split_cost(costs, b_off, replace(b_off, merging=True, radius_scale=scale))
    share = fixed / (fixed + queries)
    cost = (t_off, share * (t_on - t_off), (1 - share) * (t_on - t_off))
    print("%s renders, %s against merging at %g x the radius, %d seeds: %.2f s / %.2f s "
          "(merging's fixed part %.2f), relMSE %.4g / %.4g" % (name, off, scale, seeds, t_off, t_on, share,
                                  *(np.mean([x.mean() for _, x in r]) for r in runs)))
    global BLUR_RADIUS
    for BLUR_RADIUS in radii:
        print("  blur radius %d: mask from one half, on the other: %s" % (BLUR_RADIUS, ", ".join(
            "%.3f (share %.2f)" % halves(runs, cost, ref.shape[:2], d) for d in (0, 1))))


def halves(runs, cost, shape, which):
    """(global over mask efficiency, the mask's share): both decided on one half of the
    seeds (``which``), evaluated on the other."""
    n = len(runs[0]) // 2
    d, e = (slice(0, n), slice(n, None)) if which == 0 else (slice(n, None), slice(0, n))
    (m_off, m_on), (v_off, v_on) = ([np.mean([x for _, x in r[h]], axis=0) for r in runs]
                                    for h in (d, e))
    t_off, t_on = cost[0], sum(cost)
    merge = t_on * m_on.sum() < t_off * m_off.sum()            # the global decision
    glob_eff = t_on * v_on.sum() if merge else t_off * v_off.sum()
    mask = best_mask(blur(m_off, shape), blur(m_on, shape), cost)
    return glob_eff / mask_efficiency(mask, v_off, v_on, cost), mask.mean()


def report(cands, runs, costs, budget, shape, radius):
    """Print ``analyse``'s figures with the mask's moments blurred at ``radius``."""
    global BLUR_RADIUS
    BLUR_RADIUS = radius
    print(" blur radius %d" % radius)
    for key, rows in analyse(cands, runs, costs, budget, shape).items():
        print("  %-6s oracle %.3f (mask share %.2f);" % ((key,) + rows[0])
              + ";".join(" %d seeds %.3f (mean %.3f, %.3f-%.3f, share %.2f)" % r
                         for r in rows[1:]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--seeds", type=int, default=32)
    ap.add_argument("--blur", default="4", help="radii of the mask's box filter, e.g. 2,4,8")
    ap.add_argument("--renders", metavar="REFS", help="render a budget and its merging twin "
                    "instead (``rendered``; REFS: the suite's references, SCENE_*.npy)")
    ap.add_argument("--budget", default="light_paths=0.5,connections=all",
                    help="--renders: the budget without merging")
    ap.add_argument("--scale", type=float, default=0.25, help="--renders: merging radius / auto")
    a = ap.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))      # this checkout
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    for name in a.scenes.split(","):
        if a.renders:
            off = {k: (v if v == "all" else float(v) if "." in v else int(v))
                   for k, v in (kv.split("=") for kv in a.budget.split(","))}
            rendered(name, a.renders, off, a.scale, a.seeds, [int(x) for x in a.blur.split(",")])
            continue
        scene, depth = load(name)
        spp = SPP.get(name, 32)
        runs, chosen = [], []
        for seed in range(1, a.seeds + 1):
            cands, m, costs, budget, shape = pilot_moments(scene, spp, seed, depth)
            runs.append(m)
            chosen.append(str(budget))
        common = max(set(chosen), key=chosen.count)
        budget = next(c for c in cands if str(c) == common) if any(
            str(c) == common for c in cands) else budget
        print("%s (%d spp, %d seeds; pilot chose: %s)" % (name, spp, a.seeds, "; ".join(
            "%s x%d" % (c, chosen.count(c)) for c in sorted(set(chosen)))))
        for radius in (int(x) for x in a.blur.split(",")):
            report(cands, runs, costs, budget, shape, radius)
        sys.stdout.flush()


if __name__ == "__main__":
    main()
