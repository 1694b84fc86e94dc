"""Efficiency-aware budgets (Grittmann, Yazici, Georgiev, Slusallek 2022): choose the
budget (budgets.py) whose cost times summed relative second moment is smallest.

The pilot.  One pass opens a render whose budget is "auto"
(render.Renderer._plan_pilot; on a large film over every other pixel:
Pilot.stride): full BDPT (light_paths 1, connections "all") with the balance
heuristic, in which every contribution also reports its balance weight split into
three groups of strategies: path tracing (s <= 1), the light image (t = 1) and
connections (u_pt + u_lt + u_con = 1; the two ends of the ratio chains isolate u_pt
and u_lt, walk.PathState.d_end).  The pass keeps the splats that land in its own
pixels (film.py), so it is a complete MIS estimator of its pixels and part of the
image; a small render's pilot, on one pixel in several, prices alone (Pilot.stride).
(A pass of light and path tracing first, to count the camera walk's rays
apart, cost a second traced pass: 10-14 ms of a 64x64 render's 47 ms.)

Second moments.  The balance-heuristic combination of a candidate c, whose rates are
1, r_c and kappa_c for the three groups (mis.py), has second moment
integral f^2 / P_c, P_c = sum of rate x density over the strategies.  A pilot sample
F = f / P_pilot estimates it as F^2 P_pilot / P_c = F^2 / (u_pt + r_c u_lt + kappa_c u_con)
(the paper's reweighting by the ratio of balance sums).  A path only light subpaths
can sample (u_pt = 0) makes path tracing's moment infinite: it is never chosen where
it would miss light.  Each pixel's moment is divided by its squared mean (the pilot
image, box-filtered, without the sample itself: PilotMeans) and the sum over pixels,
a firefly pixel left out (outliers), is the candidate's relative error.

Re-decisions.  The first pass that ends at or after 4, 16 and 64 times the pilot's
spp (render.Renderer._plan_rounds) is a moment pass of the budget being rendered,
with the balance heuristic at that budget's rates (r_B, kappa_B), its camera side
recorded on one lane in 2 x spp (the pilot's memory; in a vcm render without merging
about 8x the pilot's lanes: Pilot.moment_every) and its light side on one light
subpath in every x r_B (render._splat_moments).  Its shares are of P_B, so
P_c / P_B = u_pt + (r_c / r_B) u_lt + (kappa_c / kappa_B) u_con: that gives every
candidate whose strategy groups have a positive rate in the budget (``covers``), and a
light image splat counts as value / r_B per camera sample (N_C / N_L times it).  Each
candidate's moment per camera sample is averaged over the moment passes so far, and
the means are the whole image's so far.  After path tracing there is nothing to
re-decide from: its samples give no light subpath's density.

Merging (``vcm``: settings.merging with auto budgets).  Every candidate comes with
merging off and, where it has light subpaths, on at each radius of MERGE_RADII (the
pilot's radius and a quarter of it; ``merging_candidates``).  The BDPT
pilot pass then merges too (the balance heuristic), for its moments only: its image
is BDPT's (mis.Weights' shadow), and where merging is chosen render.py turns its
samples into the estimator with merging (each contribution x (1 - u_vm), the merges
added).  The pilot pass merges at its own rate eta_P = pi r^2 N_L, and each contribution
also reports merging's share u_vm of its balance sum (mis.py's d_vm), so
P_c / P = u_pt + r_c u_lt + kappa_c u_con + v_c u_vm with v_c = eta_c / eta_P, eta_c
the candidate's rate in the passes to come (their radii, times its radius_scale, and
sizes: Costs.merge_eta).
A merge query is one sample: the photons' squares are independent samples as above,
and the rest of the query's square (the pairs, F_agg^2 - sum F_i^2) is the part that
more photons do not average away, the camera path's own variance: it scales as
(v_c / share)^2 (with the pairs scaled like single samples, the moments fell as 1 / eta
and merging looked 10x better than it renders in Veach's room).  A candidate without
merging reads a path's moment from the merges only where merging holds nearly all of
its balance sum (MERGE_ONLY), else from the other samples as BDPT's pilot would.  A
path no technique but merging reaches (a point light's caustic seen in a mirror) gives
those candidates no moment but a bias (missed_bias): their error after the render's N
samples per pixel is cost x (M + N B), not an infinite moment.  Merging's work is
counted: the grid's build per stored vertex and the query steps (QUERY_STEPS per
query and the items visited, which grow with eta).  Where the decision leaves merging off, no later
pass builds a grid or queries it (render.py), but the re-decisions still weigh the
merging candidates, by the pilot's moments (Pilot.redecide), so that the other
candidates' moments, firmer with every moment pass, can turn merging on.  The
decision is global: no per-pixel merge mask (Grittmann et al. 2022); measured, it
does not pay from the pilot's moments.  A mask would be consistent: a path's pixel
is the same for every technique that samples it (the light image's splat lands in
the pixel its t >= 2 twins' camera rays pass through), so a rate eta(p) per pixel
keeps the weights summing to 1, with the light subpath's chains carrying merging's
part apart until a connection or a splat names the pixel (d_vc is affine in h(eta),
mis.py's after_scatter; the shadow pass's d_vm is that part for the balance
heuristic).  But its decision rests on per-pixel moments, and a pilot's are too
sparse (benchmarks/experiments/merge_mask.py, RESULTS.md): a mask chosen from one
pilot's moments, blurred as its means are, gained 0.96-1.00x (medians over 32 seeds,
judged on the other seeds' moments) on SmallVCM's boxes and lost 3.4x on the SDS
scene, whose mirror caustic's pixels it leaves out; only in-sample per-pixel minima
(the pilot's noise) promised 1.12-1.34x.  Real renders' per-pixel errors, at
hundreds of samples per pixel, give a mask 1.23x on SmallVCM's large glass sphere
and 1.15x on the SDS scene (there as a region, two thirds of the film): a mask would
have to be decided from the render's own errors, not from the pilot.

Costs are counted, not timed: the pilot counts per camera sample the rays of the
camera walk with s <= 1, per light subpath the rays of the light walk and its t = 1
splats, the light vertices it stores, and the connections' shadow rays (counted apart
in the camera walk: walk.PathState.links); a vertex cache of M
connects M / (stored vertices per light subpath) of them.  Each count is priced by
the machine's unit cost (units.py, measured once by render.calibrate), and path
tracing, where Mitsuba's path renders it, by that megakernel's cost per ray.  The
counts are deterministic for a seed, so the decision is too: timing the pilot's
kernels chose different budgets for one seed with the machine's load, the kernel
cache (a first render priced compilation) and the integrator's construction.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import drjit as dr
import mitsuba as mi
import numpy as np

from .backend import device_array, read_values
from .budgets import Budget
from .units import UnitCosts
from .vertices import empty, gather

RATIOS = (0.0, 0.25, 0.5, 1.0, 2.0)
FIRST_HIT_RATIOS = (2.0, 4.0)   # light subpaths per camera sample of light_first_hits ones
CACHE_PICKS = (1, 2)
MIN_SPP = 16                   # fewer samples: the pilot would cost too much
# A pilot pass's samples at least, for its moments.  Its kernels' time is what a pass
# of that many BDPT samples costs: a full-film pilot at 128x128 (16384 lanes) took
# 90-180 ms against 35-65 ms for half of it (glass pane, loaded).
PILOT_LANES = {"llvm": 1 << 13, "cuda": 1 << 17}
# A small render's pilot takes at most one of this many of its samples (Pilot.stride):
# a pilot sample of full BDPT costs about 4-6 samples of path tracing, so the pilot
# stays near 4% of a render that then path-traces.
PILOT_SHARE = 128
BLUR = 4                       # radius of the box filter on the pilot's mean image


def _pilot_lanes() -> int:
    return PILOT_LANES["cuda" if mi.variant().startswith("cuda") else "llvm"]


def candidates(spectral: bool, light_image: bool = True, merging: bool = False) -> list[Budget]:
    """Path tracing; per light-subpath ratio, light tracing with path tracing, with
    all connections or with a vertex cache; and light tracing of smooth first hits
    (budgets.Budget.light_first_hits; it needs a light image) at the largest ratio and
    at twice it.  That one wins where the camera walk past z_1 costs much and adds
    little, and there its noise falls with every light subpath more: on the point-light
    caustic 4 per camera sample are 1.11x more efficient than 2 (the camera walk's
    share of the time halves).  At ratios below 2 it never came close on the suite
    and would only lengthen the decision.  (Spectral variants: one light subpath per
    camera sample at most, as its wavelengths are a camera sample's.)"""
    ratios = (0.0, 1.0) if spectral else RATIOS
    out = [Budget(0.0, 0)]
    for r in ratios[1:]:
        out += [Budget(r, 0), Budget(r, "all")] + [Budget(r, m) for m in CACHE_PICKS]
    if light_image:
        out += [Budget(r, 0, True) for r in ((1.0,) if spectral else FIRST_HIT_RATIOS)]
    else:
        # Light subpaths then serve connections alone: a budget with light subpaths and
        # no connections would be path tracing that pays for light walks.
        out = [b for b in out if b.light_ratio == 0 or b.connects]
    if merging:
        return merging_candidates(out)
    return out


def merging_candidates(budgets: list[Budget]) -> list[Budget]:
    """Where merging may be on (``vcm``): each budget without merging, and each one
    with light subpaths (not light_first_hits, which leaves smooth first hits to the
    light image) with merging added at each radius of MERGE_RADII: merging is one more
    rate of the MIS (mis.py), a candidate like the others, priced by its counted work
    (``Costs.of``)."""
    off = [replace(b, merging=False) for b in budgets]
    on = [replace(b, merging=True, radius_scale=scale) for scale in MERGE_RADII
          for b in budgets if b.light_ratio > 0 and not b.light_first_hits]
    return off + on


# The merging radii a candidate may take, as fractions of the radius the pilot merges
# at (merge.first_radius's r_i).  The pilot needs the large one to see the paths only
# merging samples well (at 0.5 or 0.25 of it the SDS scene's pilot left merging off),
# but a render merges better at a smaller one where photons are dense: the eta of a
# candidate at scale s is s^2 times the pilot's, its rate v (P_c / P) and the items
# its queries visit fall with it (Costs.merging).
MERGE_RADII = (1.0, 0.25)


@dataclass
class MomentSample:
    """One pilot contribution: its pixel, F^2 (luminance) and balance-weight groups."""
    pixel: mi.UInt32
    f2: mi.Float
    u_pt: mi.Float
    u_lt: mi.Float
    u_vm: mi.Float          # merging's share (mis.py's d_vm; 0 without merging)
    f2_pairs: mi.Float      # a merge query: the pairs' part of F^2 (``MomentSamples.add``)
    query: mi.Float         # 1 for a merge query's sample, else 0


def luminance(value) -> mi.Float:
    """The mean of a spectrum's channels (RGB, spectral and mono alike).  Not
    ``dr.mean``: it scales by the array's width, a literal in the kernel, so each
    number of samples compiled a kernel of its own."""
    channels = mi.unpolarized_spectrum(value)
    return sum(channels[i] for i in range(len(channels))) / len(channels)


class MomentSamples:
    """A moment pass's contributions.  Camera-side ones go to SLOTS slots per
    recorded camera lane, counted in the walk's state (no atomics; more are dropped):
    every lane of the pilot, every ``every``-th lane of a later pass (its memory stays
    the pilot's); light-image ones travel in the splat records (vertices.Splat's u_pt,
    u_lt)."""

    SLOTS = 32

    def __init__(self, lanes: int, every: int = 1, shadow: bool = False, record: bool = True,
                 allocate: bool = True, zeroed: bool = False):
        """``shadow``: the pass's merges are for its moments only (mis.Weights): a
        contribution of the image then counts as the estimator with merging would
        have weighted it, value x (1 - u_vm) (the balance heuristic's), and
        ``correction`` sums per lane what turns the lane's value into that estimator's
        (-u_vm x value, and the merges): render.py adds it where merging is chosen.
        ``record``: False for a shadow pass that only needs its correction (the vcm
        pilot's first pass merged for it before; no pass does since, Pilot.budget).
        ``allocate``: False leaves the buffers to ``allocate``, which a frozen camera
        walk calls inside its recording (render.py; see vertices.LightVertexStore).
        ``zeroed``: the slots filled with zeros first (a timed pass's, below)."""
        self.lanes, self.every, self.shadow, self.record = lanes, every, shadow, record
        self.zeroed = zeroed
        self.correction = self.items = self.count = self.base = self._every = None
        if allocate:
            self.allocate()

    def allocate(self) -> None:
        lanes, every = self.lanes, self.every
        self.correction = dr.zeros(mi.Spectrum, lanes) if self.shadow else None
        if not self.record:
            return
        # Only the slots a lane used are read (``_camera_side``).  A timed pass
        # (render.calibrate) zeroes them by a memset, which its timer does not count:
        # written first by the timed camera walk, the fresh pages' faults were charged
        # to connections, 1.5-9x their cost (Veach's MIS scene 1.6-5.8e-7 s per sample
        # against 0.65e-7; see vertices.LightVertexStore).  Elsewhere the memset is
        # only work: 7 launches, 0.3 ms of a 64x64 pilot pass's 2.4 ms of kernels.
        self.items = empty(MomentSample, -(-lanes // every) * self.SLOTS, zeroed=self.zeroed)
        self.count = dr.zeros(mi.UInt32, lanes)           # slots used, per lane
        self._every = dr.opaque(mi.UInt32, every)
        # Each lane's first slot, or NOT_RECORDED (one gather per contribution).
        lane = dr.arange(mi.UInt32, lanes)
        self.base = dr.select(lane % self._every == 0, lane // self._every * self.SLOTS,
                              self.NOT_RECORDED)
        dr.make_opaque(self.items, self.count, self.base)

    def buffers(self) -> tuple:
        """The arrays the camera walk writes, for ``adopt`` (a frozen walk's outputs)."""
        return self.correction, self.items, self.count, self.base, self._every

    def adopt(self, buffers: tuple) -> None:
        self.correction, self.items, self.count, self.base, self._every = buffers

    NOT_RECORDED = 0xFFFFFFFF

    def add(self, slot, lane, pixel, value, u_pt, u_lt, u_vm, active, singles=None):
        """Record a camera-side contribution in the lane's next slot; returns the slot
        count.  ``singles``: a merge query's value is a sum over photons, and this the
        sum of their squares; the rest of its square is the pairs' (``f2_pairs``)."""
        lum = luminance(value)
        if self.shadow:
            change = value if singles is not None else value * -mi.Float(u_vm)
            dr.scatter_reduce(dr.ReduceOp.Add, self.correction, change, lane, active)
            if not self.record:
                return slot
            if singles is None:
                lum = lum * (1.0 - u_vm)
        base = dr.gather(mi.UInt32, self.base, lane, active)
        ok = active & (lum != 0) & (slot < self.SLOTS) & (base != self.NOT_RECORDED)
        f2 = dr.square(lum)
        single = f2 if singles is None else dr.minimum(singles, f2)
        dr.scatter(self.items, MomentSample(pixel=mi.UInt32(pixel), f2=mi.Float(single),
                                            u_pt=mi.Float(u_pt), u_lt=mi.Float(u_lt),
                                            u_vm=mi.Float(u_vm), f2_pairs=mi.Float(f2 - single),
                                            query=mi.Float(0.0 if singles is None else 1.0)),
                   base + slot, ok)
        return slot + dr.select(ok, 1, 0)

    def relative_moments(self, rates: np.ndarray, means: "PilotMeans", splats=None,
                         merging: bool = False) -> np.ndarray:
        """Per candidate (rows of ``rates``: r, kappa, light_first_hits, merging rate v,
        each relative to the pass's own rates), the second moment of its balance
        estimator relative to each pixel's squared mean (``means``), summed over these
        samples (times ``every``) and the pass's splats (a ``MomentSample`` of them,
        with its validity, the weight of each and the pass's r = N_L / N_C), outlier
        pixels left out (``outliers``): an estimate of the sum over the pass's camera
        samples.

        A light_first_hits candidate samples a path whose z_1 is smooth by the light
        image alone, and any other path as its base budget (r, kappa) does.  The light
        image can sample exactly the paths with u_lt > 0 (at a delta z_1 the t = 1
        term is 0), which tells the two kinds apart without a flag per sample.

        ``merging``: the samples may hold merges (a vcm moment pass): the pairs and, for
        candidates without merging, the maximum heuristic over the kinds of sample
        (below); without, the kernel is BDPT's alone.
        """
        f64 = dr.float64_array_t(mi.Float)
        groups = []         # per kind of sample: (relative F^2, u_pt, u_lt, u_vm, pixel,
                            # relative F^2 of merge pairs)
        kinds = [(self._camera_side(), None, self.every, means.own)]
        if splats is not None:          # a splat is 1 / r of a camera sample's share
            items, valid, weight, r = splats
            own = means.own if means.light_own is None else means.light_own
            kinds.append((items, valid, weight, own * dr.opaque(mi.Float, 1.0 / r)))
        for items, valid, weight, own in kinds:
            if valid is not None:
                items = gather(items, dr.compress(valid))  # the recorded samples only
            if dr.width(items.f2) == 0:
                continue
            mean2 = means.squared(items.pixel, dr.sqrt(items.f2 + items.f2_pairs), own)
            weight = dr.opaque(mi.Float, weight)           # no kernel per value
            groups.append((f64(items.f2 / mean2 * weight), f64(items.u_pt), f64(items.u_lt),
                           f64(items.u_vm), items.pixel, f64(items.f2_pairs / mean2 * weight),
                           f64(items.query)))
        dropped = outliers(groups, dr.width(means.blurred))
        # The candidates' rates in arrays, read by index: as literals, kappa (new with
        # every render) compiled a kernel per decision (0.03-0.05 s).
        merge = rates[:, 3] if rates.shape[1] > 3 else np.zeros(len(rates))   # no merging
        rate, kappa, vm = f64(rates[:, 0]), f64(rates[:, 1]), f64(merge)
        # Gathered at an opaque index: a literal index reads the value to the host, one
        # sync per candidate and array (114 in a pilot pass: a GPU sync each).
        first = dr.opaque(mi.UInt32, 0)
        sums = np.zeros(len(rates))
        for relative, u_pt, u_lt, u_vm, pixel, pairs, query in groups:
            out_pixel = dr.gather(mi.Bool, dropped, pixel)
            relative = dr.select(out_pixel, 0.0, relative)
            pairs = dr.select(out_pixel, 0.0, pairs)
            u_con = dr.maximum(1.0 - u_pt - u_lt - u_vm, 0.0)
            # Each candidate's sum is scatter-added into its slot, all in one kernel (a
            # reduction per candidate took 200 launches: the decision took 14 ms at
            # 256x256, now 8).
            out = dr.zeros(f64, len(rates))
            without = _without_merges(relative, u_vm, query, _missed(query, u_pt, u_lt, u_vm))
            for c, (first_hits, merges) in enumerate(zip(rates[:, 2].tolist(),
                                                         (merge > 0).tolist())):
                r, k, v = (dr.gather(f64, a, first + c) for a in (rate, kappa, vm))
                share = u_pt + r * u_lt + k * u_con + (v * u_vm if merges else 0.0)
                if first_hits:
                    share = dr.select(u_lt > 0, r * u_lt, share)
                # A share of 0: the candidate cannot sample this path (infinite moment).
                share = dr.maximum(share, 1e-9)
                if not merging:                                 # (BDPT's kernel, as before)
                    moment = relative / share
                elif merges:
                    moment = relative / share + pairs * dr.square(v / share)
                else:
                    moment = without[0] / dr.maximum(without[1] * share, 1e-9)
                dr.scatter_reduce(dr.ReduceOp.Add, out, moment, c)
            sums += out.numpy()
        return sums

    def _camera_side(self) -> MomentSample:
        """The recorded camera-side samples (the slots each lane used)."""
        idx = dr.arange(mi.UInt32, dr.width(self.items.f2))
        live = idx % self.SLOTS < dr.gather(mi.UInt32, self.count, idx // self.SLOTS * self._every)
        return gather(self.items, dr.compress(live))


def _without_merges(relative, u_vm, query, missed):
    """In a pass that merges (MomentSamples.add), what a candidate without merging reads
    of a sample, (relative F^2, the share of the balance sum it stands for): a path's
    moment from one kind of sample, merge queries where u_vm >= MERGE_ONLY, over u_vm
    (a mirror caustic, which BDPT's pilot cannot see), else the other samples as
    BDPT's pilot has them (value / (1 - u_vm), shares over 1 - u_vm); its moment is
    relative / (share x the candidate's own share).  With every merge sample in (the
    balance heuristic), sparse photons' fireflies made vcm choose worse budgets than
    bdpt in Veach's room.  A ``missed`` path (``missed_bias``) is no sample of these
    candidates: its error there is a bias, counted apart.  (A candidate with merging,
    of rate v: its single part over its share and a merge query's pairs scaled by
    (v / share)^2.)"""
    mine = dr.select(query > 0, u_vm >= MERGE_ONLY, u_vm < MERGE_ONLY) & ~missed
    return dr.select(mine, relative, 0.0), dr.select(query > 0, u_vm, 1.0 - u_vm)


# A candidate without merging takes a path's moment from merge samples where merging
# holds at least this share of the path's balance sum (at the pilot's eta), from the
# other samples elsewhere (MomentSamples.relative_moments): a path BDPT's techniques
# all but cannot sample (the SDS scene's mirror caustic) is seen through its merges.
# Measured, not derived: at 0.9 the merges of Veach's room's diffuse paths (merging
# holds 90-99.9% of their sums at the pilot's large eta) decided for the candidates
# without merging, and vcm chose worse budgets than bdpt in 4 of 8 seeds (1 at 0.999);
# at 0.9999 the SDS scene left merging off (4 seeds of 4).
MERGE_ONLY = 0.999

# A merge query's path that no technique without merging samples: its balance sum
# without merging is below this share of the whole (exactly 0 in float32 for a caustic
# of a point light seen in a mirror, L-S-D-S-E: nothing but merging reaches it).
MISSED = 1e-7


def _missed(query, u_pt, u_lt, u_vm):
    """Merge queries of paths that the candidates without merging miss (MISSED)."""
    return (query > 0) & (u_pt + u_lt + dr.maximum(1.0 - u_pt - u_lt - u_vm, 0.0) < MISSED)


def missed_bias(samples: "MomentSamples", means: "PilotMeans", shape: tuple) -> float:
    """The relative squared bias of a budget without merging, per pixel and averaged
    over the film (H, W = ``shape``): the paths it misses (``_missed``; the merge
    queries' values estimate their mean m_p) over the pilot image's blurred mean
    (``means``), m_p blurred as that mean is.  The pass's camera samples are spread
    evenly, n = lanes / pixels per pixel (the pilot's alternate pixels average out in
    a window); m_p^2 from the window's sum S and sum of squares Q of the samples'
    values: (S^2 - Q) / (n k^2)^2, unbiased for independent samples.  A budget that
    misses a path does not have an infinite second moment: after N samples per pixel
    its relative MSE is M / N + B, its error at equal time cost x (M + N B)
    (Pilot._decide).  Measured on SmallVCM's point-light box: the pilot's 2 such
    samples of 8192 gave the candidates without merging summed moments of 1e5 (a share
    floored at 1e-9) against 0.6 with merging, which renders at 2.8x the cost for
    0.94x the relative MSE."""
    if not samples.record:
        return 0.0
    items = samples._camera_side()
    miss = dr.compress(_missed(items.query, items.u_pt, items.u_lt, items.u_vm))
    if dr.width(miss) == 0:
        return 0.0
    items = gather(items, miss)
    h, w = shape
    f64 = dr.float64_array_t(mi.Float)
    value = f64(dr.sqrt(dr.maximum(items.f2 + items.f2_pairs, 0.0)))
    every = dr.opaque(f64, samples.every)    # one lane in ``every`` recorded
    s, q = dr.zeros(f64, h * w), dr.zeros(f64, h * w)
    dr.scatter_reduce(dr.ReduceOp.Add, s, value * every, items.pixel)
    dr.scatter_reduce(dr.ReduceOp.Add, q, value * value * every, items.pixel)
    n = samples.lanes / float(h * w) * (2 * BLUR + 1) ** 2      # samples in a window
    k2 = float((2 * BLUR + 1) ** 2)
    square = (dr.maximum(dr.square(_blur(s, shape) * k2) - _blur(q, shape) * k2, 0.0)
              * dr.opaque(f64, 1.0 / n ** 2))
    mean2 = dr.maximum(dr.square(f64(means.blurred)), dr.opaque(f64, means.floor))
    return float(dr.mean(square / mean2)[0])


# Outlier pixels: a pixel whose pilot moment outweighs all the others together weighs
# nothing in the decision (up to 1 in OUTLIER_SHARE of the pixels, at least one).  One
# pixel held 97-100% of the summed moment in 5 of 12 pilots of Veach's MIS scene
# (128x72): every candidate's moment was that one sample's, so the cheapest, path
# tracing, won, and it renders that scene 4x less efficiently than light_paths 0.25.
# (SeeSharp's EfficiencyAwareMIS drops the largest 0.002% of pixel moments, "or a
# single firefly pixel can completely change the result"; at suite sizes that is no
# pixel at all.)  A caustic's focus keeps its weight: on the point caustic the largest
# pixel holds 25-40%.
OUTLIER_SHARE = 50000


def outliers(groups, pixels: int) -> mi.Bool:
    """Per pixel, whether its summed relative moment under the pilot's own weights
    (the samples' F^2 / mean^2) is an outlier (above)."""
    f64 = dr.float64_array_t(mi.Float)
    per_pixel = dr.zeros(f64, pixels)
    for relative, _, _, _, pixel, pairs, _ in groups:
        dr.scatter_reduce(dr.ReduceOp.Add, per_pixel, relative + pairs, pixel)
    total, largest = read_values(dr.sum(per_pixel), dr.max(per_pixel))
    if largest <= total - largest:          # none outweighs the rest: no read of them
        return dr.zeros(mi.Bool, pixels)
    moment = per_pixel.numpy()
    n = max(1, pixels // OUTLIER_SHARE)
    largest = np.argpartition(moment, -n)[-n:] if pixels > n else np.arange(pixels)
    largest = largest[np.argsort(moment[largest])[::-1]]
    dropped = np.zeros(pixels, dtype=bool)
    rest = float(moment.sum())
    for i in largest:
        rest -= moment[i]
        if moment[i] <= rest:
            break
        dropped[i] = True
    return device_array(mi.Bool, dropped)


# Relative moments divide by max(mean^2, DARK * image mean^2): a pixel darker than
# a tenth of the image's mean weighs as if it were that bright.  Relative error in a
# near-black pixel is invisible once the image is tone-mapped, and so it is in the
# benchmarks' relative MSE (mean^2 + 0.01).  With 1e-4 the point-light caustic's
# shadow (blurred mean ~0.003 against 0.4) outweighed the caustic and the direct
# light: it chose 1 light subpath per sample where 2 render it 1.3x faster.
DARK = 1e-2


@dataclass
class PilotMeans:
    """The pilot image's pixel means, which relative moments divide by: box-filtered
    (radius BLUR), with each sample's own part taken out (leave one out), floored.

    A mean estimated from the same samples as the moment correlates with it: where
    samples are sparse (light-image splats in a dim caustic, fireflies), a sample that
    lands there is most of its own pixel's mean, and F^2 / mean^2 comes out small
    exactly when F is large.  On the point-light caustic that bias made the summed
    moment 27x too small, and the decision ignored the noise that dominates there."""
    blurred: mi.Float       # luminance per pixel, box-filtered
    own: mi.Float           # a camera sample's weight in its own pixel's blurred mean
    floor: float            # DARK x the image mean^2
    light_own: mi.Float | None = None   # a splat's per unit of value / r (own's if None)

    @classmethod
    def of(cls, image, spp: int, filled=None, stride: int = 1) -> "PilotMeans":
        """From the pilot image's luminance (H, W) after ``spp`` camera samples per
        pixel: each sample is 1 / spp of its pixel (splats too: film.py's light image
        normalization; a wider pixel filter spreads that share over neighbours, almost
        all inside the same blur window), and a pixel is counts_x x counts_y /
        (2 r + 1)^2 of its own blurred value (1 + r times on the film's edge, which the
        blur extends; r = BLUR).  ``filled``: the pixels that have samples, where the
        pilot took only some (Pilot.stride); the blur averages over those alone, in a
        window widened to hold as many of them as BLUR's holds pixels (a noisier mean
        makes the moments larger, 1 / mean^2: a quarter-film pilot's were 1.09-1.15x
        what the whole film's later passes estimated with BLUR's window, 1.03-1.13x
        with this one, test_optimizer.py).  There a splat counts ``stride`` times in a
        filled pixel (the film keeps the splats in the pass's pixels, scaled) and not
        at all in another.

        The pixels' work runs on the device (a 1024x1024 film's took 150 ms of host
        NumPy per decision on an H100's host); ``image``: a TensorXf (H, W) or NumPy
        array, ``filled``: a flat mi.Bool or a NumPy (H, W) mask."""
        if isinstance(image, np.ndarray):
            image = device_array(mi.TensorXf, np.asarray(image, dtype=np.float32))
        shape = image.shape
        values, r, cover, inside = image.array, BLUR, 1.0, None
        if filled is not None:
            if isinstance(filled, np.ndarray):
                share, filled = float(filled.mean()), device_array(mi.Bool, filled.ravel())
            else:
                share = 1.0 / stride        # (Renderer._pilot_pixels: to 1 / pixels)
            r = int(round(BLUR / np.sqrt(max(share, 1e-3))))
            inside = dr.select(filled, 1.0, 0.0)
            cover = dr.maximum(_blur(inside, shape, r), 1.0 / (2 * r + 1) ** 2)
            values = values * inside
        f64 = dr.float64_array_t(mi.Float)
        total = dr.sum(f64(values))
        count = f64(shape[0] * shape[1]) if inside is None else dr.sum(f64(inside))
        total, count = read_values(total, count)
        mean = total / max(count, 1.0)
        y, x = rows_and_columns(shape)
        own = (_self_counts(y, shape[0], r) * _self_counts(x, shape[1], r)
               * dr.opaque(mi.Float, 1.0 / ((2 * r + 1) ** 2 * max(spp, 1))) / cover)
        light_own = own if filled is None else own * inside * dr.opaque(mi.Float, stride)
        blurred = _blur(values, shape, r) / cover
        dr.eval(blurred, own, light_own)
        return cls(blurred=blurred, own=own, light_own=light_own,
                   floor=DARK * max(mean ** 2, 1e-12))

    def squared(self, pixel: mi.UInt32, value: mi.Float, own: mi.Float | None = None) -> mi.Float:
        """The squared mean a sample of luminance ``value`` at ``pixel`` divides by;
        ``own``: its weight in its pixel's mean per unit of value (a camera
        sample's by default)."""
        own = self.own if own is None else own
        mean = dr.gather(mi.Float, self.blurred, pixel) - value * dr.gather(mi.Float, own, pixel)
        return dr.maximum(dr.square(dr.maximum(mean, 0.0)), dr.opaque(mi.Float, self.floor))


def rows_and_columns(shape: tuple) -> tuple:
    """Each pixel's row and column in an image (H, W) held flat (the width opaque:
    one kernel for every film)."""
    i = dr.arange(mi.Int32, shape[0] * shape[1])
    width = dr.opaque(mi.Int32, shape[1])
    y = i // width
    return y, i - y * width


def _self_counts(i: mi.Int32, n: int, radius: int = BLUR) -> mi.Float:
    """How often index i appears in its own window of ``radius`` over an axis of n
    extended by its edge values."""
    last = dr.opaque(mi.Int32, n - 1)
    edges = dr.select(i == 0, 1.0, 0.0) + dr.select(i == last, 1.0, 0.0)
    return 1.0 + radius * edges


# A merge query's own work (merge.visit: the 8 cells' counts read before its loop), in
# loop iterations (merge_step): about one iteration's gathers.
QUERY_STEPS = 1.0


@dataclass
class Costs:
    """A camera sample's work, counted in the pilot, and the machine's price of each
    unit of it (units.UnitCosts): a candidate's cost reads no clock."""
    units: UnitCosts = field(default_factory=UnitCosts)
    camera_rays: float = 0.0          # per camera sample: the camera walk with s <= 1
    light_rays: float = 0.0           # per light subpath: the light walk, t = 1 splats
    stored_per_path: float = 1.0      # light vertices stored per light subpath
    connection_rays: float = 0.0      # per camera sample: connecting to whole subpaths
    first_hit_share: float = 1.0      # of the camera walk's rays, those that a
                                      # light_first_hits budget traces (z_1's ray, and
                                      # all of a lane whose z_1 is delta)
    path_tracer: bool = False         # path tracing runs as Mitsuba's path (render.py)
    merges: float = 0.0               # per camera sample: merge queries (merge.visit)
    merge_items: float = 0.0          # per camera sample and unit of eta: grid items
                                      # they visited (their number grows with eta)
    merge_eta: float = 0.0            # eta = pi r^2 N_L per light subpath per camera
                                      # sample, over the passes to come (render.py)

    def of(self, b: Budget) -> float:
        u = self.units
        if b.light_ratio <= 0:
            return self.camera_rays * (u.path_ray if self.path_tracer else u.camera_ray)
        share = self.first_hit_share if b.light_first_hits else 1.0
        cost = self.camera_rays * u.camera_ray * share + b.light_ratio * self.light_rays * u.light_ray
        if b.connects or b.merging:
            cost += b.light_ratio * self.stored_per_path * u.stored_vertex
        if b.connects:
            full = self.connection_rays * u.connection
            cost += full if b.connections == "all" else full * min(
                1.0, b.connections / max(self.stored_per_path, 1e-3))
        if b.merging:
            cost += self.merging(b.light_ratio, b.radius_scale)
        return cost

    def merging(self, light_ratio: float, radius_scale: float = 1.0) -> float:
        """Merging's cost per camera sample: the grid's build per stored vertex, and
        the queries' steps (QUERY_STEPS a query, reading its 8 cells' counts, and an
        iteration per item of their buckets, as many as the photons within reach: their
        count per query grows with eta, the light subpaths times the disc,
        radius_scale^2)."""
        u = self.units
        eta = light_ratio * self.merge_eta * radius_scale ** 2
        steps = QUERY_STEPS * self.merges + self.merge_items * eta
        return light_ratio * self.stored_per_path * u.grid_vertex + steps * u.merge_step

    def describe(self) -> str:
        """The counts (the units: UnitCosts.describe)."""
        return ("camera_rays=%.4g light_rays=%.4g stored_per_path=%.4g connection_rays=%.4g "
                "first_hit_share=%.4g path_tracer=%d%s"
                % (self.camera_rays, self.light_rays, self.stored_per_path,
                   self.connection_rays, self.first_hit_share, self.path_tracer,
                   "" if not self.merges else " merges=%.4g merge_items=%.4g merge_eta=%.4g"
                   % (self.merges, self.merge_items, self.merge_eta)))


def covers(current: Budget, candidate: Budget) -> bool:
    """Whether balance weights of ``current``'s samples give ``candidate``'s balance
    sum (optimizer docstring): every group of strategies the candidate uses has a
    positive rate in ``current``, and a light_first_hits ``current`` lacks path
    tracing's density at smooth first hits, which every other candidate needs."""
    if candidate.light_ratio > 0 and current.light_ratio <= 0:
        return False
    if candidate.connects and not current.connects:
        return False
    if candidate.merging and not current.merging:
        return False
    return candidate.light_first_hits or not current.light_first_hits


@dataclass
class Decision:
    budget: Budget
    table: list = field(default_factory=list)       # (budget, cost, moment, efficiency)

    def describe(self) -> str:
        best = self.table[0][3] if self.table else 1.0
        rows = ["%s: relative efficiency %.2f" % (b, e / best) for b, _, _, e in self.table[:5]]
        return "chose %s (%s)" % (self.budget, "; ".join(rows))


def decide(cands: list[Budget], relative: np.ndarray, costs: Costs) -> Decision:
    """The candidate of least cost x summed relative second moment."""
    rows = []
    for b, m in zip(cands, relative):
        cost = costs.of(b)
        rows.append((b, cost, float(m), 1.0 / max(cost * m, 1e-30)))
    rows.sort(key=lambda row: -row[3])
    return Decision(budget=rows[0][0], table=rows)


def _blur(values, shape: tuple, radius: int = BLUR):
    """A box filter of ``radius`` over an image (H, W) held flat, extended by its edge
    values (the pilot's mean is noisy): separable, 2 r + 1 gathers per axis."""
    kind = type(values)
    y, x = rows_and_columns(shape)
    width, height = dr.opaque(mi.Int32, shape[1]), dr.opaque(mi.Int32, shape[0])
    rows = kind(0.0)
    for d in range(-radius, radius + 1):
        rows += dr.gather(kind, values, y * width + dr.clip(x + d, 0, width - 1))
    out = kind(0.0)
    for d in range(-radius, radius + 1):
        out += dr.gather(kind, rows, dr.clip(y + d, 0, height - 1) * width + x)
    return out * (1.0 / (2 * radius + 1) ** 2)


# A vcm render's later moment passes without merging record about this many times the
# pilot's camera lanes (Pilot.moment_every; 32 slots of 28 bytes: 59 MB at 8 x 8192
# lanes on a CPU, 0.9 GB at 8 x 2^17 on a GPU, where a pass of a large film already
# records pixels / 2).
MOMENT_PILOTS = 8


class Pilot:
    """The pilot pass of an "auto" render (module docstring) and its decision."""

    PASSES = 1

    @staticmethod
    def spp(pixels: int, total_spp: int) -> int:
        """Samples per pixel of the pilot pass: enough lanes for its moments, at most
        1/32 of the render."""
        return max(1, min(-(-_pilot_lanes() // pixels), total_spp // 32))

    @staticmethod
    def stride(pixels: int, spp: int, total_spp: int, merging: bool = False) -> tuple[int, bool]:
        """The pilot pass takes one pixel in ``stride``, and whether its samples stay
        in the image (``kept``):

        * a large film: 2 where half of it at 1 spp still gives the pass PILOT_LANES;
          the odd pixels then get their sample of the round from the chosen budget
          (render.Renderer._plan_pilot).  Past that size the pilot's samples need not
          grow with the film: its decision prices counts, not timings, so its pass
          needs no occupancy, only enough samples for the moments.  The means its
          moments divide by (PilotMeans) rest on fewer samples, which makes every
          candidate's moment a few percent larger (1 / mean^2 of a noisier mean),
          about alike for all.  (A pilot on a quarter of the film made them
          1.03-1.13x the whole film's estimate, Cornell box 256x256, 7 seeds; on half
          of it 1.02-1.06x.)
        * a small render (under PILOT_SHARE spp on a film under that size): one pixel
          in as many as keeps the pilot to 1 / PILOT_SHARE of the render's samples,
          and PILOT_LANES / 4 of them at least (every pixel where the film has fewer:
          a GPU's 64x64 and 128x128).  Its samples price the candidates and are then
          dropped: they would cover the film unevenly, and a pass per pixel
          set to complete the round costs more than they give (the glass pane at
          64x64, 32 spp: 1.5x ``path``'s error at equal time with a kept pilot on
          half the film, 1.36x on all of it).  It draws the same numbers in every
          render, and a later render of the same scene reuses its outcome
          (render._ReusedPilot), so it need not be the cheapest: at PILOT_LANES / 8,
          a quarter of that film, Veach's room chose light_paths=2 connections=0
          with the light image's first hits, 1.7x the error x time.  Not where
          merging is a candidate (``merging``), whose moments rest on rare samples:
          the SDS scene at 64x64, 32 spp, took 1.3-1.5x the error x time of a
          whole-film pilot."""
        if spp > 1:
            return 1, True
        if pixels // 2 >= _pilot_lanes():
            return 2, True
        if merging:
            return 1, True
        lanes = max(_pilot_lanes() // 4, pixels * total_spp // PILOT_SHARE)
        return max(1, -(-pixels // lanes)), False

    @staticmethod
    def moment_every(lanes: int, spp: int, unmerged_vcm: bool = False) -> int:
        """A later moment pass records one camera lane in this many: the first sample
        of every other pixel, the pilot's memory.  A vcm render's pass of a budget
        without merging (``unmerged_vcm``) records about MOMENT_PILOTS times the
        pilot's lanes.  There the candidates without merging read the paths that
        merges sample almost alone from rare BDPT samples, a heavy-tailed estimate
        whose typical value is far short of its mean, and such a budget renders in
        large passes: its one moment pass is its one chance to turn merging on.  On
        SmallVCM's large glass sphere the caustic seen through the glass came in 0-3
        of 8192 recorded samples; that pass put the candidates without merging at
        summed moments of 0.8-1.1 where passes that merged put them at 2.5-5, and
        merging stayed off.  SeeSharp's iterative updates read every sample of the
        render (Grittmann et al. 2022); MomentSamples' slots cap ours.  A merging
        budget's passes are small, three of them re-decide, and recording all their
        lanes cost the SDS scene 9% of its render for the same decisions."""
        every = 2 * spp
        if unmerged_vcm:
            every = min(every, max(1, lanes // (MOMENT_PILOTS * _pilot_lanes())))
        return every

    def __init__(self, spectral: bool, light_image: bool = True,
                 units: UnitCosts | None = None, merging: bool = False, spp: int = 0):
        self.candidates = candidates(spectral, light_image, merging)
        self.spp = spp                  # the render's samples per pixel (missed_bias)
        self.light_image = light_image
        self.merging = merging          # vcm: merging is a candidate
        self.costs = Costs(units or UnitCosts())
        self.decision: Decision | None = None     # the latest
        self.first: Decision | None = None        # the pilot's
        self.rounds: list = []                    # (spp, budget) of each re-decision
        self.pilot_eta = 0.0                      # the pilot pass's merging rate
        self.moments: dict = {}                   # candidate: (sum of estimates x
                                                  # recorded samples, recorded samples)
        self.bias = (0.0, 0.0)                    # N B (missed_bias), the same way

    def budget(self, index: int):
        """(budget, heuristic, with moments) of pilot pass ``index``: full BDPT with the
        balance heuristic.  With merging (vcm) it merges too, its image without it
        (render.py, mis.Weights' shadow): its merges give the merging candidates'
        moments, and where merging is chosen its image becomes the estimator with
        merging (with the balance heuristic, which gives that estimator's weights from
        u_vm)."""
        return Budget(1.0, "all", merging=True if self.merging else None), "balance", True

    def record(self, lanes: int, walk_rays: int, connection_rays: int, light_subpaths: int,
               light_rays: int, stored: int, first_hit_share: float = 1.0) -> None:
        """The work the pilot pass counted over ``lanes`` camera samples: the rays of
        its camera walk with s <= 1 and those of its connections to stored vertices,
        the rays of its light walk with the t = 1 splats, and the light vertices it
        stored."""
        self.costs.camera_rays = walk_rays / max(lanes, 1)
        self.costs.first_hit_share = first_hit_share
        self.costs.light_rays = light_rays / max(light_subpaths, 1)
        self.costs.connection_rays = connection_rays / max(lanes, 1)
        self.costs.stored_per_path = stored / max(light_subpaths, 1)

    def record_merging(self, lanes: int, merges: int, items: int, eta: float) -> None:
        """The merge work the pilot pass counted at its merging rate ``eta``."""
        self.costs.merges = merges / max(lanes, 1)
        self.costs.merge_items = items / max(lanes, 1) / max(eta, 1e-30)

    def decide(self, samples: MomentSamples, splats, mean: np.ndarray, spp: int,
               filled: np.ndarray | None = None, stride: int = 1) -> Decision:
        """The budget for the rest of the render, from the pilot pass's samples and
        its image (its luminance, (H, W), after ``spp`` camera samples per pixel of
        those in ``filled``, all by default, one pixel in ``stride``)."""
        self.decision = self._decide(self.candidates, samples, splats, mean, spp,
                                     (1.0, 1.0, self.pilot_eta), filled=filled,
                                     stride=stride)
        self.first = self.decision
        return self.decision

    def redecide(self, samples: MomentSamples, splats, mean: np.ndarray, spp: float,
                 budget: Budget, rates: tuple) -> Decision:
        """A decision after a later moment pass (``Renderer._plan_rounds``), which
        rendered ``budget`` with the balance heuristic at MIS ``rates`` (N_L / N_C,
        kappa): among the candidates whose balance sums that pass's samples give
        (``covers``), with each candidate's moment averaged over every moment pass so
        far.  The image's means are the whole render's so far (``spp`` per pixel);
        ``rates`` ends with the pass's merging rate eta (0 without merging).

        A pass without merging cannot price merging, but its samples firm up the
        moments of the candidates without it: merging candidates then keep the moments
        of the passes that merged (the pilot's), and the decision weighs them too
        (SeeSharp's iterative updates; without, the pilot's choice to leave merging off
        held).  Their pilot estimate is the reliable one: on SmallVCM's large glass
        sphere the pilot saw the caustic through the glass in 11-22 merges and 0-3 BDPT
        samples, so the candidates without merging were short of that moment in most
        pilots."""
        cands = [c for c in self.candidates if covers(budget, c)]
        kept = [c for c in self.candidates if c.merging and not budget.merging
                and c in self.moments]
        self.decision = self._decide(cands, samples, splats, mean, spp, rates, kept)
        self.rounds.append((spp, self.decision.budget))
        return self.decision

    def _decide(self, cands, samples, splats, mean, spp, rates, kept=(), filled=None,
                stride: int = 1) -> Decision:
        """Per candidate, the relative moment summed over pixels per camera sample of
        this pass, averaged with earlier passes' by their recorded camera samples; the
        decision among ``cands`` and ``kept`` (moments of earlier passes alone).  The
        bias N B of the candidates without merging (missed_bias) is no moment: it is
        measured by the passes that merge and averaged over them alone."""
        r, k, eta = rates
        rows = np.array([[c.light_ratio / r, c.kappa(1, self.costs.stored_per_path) / k if k
                          else 0.0, float(c.light_first_hits), self._merge_rate(c, eta)]
                         for c in cands])
        recorded = samples.lanes / samples.every
        means = PilotMeans.of(mean, spp, filled, stride)
        relative = samples.relative_moments(rows, means, splats, self.merging) / samples.lanes
        if self.merging and eta > 0:    # what the candidates without merging miss
            total, weight = self.bias
            self.bias = (total + self.spp * missed_bias(samples, means, mean.shape) * recorded,
                         weight + recorded)
        bias = self.bias[0] / self.bias[1] if self.bias[1] else 0.0
        for c, m in zip(cands, relative):
            total, weight = self.moments.get(c, (0.0, 0.0))
            self.moments[c] = (total + m * recorded, weight + recorded)
        cands = list(cands) + list(kept)
        return decide(cands, np.array([self.moments[c][0] / self.moments[c][1]
                                       + (0.0 if c.merging else bias) for c in cands]),
                      self.costs)

    def _merge_rate(self, c: Budget, eta: float) -> float:
        """Candidate c's merging rate over the moment pass's: its eta in the passes to
        come (Costs.merge_eta per light subpath per camera sample, at c's radius) over
        ``eta``."""
        if not c.merging or eta <= 0:
            return 0.0
        return c.light_ratio * self.costs.merge_eta * c.radius_scale ** 2 / eta
