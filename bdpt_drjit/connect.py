"""The camera-side strategies: each evaluates one contribution per lane at the camera
vertex z_{t-1} the camera walk is at, and asks mis.Weights for its weight.

=============  ============================================  ==================
strategy       how the path is completed                     where it lands
=============  ============================================  ==================
s = 0          camera subpath hits an emitter                camera block
s = 1          fresh emitter sample at z_{t-1} (NEE)         camera block
s, t >= 2      shadow ray between y_{s-1} and z_{t-1}        camera block
t = 1          light vertex through the lens (splat.py)      light block
=============  ============================================  ==================

Contribution of (s, t) (Veach eq. 10.8, pbrt-v3 section 16.3.3):
    C = beta_L(y_{s-1}) f_L(y_{s-2} -> y_{s-1} -> z) G f_E(y -> z_{t-1} -> z_{t-2}) beta_E(z_{t-1})
with Mitsuba's ``bsdf.eval`` already holding each endpoint's shading cosine, so G
reduces to 1 / d^2.  Light-side BSDFs are evaluated in importance mode with the
shading-normal adjoint correction.  Every contribution passes ``finite``.
In media (media.py) every connection carries the transmittance between its
endpoints, and the densities of the distances a walk would have drawn along it join
the endpoints' densities (``dens_fwd`` toward the far end, ``dens_rev`` back).
Vertices are surface.Vertex: a surface or a point in a medium.
Functions that trace shadow rays also return how many they traced (statistics).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from . import mis
from .emitters import DIRECTIONAL, ENV
from .media import connection_key
from .surface import VertexRecord, finite, spectrum_nonzero
from .vertices import NONE, Pool, gather

# Whether render passes connect after the camera walk (``link_pool``): off
# (BDPT_DEFERRED_CONNECTIONS=1 turns it on, the A/B of benchmarks/gpu_check.sh's step
# "links").  In the walk, a GPU warp runs each depth's connection loop as long as any of
# its lanes connects, inside the walk's kernel with all of its state (the Cornell box
# at 1024x1024 on an H100: the connections 21 ns of the camera walk's 26 per lane,
# 5x a whole sample of Mitsuba's path; RESULTS.md, "On a GPU").  Deferred, a kernel of
# their own runs them, one lane per camera vertex that connects.
DEFERRED = os.environ.get("BDPT_DEFERRED_CONNECTIONS") == "1"
# Camera vertices that connect per lane that a pass's pool holds at first (Veach's
# BDPT at 128x128: 2.5 in the Cornell box, 3.1 lit via its ceiling, 3.45 in Veach's
# room); a pass that needs more runs its camera walk again with 1.25x what it needed,
# and the passes after it are planned with that.
LINKS_PER_LANE = 4.0


def _shown(ctx, state):
    """Whether an emitter the camera path reaches now may show: with hide_emitters, not
    if every vertex before it was passed by a null lobe (a mask's hole), where Mitsuba's
    path and volpath hide it as seen directly (k = 1 is already off: strategies.py)."""
    return state.hit if ctx.settings.hide_emitters else True


def emission_hit(ctx, state, v):
    """s = 0, t = j + 1: the camera ray arriving at z_j hit an area emitter."""
    t = state.depth + 1
    si = v.si
    # A medium vertex's si is invalid, which si.emitter() reads as the environment.
    surface = state.active & ~v.in_medium if ctx.media.present else state.active
    emitter = si.emitter(ctx.scene, surface)
    hit = surface & (emitter != None) & ctx.strategies.enabled(0, t) & _shown(ctx, state)  # noqa: E711
    contrib = state.beta * emitter.eval(si, hit)
    n, to_prev = si.sh_frame.n, si.to_world(si.wi)
    pos_pdf_a, emission_pdf_aw = mi.Float(0.0), mi.Float(0.0)
    if ctx.weights.chains:
        pos_pdf_a, emission_pdf_aw, _, _ = ctx.emitters.emission_pdfs(emitter, n, to_prev, hit)
    from_pinhole = state.depth == 1
    nee_pdf_a = ctx.emitters.nee_pdf_a(state.prev, si.p, n, si.uv, emitter, mi.Bool(False),
                                       si.time, hit & ~from_pinhole)
    contrib *= ctx.weights.emission_hit(state.d_vcm, state.d_vc, state.lw, from_pinhole,
                                        nee_pdf_a, pos_pdf_a, emission_pdf_aw)
    contrib = dr.select(hit, finite(contrib), 0.0)
    if ctx.moments is not None:
        direct_pdf_a = ctx.weights.direct_pdf_a(from_pinhole, nee_pdf_a, pos_pdf_a)
        d_vm = state.d_vm_or_0
        state.slot = ctx.moments.add(state.slot, ctx.lane, ctx.pixel, contrib, *mis.groups_emission_hit(
            state.d_vcm, ctx.weights.moment_d_vc(state.d_vc, d_vm), state.d_end, from_pinhole,
            direct_pdf_a, emission_pdf_aw, d_vm), hit)
    return contrib


def environment_hit(ctx, state, flight):
    """s = 0, t = j + 1: the camera ray leaving z_{j-1} escaped to the environment
    (the chains as the last scatter left them, in solid angle at z_{j-1})."""
    env = ctx.emitters.environment
    t = state.depth + 1
    active = flight.escaped & ctx.strategies.enabled(0, t) & _shown(ctx, state)
    d_vcm, d_vc, d_end = state.d_vcm, state.d_vc, state.d_end
    if ctx.media.present:
        d_vcm, d_vc = ctx.weights.after_escape(d_vcm, d_vc, flight.dens_fwd, flight.dens_rev)
        d_end = d_end * flight.dens_rev / flight.dens_fwd
    ray = state.ray
    contrib = state.beta * ctx.emitters.environment_radiance(env, -ray.d, ray.wavelengths,
                                                             ray.time, active)
    rival = active & (state.depth > 1)
    if ctx.weights.chains:
        nee_pdf_w, emission_pdf_aw = ctx.emitters.environment_pdfs(
            mi.EmitterPtr(env), state.prev, ray.d, rival)
    else:
        nee_pdf_w = ctx.emitters.environment_nee_pdf_w(mi.EmitterPtr(env), state.prev, ray.d, rival)
        emission_pdf_aw = mi.Float(0.0)
    contrib *= ctx.weights.environment_hit(d_vcm, d_vc, state.lw, state.depth == 1,
                                           nee_pdf_w, emission_pdf_aw)
    contrib = dr.select(active, finite(contrib), 0.0)
    if ctx.moments is not None:        # an escape at once has no rival: all path tracing
        d_vm = state.d_vm_or_0
        if ctx.media.present and state.d_vm is not None:
            d_vm = d_vm * flight.dens_rev / flight.dens_fwd
        u_pt, u_lt, u_vm = mis.groups_emission_hit(d_vcm, ctx.weights.moment_d_vc(d_vc, d_vm),
                                                   d_end, False, nee_pdf_w, emission_pdf_aw, d_vm)
        first = state.depth == 1
        state.slot = ctx.moments.add(state.slot, ctx.lane, ctx.pixel, contrib,
                                     dr.select(first, 1.0, u_pt), dr.select(first, 0.0, u_lt),
                                     dr.select(first, 0.0, u_vm), active)
    return contrib


def next_event(ctx, state, v, sample, active):
    """s = 1, t = j + 1: sample a point on an emitter from z_j (Mitsuba's own light
    sampling, so its pdf includes the selection pmf) and connect to it."""
    scene = ctx.scene
    ds, spec = scene.sample_emitter_direction(v.si, sample, False, active)
    active = active & (ds.pdf > 0) & spectrum_nonzero(spec)
    directional = False                 # (a Python False where no such light exists)
    if ctx.emitters.kinds_present & {ENV, DIRECTIONAL}:
        kind = ctx.emitters.kind_of(ds.emitter, active)
        directional = kind == DIRECTIONAL
        at_infinity = (kind == ENV) | directional
        ds.p = dr.select(at_infinity, ctx.emitters.past_the_scene(v.p, ds.d), ds.p)
    cos_cam, ok = v.cosine(ds.d)
    active = active & ok
    weights = ctx.weights
    if weights.on and weights.chains:
        f, bsdf_pdf_w, bsdf_rev_w = v.eval_and_reverse(ds.d, active)
    else:
        (f, bsdf_pdf_w), bsdf_rev_w = v.eval(ds.d, active), mi.Float(0.0)
    contrib = state.beta * f * spec
    traced = active & spectrum_nonzero(contrib)
    key = connection_key(ctx, state.depth, 0)
    tr, dens_fwd, dens_rev, rays = ctx.media.transmittance(v, ds.p, 1.0, key, traced)
    contrib *= tr
    active = traced & spectrum_nonzero(tr)
    if weights.on:
        emission_pdf_aw, cos_light = mi.Float(0.0), mi.Float(1.0)
        if weights.chains:
            _, emission_pdf_aw, cos_light, _ = ctx.emitters.emission_pdfs(ds.emitter, ds.n, -ds.d, active)
            emission_pdf_aw *= dens_rev
        nee_pdf_w = weights.nee_density_w(
            ds, scene.pdf_emitter_direction(v.si, ds, active & ~ds.delta), directional)
        bsdf_pdf_w = bsdf_pdf_w * dens_fwd
        contrib *= weights.nee(state.d_vcm, state.d_vc, state.lw, state.depth,
                               weights.specularity(v.bsdf.flags()), ds.delta, bsdf_pdf_w,
                               nee_pdf_w, emission_pdf_aw, cos_cam, cos_light, bsdf_rev_w,
                               v.surface)
    contrib = dr.select(active, finite(contrib), 0.0)
    if ctx.moments is not None:
        d_vm = state.d_vm_or_0
        state.slot = ctx.moments.add(state.slot, ctx.lane, ctx.pixel, contrib, *mis.groups_nee(
            state.d_vcm, ctx.weights.moment_d_vc(state.d_vc, d_vm), state.d_end, state.depth == 1,
            dr.select(ds.delta, 0.0, bsdf_pdf_w / nee_pdf_w),
            emission_pdf_aw * cos_cam / (nee_pdf_w * cos_light), bsdf_rev_w,
            ctx.weights.rate(state.depth), d_vm, ctx.weights.vm_moment(v.surface)), active)
    return contrib, rays


def stored_vertices(ctx, store, state, v, connectible):
    """s, t >= 2: z_j (t = j + 1) to the stored light vertices, each y_{s-1} of the
    lane's light subpath, or (a vertex cache) M vertices drawn from all of them.
    Returns the radiance with these strategies added, and the shadow rays traced."""
    if ctx.budget.caches:
        return _cached_vertices(ctx, store, state, v, connectible)
    return _subpath_vertices(ctx, store, state, v, connectible)


def _subpath_vertices(ctx, store, state, v, connectible):
    """Every stored vertex of the lane's light subpath (``along_subpath``)."""
    radiance, rays, state.slot = along_subpath(ctx, store, state, v, connectible, ctx.lane,
                                               state.radiance, state.slot)
    return radiance, rays


def along_subpath(ctx, store, cam, v, connectible, lane, radiance, slot):
    """Camera vertex ``v`` (the walk's state ``cam`` there, camera lane ``lane``) to
    every stored vertex of the lane's light subpath, in a symbolic loop along its list,
    added to ``radiance``.  The list runs y_1, y_2, ..., so the loop stops at the first
    vertex whose path would be longer than max_depth.  Returns the radiance, the shadow
    rays traced and the moment slots."""
    t = cam.depth + 1
    first = dr.gather(mi.UInt32, store.first, ctx.light_subpath(lane), connectible)
    k_max = ctx.strategies.max_depth

    def more(item, radiance, rays, slot):
        go = item != NONE
        if k_max >= 0:
            s = store.vertices.s(item, go)
            go &= s + t - 1 <= k_max
        return go

    def body(item, radiance, rays, slot):
        light = store.vertex(item, True)
        on = ctx.strategies.enabled(light.s, t)
        c, traced, groups = connect_vertices(ctx, light, on, cam, v)
        radiance = ctx.strategies.add(ctx.images, radiance, lane, light.s, t, c)
        if groups is not None:
            slot = ctx.moments.add(slot, lane, ctx.pixel, c, *groups, on)
        return light.next, radiance, rays + traced, slot

    _, radiance, rays, slot = dr.while_loop(
        (dr.select(connectible, first, NONE), mi.Spectrum(radiance),
         dr.zeros(mi.UInt32, dr.width(first)), mi.UInt32(slot)),
        more, body, labels=("item", "radiance", "rays", "slot"), label="connections")
    return radiance, rays, slot


# -- connections after the camera walk (DEFERRED) ------------------------------------
@dataclass
class Link:
    """A camera vertex z_j whose connections run after the camera walk
    (``run_links``): what ``connect_vertices`` reads of the walk's state there."""
    record: VertexRecord    # z_j
    beta: mi.Spectrum       # beta_E(z_j)
    d_vcm: mi.Float         # the camera chains at z_j (mis.py)
    d_vc: mi.Float
    lw: mi.Float            # mis="lafortune": the walk's product at z_j
    depth: mi.UInt32        # j
    lane: mi.UInt32         # the camera lane


def link_bytes(strategies, budget, media: bool, per_lane: float) -> int:
    """Bytes per camera lane of a render pass's deferred connections (``link_pool``,
    which render.Renderer._lanes_for adds to a lane's), or 0 where the camera walk
    connects at each vertex itself: DEFERRED off, a budget without connections or with
    a vertex cache, or a scene with media (a connection's ratio tracking keys its
    numbers by the walk's lane).  ``per_lane``: the camera vertices that connect per
    lane that the pool holds, at most one per camera depth."""
    if not DEFERRED or media or not budget.connects or budget.caches:
        return 0
    return int(_links(strategies, per_lane) * _link_bytes())


def _links(strategies, per_lane: float) -> float:
    """``per_lane``, at most one per camera vertex z_j, j <= max_depth - 1."""
    depths = strategies.max_depth - 1 if strategies.max_depth >= 0 else None
    if strategies.max_camera_vertices() is not None:
        depths = min(depths or 2 ** 31, strategies.max_camera_vertices())
    return per_lane if depths is None else min(per_lane, max(depths, 1))


def _link_bytes() -> int:
    """A Link's bytes: VertexRecord's 31 values, beta, and 5 more."""
    return 4 * (31 + dr.size_v(mi.Spectrum) + 5)


def link_pool(strategies, budget, lanes: int, moments: bool, media: bool,
              memory_budget: int, per_lane: float) -> Pool | None:
    """The pool of a render pass's deferred connections (``defer``, ``run_links``;
    allocated by the walk that fills it), ``per_lane`` records per camera lane; None
    where the walk connects (``link_bytes``), in a moment pass (its samples take slots
    in the walk's order), or where the pool would pass ``memory_budget`` (a pass of
    explicit size).  A walk that needs more runs again with a larger one
    (render.Renderer._camera_subpaths)."""
    per_lane_bytes = link_bytes(strategies, budget, media, per_lane)
    if not per_lane_bytes or moments or lanes * per_lane_bytes > memory_budget:
        return None
    return Pool(Link, max(1, int(math.ceil(lanes * _links(strategies, per_lane)))),
                allocate=False)


def defer(ctx, store, state, v, connectible) -> None:
    """Camera vertex z_j's connections, put off until the walk ends (``run_links``):
    where the lane's light subpath stored a vertex."""
    first = dr.gather(mi.UInt32, store.first, ctx.light_subpath(ctx.lane), connectible)
    ctx.links.append(Link(record=VertexRecord.of(v), beta=mi.Spectrum(state.beta),
                          d_vcm=mi.Float(state.d_vcm), d_vc=mi.Float(state.d_vc),
                          lw=mi.Float(state.lw), depth=mi.UInt32(state.depth),
                          lane=mi.UInt32(ctx.lane)),
                     connectible & (first != NONE))


def run_links(ctx, store, cam) -> None:
    """The connections a camera walk deferred (``defer``), one lane per camera vertex,
    each as the walk would run them (``along_subpath``): their value goes to the
    camera lane's radiance (and strategy images), their shadow rays to its count.  The
    sum differs from the walk's own by float rounding.  The pool's size stays on the
    device (a recorded walk reads nothing back, frozen.py): lanes past it do nothing."""
    pool = ctx.links
    n = pool.capacity
    index = dr.arange(mi.UInt32, n)
    active = index < dr.gather(mi.UInt32, pool.count, dr.zeros(mi.UInt32, n))
    q = gather(pool.items, index, active)
    v = q.record.vertex(at_lane(ctx.time, q.lane, active),
                        at_lane(ctx.wavelengths, q.lane, active), False)
    radiance, rays, _ = along_subpath(ctx, store, q, v, active, q.lane,
                                      dr.zeros(mi.Spectrum, n), dr.zeros(mi.UInt32, n))
    dr.scatter_reduce(dr.ReduceOp.Add, cam.radiance, radiance, q.lane, active)
    dr.scatter_reduce(dr.ReduceOp.Add, cam.rays, rays, q.lane, active)


def at_lane(values, lane, active):
    """A per-lane value of the pass (time, wavelengths) at ``lane``; one shared by
    every lane as it is."""
    return dr.gather(type(values), values, lane, active) if dr.width(values) > 1 else values


_GOLDEN = 0.6180339887498949


def _cached_vertices(ctx, store, state, v, connectible):
    """M vertices drawn uniformly from the V stored vertices of the pass (Davidovic et
    al. 2014).  Lane i's m-th pick is item (i M + m + o_j) mod V, with o_j uniform per
    pass and camera depth j: each pick is uniform over the pool, and neighbouring
    lanes read neighbouring records (uniform random picks measured 1.2-1.3x slower).
    A pick's contribution is divided by its density relative to "all", M N_L / V."""
    t = state.depth + 1
    phase = ctx.pick_offset + mi.Float(state.depth) * _GOLDEN
    offset = mi.UInt32(dr.floor((phase - dr.floor(phase)) * mi.Float(ctx.stored)))
    radiance, rays = mi.Spectrum(state.radiance), dr.zeros(mi.UInt32, dr.width(ctx.lane))
    picks = ctx.budget.connections
    order = store.order
    for m in range(picks):
        position = (ctx.lane * picks + m + offset) % ctx.stored
        item = dr.gather(mi.UInt32, order, position, connectible)
        # A pass that stored no vertex has one NONE: its pool's record 0 is unwritten
        # memory, whose garbage vertex crashed a render (max_depth 2, where no vertex
        # is stored, after earlier passes had filled that memory).
        picked = connectible & (item != NONE)
        light = store.vertex(item, picked)
        on = picked & ctx.strategies.enabled(light.s, t)
        c, traced, groups = connect_vertices(ctx, light, on, state, v)
        c = c * ctx.connection_scale
        radiance = ctx.strategies.add(ctx.images, radiance, ctx.lane, light.s, t, c)
        if groups is not None:            # a moment pass (optimizer.py)
            state.slot = ctx.moments.add(state.slot, ctx.lane, ctx.pixel, c, *groups, on)
        rays += traced
    return radiance, rays


def connect_vertices(ctx, light, active, cam, v_c):
    """s, t >= 2: connect the stored light vertex y_{s-1} (``light``) to the camera
    vertex z_{t-1} the camera walk is at (``v_c``, state ``cam``).  Returns the
    contribution, the shadow rays traced and (moment passes) the moment groups."""
    v_l = light.record.vertex(v_c.si.time, v_c.si.wavelengths, ctx.media.present)
    d = v_l.p - v_c.p
    dist2 = dr.squared_norm(d)
    w = d * dr.rsqrt(dist2)                     # from z_{t-1} toward y_{s-1}
    active = active & (dist2 > 0)
    cos_c, ok_c = v_c.cosine(w)
    cos_l, ok_l = v_l.cosine(-w)
    active = active & ok_c & ok_l
    f_c, pdf_c_w, rev_c_w = v_c.eval_and_reverse(w, active)
    f_l, rev_l_w, pdf_l_w = v_l.eval_adjoint_and_pdf(-w, active)
    contrib = cam.beta * f_c * f_l * light.beta / dist2
    traced = active & spectrum_nonzero(contrib)
    # (Keyed by the walk's lane: deferred connections, link_pool, have no media.)
    key = connection_key(ctx, cam.depth, light.s) if ctx.media.present else None
    tr, dens_fwd, dens_rev, rays = ctx.media.transmittance(v_c, v_l.p, v_l.sigma_t(), key, traced)
    contrib *= tr
    active = traced & spectrum_nonzero(tr)
    weights = ctx.weights
    if weights.on:
        pdf_c_a = pdf_c_w * cos_l / dist2 * dens_fwd
        pdf_l_a = pdf_l_w * cos_c / dist2 * dens_rev
        contrib *= weights.connect(light, cam.d_vcm, cam.d_vc, cam.depth, cam.lw,
                                   weights.specularity(v_c.bsdf.flags()),
                                   pdf_c_a, rev_c_w, pdf_l_a, rev_l_w, v_l.surface, v_c.surface)
    contrib = dr.select(active, finite(contrib), 0.0)
    groups = None
    if ctx.moments is not None:
        d_vm = cam.d_vm_or_0
        chains = mis.Chains(light.d_vcm, weights.moment_d_vc(light.d_vc, light.d_vm),
                            light.d_end, light.d_vm)
        groups = mis.groups_connect(chains, light.s == 2, cam.d_vcm,
                                    weights.moment_d_vc(cam.d_vc, d_vm), cam.d_end,
                                    cam.depth == 1, pdf_c_a, rev_c_w, pdf_l_a, rev_l_w,
                                    weights.rate(light.s - 1), weights.rate(cam.depth),
                                    weights.kappa, d_vm, weights.vm_moment(v_l.surface),
                                    weights.vm_moment(v_c.surface))
    return contrib, rays, groups
