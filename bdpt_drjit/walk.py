"""The subpath walks: each a symbolic loop over depths, one kernel per walk.

    light walk, per depth i:  intersect y_i -> MIS to area measure -> t = 1 splat
                              -> store y_i for connections -> scatter -> roulette
    camera walk, per depth j: intersect z_j -> s = 0 (emitter or environment hit)
                              -> MIS to area measure -> s = 1 (next event)
                              -> s, t >= 2 (z_j to the lane's stored light vertices;
                                 or, with connect.DEFERRED, z_j stored and connected
                                 after the walk)
                              -> merges (``merging``: z_j with every stored light
                                 vertex within r, merge.py; or, with merge.DEFERRED,
                                 z_j stored and merged after the walk) -> scatter -> roulette

``strategy_subset`` ``ppm`` (merging alone) ends a camera subpath at the first vertex
where it scatters smoothly: that vertex's merges render the rest.

A budget that leaves first hits to the light image (budgets.Budget.light_first_hits)
evaluates nothing at z_1 and ends every camera subpath whose z_1 scatters smoothly.

The loops are Dr.Jit symbolic loops (``dr.while_loop``): the kernel of a walk is
traced once, whatever the depth a subpath reaches, the seed, the film size or
the spp, so a render compiles nothing that an earlier one compiled.  On the CPU a
SIMD packet runs the loop only while one of its lanes lives, which is what
compacting a wavefront of dead lanes bought, with no kernel per depth.

Loop state is ``PathState``; every random number of a depth is drawn at the top
of the depth into ``DepthSamples`` (pbrt-v4's ``RaySamples``), so which of them a
strategy uses never shifts the others.  In a scene with media, the ray of a depth
then runs through free flights to its vertex (media.Media.next_vertex, a nested
loop that draws each segment's numbers after the depth's), and the vertex may be a
point in a medium: strategies see a surface.Vertex either way.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from . import connect, merge, mis, splat
from .media import camera_passes_emitters
from .surface import IMPORTANCE, RADIANCE, Vertex, VertexRecord, adjoint_correction, spectrum_nonzero
from .vertices import NONE, LightVertex


@dataclass
class DepthSamples:
    """Every random number one depth of a walk uses, drawn together in this order."""
    endpoint: mi.Point2f    # camera walk: NEE's emitter sample (s = 1); light walk: the
                            # lens sample of the t = 1 connection
    lobe: mi.Float          # BSDF lobe
    direction: mi.Point2f   # BSDF direction
    roulette: mi.Float      # Russian roulette

    @staticmethod
    def draw(sampler: mi.Sampler) -> "DepthSamples":
        return DepthSamples(endpoint=sampler.next_2d(), lobe=sampler.next_1d(),
                            direction=sampler.next_2d(), roulette=sampler.next_1d())


@dataclass
class PathState:
    """A subpath walk, one lane per subpath: the loop state of both walks."""
    ray: mi.Ray3f           # the ray toward the next vertex
    beta: mi.Spectrum       # throughput up to the ray's origin, 1/q of roulette included
    rr_beta: mi.Spectrum    # the same for Russian roulette's survival probability
    eta: mi.Float           # product of relative IORs crossed (roulette, as Mitsuba's)
    d_vcm: mi.Float         # MIS chain state at the ray's origin (mis.py)
    d_vc: mi.Float
    d_end: mi.Float         # moment passes: the chain's far end (mis.end_after_scatter)
    prev: mi.Interaction3f  # the ray's origin vertex (pdf queries of the next one)
    depth: mi.UInt32        # j of the vertex z_j (or i of y_i) the ray will hit
    active: mi.Bool         # the subpath goes on
    rays: mi.UInt32         # rays this lane traced (statistics)
    lw: mi.Float            # camera walk, mis="lafortune": product of W'(z_m), m < j,
                            # at z_j (mis.lafortune_specularity)
    lw_prev: mi.Float       # the same without z_{j-1}'s factor
    radiance: mi.Spectrum   # camera walk: sum of this sample's strategies
    hit: mi.Bool            # camera walk: the path reached an opaque surface (film alpha)
    last_item: mi.UInt32    # light walk: this lane's last stored vertex (or NONE)
    slot: mi.UInt32         # camera walk, moment passes: moment samples recorded
    specular_z1: mi.Bool    # camera walk: z_1 scattered through a delta lobe
    medium: mi.MediumPtr = None     # media: the medium the ray travels in
    sigma_prev: mi.Spectrum = None  # media: sigma_t at the ray's origin vertex (Vertex.sigma_t)
    d_vm: mi.Float = None           # moment passes with merging: d_vc's merge part (mis.py)
    merges: mi.UInt32 = None        # camera walk with merging: merge queries (merge.visit)
    merge_items: mi.UInt32 = None   # the grid items those queries visited
    links: mi.UInt32 = None         # camera walk, moment passes: shadow rays of the
                                    # connections to stored vertices (of ``rays``)

    @property
    def d_vm_or_0(self):
        return 0.0 if self.d_vm is None else self.d_vm

    @staticmethod
    def start(ray, beta, d_vcm, d_vc, prev, active, medium=None, vm_shares=False,
              merge_counts=False, link_counts=False) -> "PathState":
        """``medium``: the medium the first ray travels in (None: a scene without media);
        ``vm_shares``: carry d_vm; ``merge_counts``: count merge work; ``link_counts``:
        count the connections' rays apart."""
        n = dr.width(ray.o)
        media = medium is not None
        zero = dr.zeros(mi.UInt32, n) if merge_counts else None
        return PathState(ray=mi.Ray3f(ray), beta=mi.Spectrum(beta), rr_beta=dr.ones(mi.Spectrum, n),
                         eta=dr.ones(mi.Float, n), d_vcm=mi.Float(d_vcm), d_vc=mi.Float(d_vc),
                         d_end=mi.Float(d_vcm),
                         prev=prev, depth=dr.ones(mi.UInt32, n), active=mi.Bool(active),
                         rays=dr.zeros(mi.UInt32, n), lw=dr.ones(mi.Float, n),
                         lw_prev=dr.ones(mi.Float, n),
                         radiance=dr.zeros(mi.Spectrum, n), hit=dr.zeros(mi.Bool, n),
                         last_item=dr.full(mi.UInt32, NONE, n), slot=dr.zeros(mi.UInt32, n),
                         specular_z1=dr.zeros(mi.Bool, n),
                         medium=mi.MediumPtr(medium) if media else None,
                         sigma_prev=dr.ones(mi.Spectrum, n) if media else None,
                         d_vm=dr.zeros(mi.Float, n) if vm_shares else None,
                         merges=zero, merge_items=mi.UInt32(zero) if merge_counts else None,
                         links=dr.zeros(mi.UInt32, n) if link_counts else None)


def _point(p, n, time, wavelengths) -> mi.Interaction3f:
    it = dr.zeros(mi.Interaction3f)
    it.p, it.n, it.time, it.wavelengths = p, n, time, wavelengths
    return it


def _loop(label: str, state: PathState, sampler, step):
    """Run ``step(state, samples, sampler)`` for every depth while some lane is active."""
    def body(state, sampler):
        step(state, DepthSamples.draw(sampler), sampler)
        return state, sampler
    state, sampler = dr.while_loop((state, sampler), lambda state, sampler: state.active,
                                   body, label=label)
    return state


# -- light subpaths -----------------------------------------------------------------
def trace_light_subpaths(ctx, store) -> mi.UInt32:
    """Light subpaths y_0 .. y_n: t = 1 splats and the stored vertices go to
    ``store``; returns the rays each lane traced."""
    es, state = _light_start(ctx, store)
    max_i = ctx.strategies.max_light_vertices()

    def step(state: PathState, u: DepthSamples, sampler):
        flight, v = _next_vertex(ctx, state, sampler)
        s = state.depth + 1                # strategies ending the light subpath at y_i
        _light_vertex_mis(ctx, es, state, v, flight)
        connectible = state.active & v.smooth
        vertex = LightVertex(record=VertexRecord.of(v), beta=mi.Spectrum(state.beta),
                             d_vcm=state.d_vcm, d_vc=state.d_vc, d_end=state.d_end,
                             d_vm=mi.Float(state.d_vm_or_0), s=s, next=mi.UInt32(NONE))
        state.rays += splat.light_vertex_to_camera(
            ctx, store, v, vertex, u.endpoint, connectible & ctx.strategies.enabled(s, 1))
        state.last_item = store.add_vertex(vertex, ctx.lane, state.last_item,
                                           connectible & ctx.strategies.stores(s))
        goes_on = state.active if max_i is None else state.active & (state.depth < max_i)
        _scatter(ctx, state, v, u, goes_on, importance=True)

    state = _loop("light subpaths", state, ctx.light_sampler, step)
    return state.rays


def _light_vertex_mis(ctx, es, state: PathState, v, flight):
    """The MIS chains at y_i, in area measure.  At y_1 they also take the density with
    which next-event estimation from y_1 would have picked y_0 (mis.first_light_vertex)."""
    cos_in, _ = v.cosine(state.ray.d)
    dist2 = dr.squared_norm(v.p - state.prev.p)
    first = state.depth == 1
    nee_pdf_a = ctx.emitters.nee_pdf_a(v.si, es.p, es.n, es.uv, es.emitter, es.delta_pos,
                                       ctx.time, state.active & first & ~es.infinite)
    nee_pdf_w = ctx.emitters.environment_nee_pdf_w(es.emitter, v.si, -state.ray.d,
                                                   state.active & first & es.infinite)
    dens = flight.dens_fwd, flight.dens_rev
    d_vcm1, d_vc1 = ctx.weights.first_light_vertex(state.d_vc, nee_pdf_a, nee_pdf_w, es.infinite,
                                                   es.emission_pdf, dist2, cos_in, *dens)
    d_vcm, d_vc = ctx.weights.after_hit(state.d_vcm, state.d_vc, dist2, cos_in, *dens)
    if ctx.moments is not None:
        state.d_end = mis.end_after_hit(state.d_end, dist2, cos_in, False, *dens)
    if state.d_vm is not None:
        state.d_vm = mis.vm_after_hit(state.d_vm, dist2, cos_in, *dens)
    state.d_vcm = dr.select(first, d_vcm1, d_vcm)
    state.d_vc = dr.select(first, d_vc1, d_vc)


def _light_start(ctx, store):
    """y_0 on an emitter and the ray leaving it; (1,1) is splatted here."""
    sampler = ctx.light_sampler
    es = ctx.emitters.sample_emission(ctx.time, ctx.wavelengths, sampler.next_1d(),
                                      sampler.next_2d(), sampler.next_2d())
    u_lens = sampler.next_2d()        # drawn whether or not (1,1) is on
    medium = ctx.media.start_medium(es, ctx.time, es.valid) if ctx.media.present else None
    rays = splat.emitter_to_camera(ctx, store, es, medium, u_lens,
                                   es.valid & ctx.strategies.enabled(1, 1))
    y0 = _point(es.p, es.n, ctx.time, ctx.wavelengths)
    d_vc = ctx.weights.light_start(es.emission_pdf, es.cos_emit, es.delta_pos | es.delta_dir)
    max_i = ctx.strategies.max_light_vertices()
    active = es.valid & (max_i is None or max_i >= 1)
    state = PathState.start(_emission_ray(es, ctx), es.beta, 0.0, d_vc, y0, active, medium,
                            vm_shares=_vm_shares(ctx))
    state.rays += rays
    return es, state


def _emission_ray(es, ctx) -> mi.Ray3f:
    """The ray leaving y_0.  Mitsuba's spawn_ray offsets its origin along the normal,
    which a point light lacks (n = 0): OptiX then reports the surface that the light
    sits on at t = 0 (Embree does not; a black image came out bright under
    cuda_ad_rgb, tests/test_stability.py point-on-surface), so such a ray is offset
    along its own direction, as an environment's is (its n is d)."""
    no_normal = dr.all(es.n == 0.0)
    return _point(es.p, dr.select(no_normal, es.d, es.n), ctx.time, ctx.wavelengths).spawn_ray(es.d)


# -- camera subpaths ----------------------------------------------------------------
def trace_camera_subpaths(ctx, rays, store) -> PathState:
    """Camera subpaths z_0 .. z_n with every strategy t >= 2; returns the final
    state (``radiance``, ``hit``, ``rays`` per lane)."""
    max_j = ctx.strategies.max_camera_vertices()
    d_vcm, d_vc = ctx.weights.camera_start(rays.pdf_w)
    # z_0: the pinhole, the lane's lens point, or its point on an orthographic film plane
    z0 = _point(rays.origin, mi.Normal3f(0.0), ctx.time, ctx.wavelengths)
    state = PathState.start(rays.ray, rays.weight, d_vcm, d_vc, z0, max_j is None or max_j >= 1,
                            ctx.media.camera_start() if ctx.media.present else None,
                            vm_shares=_vm_shares(ctx), merge_counts=ctx.grid is not None,
                            link_counts=ctx.moments is not None)

    def step(state: PathState, u: DepthSamples, sampler):
        t = state.depth + 1
        first = state.depth == 1
        flight, v = _next_vertex(ctx, state, sampler,
                                 first if camera_passes_emitters(ctx) else None)
        state.hit |= first & flight.medium
        if ctx.emitters.environment is not None:
            _add(ctx, state, 0, t, connect.environment_hit(ctx, state, flight))
        _camera_vertex_mis(ctx, state, v, flight)
        walking = state.active
        if ctx.strategies.light_first_hits:     # z_1's strategies are the light image's
            state.active = walking & ~first
        connectible = state.active & v.smooth
        if ctx.emitters.count:
            _add(ctx, state, 0, t, connect.emission_hit(ctx, state, v))
        if ctx.weights.lafortune:   # past a delta z_j, no connection ends at z_{j-1}
            state.lw = dr.select(v.smooth, state.lw, state.lw_prev)
        if ctx.emitters.count:
            _add(ctx, state, 1, t, *connect.next_event(
                ctx, state, v, u.endpoint, connectible & ctx.strategies.enabled(1, t)))
        if store is not None and ctx.strategies.connects:
            at = connectible & ctx.strategies.connects_at(t)
            if ctx.links is not None:           # connected after the walk (connect.run_links)
                connect.defer(ctx, store, state, v, at)
            else:
                state.radiance, rays = connect.stored_vertices(ctx, store, state, v, at)
                state.rays += rays
                if state.links is not None:
                    state.links += rays
        if ctx.grid is not None:                # vertex merging (merge.py)
            can = merge.can_merge(ctx.strategies, v, state.depth, connectible)
            if ctx.queries is not None:         # merged after the walk (merge.run_queries)
                merge.defer(ctx, state, v, can)
            else:
                merged = merge.merge_at(ctx, store, state, v, can)
                if not ctx.weights.shadow:      # a shadow pass merges for its moments only
                    state.radiance = ctx.strategies.add_merge(ctx.images, state.radiance,
                                                              ctx.lane, merged)
        goes_on = walking if max_j is None else walking & (state.depth < max_j)
        delta, null = _scatter(ctx, state, v, u, goes_on, importance=False)
        # Film alpha, as Mitsuba's path: a surface the path reaches and does not pass
        # through by a null lobe (mask, null: a medium boundary) makes the sample opaque.
        state.hit |= flight.surface & ~null
        if ctx.strategies.ppm:                  # merged at its first smooth vertex
            state.active &= delta
        state.specular_z1 |= first & delta
        if ctx.strategies.light_first_hits:     # past z_1 only through a delta lobe
            state.active &= ~first | delta
        if ctx.weights.lafortune:
            state.lw_prev = mi.Float(state.lw)
            state.lw *= ctx.weights.specularity(v.bsdf.flags(), delta)

    return _loop("camera subpaths", state, ctx.camera_sampler, step)


@dataclass
class PathTracerWalk:
    """What a pass reads of a camera walk (``PathState``'s fields of that name)."""
    radiance: mi.Spectrum
    hit: mi.Bool
    rays: mi.UInt32          # not counted by Mitsuba: 0
    slot: mi.UInt32
    specular_z1: mi.Bool


def path_tracer_walk(integrator: mi.Integrator, scene, rays, sampler) -> PathTracerWalk:
    """The camera walk of a pass whose budget is path tracing (light_paths 0), run by
    Mitsuba's own ``path`` integrator on the pass's camera rays: its megakernel costs
    0.87x this engine's s <= 1 walk (525 against 605 ms of kernel time on the glass
    pane, 128x128, 256 spp), and the estimator is the same (next-event
    estimation and BSDF sampling, power heuristic), so the image stays unbiased.
    Only in scenes without media (``path`` ignores them)."""
    n = dr.width(rays.pixel)
    radiance, valid, _ = integrator.sample(scene, sampler, rays.ray, None, dr.ones(mi.Bool, n))
    return PathTracerWalk(radiance=mi.Spectrum(radiance * rays.weight), hit=mi.Bool(valid),
                          rays=dr.zeros(mi.UInt32, n), slot=dr.zeros(mi.UInt32, n),
                          specular_z1=dr.zeros(mi.Bool, n))


def _camera_vertex_mis(ctx, state: PathState, v, flight):
    """The MIS chains at z_j, in area measure."""
    cos_in, _ = v.cosine(state.ray.d)
    dist2 = dr.squared_norm(v.p - state.prev.p)
    dens = flight.dens_fwd, flight.dens_rev
    state.d_vcm, state.d_vc = ctx.weights.after_hit(state.d_vcm, state.d_vc, dist2, cos_in, *dens)
    if ctx.moments is not None:
        state.d_end = mis.end_after_hit(state.d_end, dist2, cos_in, state.depth == 1, *dens)
    if state.d_vm is not None:
        state.d_vm = mis.vm_after_hit(state.d_vm, dist2, cos_in, *dens)


# -- shared steps ---------------------------------------------------------------------
def _vm_shares(ctx) -> bool:
    """A moment pass with merging: its walks carry d_vm (mis.vm_after_scatter)."""
    return ctx.moments is not None and ctx.weights.merges_evaluated


def _next_vertex(ctx, state: PathState, sampler, past_emitters=None):
    """The vertex the ray reaches (media: past null collisions and boundaries, with the
    free flights' weight); lanes whose ray escapes stop (``flight.escaped``).
    ``past_emitters``: lanes whose ray passes area emitters (media.camera_passes_emitters)."""
    flight = ctx.media.next_vertex(state, sampler, state.active, past_emitters)
    state.rays += flight.rays
    state.active = flight.surface | flight.medium
    if not ctx.media.present:
        return flight, Vertex(flight.si, flight.si.bsdf())
    state.beta = mi.Spectrum(state.beta * flight.weight)
    state.rr_beta = mi.Spectrum(state.rr_beta * flight.weight)
    v = Vertex.in_walk(flight.si, flight.mei, flight.medium, state.medium, True)
    state.sigma_prev = v.sigma_t()       # for the next edge's reverse density
    return flight, v


def _add(ctx, state: PathState, s, t, value, rays=None):
    """Strategy (s, t)'s contribution to this camera sample (and its shadow rays)."""
    state.radiance = ctx.strategies.add(ctx.images, state.radiance, ctx.lane, s, t, value)
    if rays is not None:
        state.rays += rays


def _scatter(ctx, state: PathState, v: Vertex, u: DepthSamples, active, importance: bool):
    """Sample the BSDF (or phase function) at the current vertex, extend the subpath by
    one ray, update the MIS chains and apply Russian roulette; returns whether a delta
    lobe, and whether a null lobe, was sampled."""
    mode = IMPORTANCE if importance else RADIANCE
    bs, weight, wo = v.sample(mode, u.lobe, u.direction, active)
    cos_out, ok = v.cosine(wo)
    active = active & ok & (bs.pdf > 0)
    delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
    null = active & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null)
    if importance:
        # Smooth lobes: the adjoint from the BSDF itself (surface.eval_adjoint); a delta
        # lobe cannot be evaluated, so it keeps the correction with si.sh_frame.  The
        # same call gives the reverse (radiance-mode) pdf.
        # f_adj / pdf only where the BSDF accepted its own sample (weight > 0): a rough
        # dielectric whose microfacet reflects wi to the far side (or refracts it back)
        # returns weight 0 with bs.wo and the sampled lobe's pdf set, while eval sees
        # the other lobe there; counting such samples made light tracing through rough
        # glass 20-60% too bright (tests/test_rough_glass.py).
        f_adj, pdf_rev_w = v.eval_adjoint(wo, active)
        smooth = dr.select(spectrum_nonzero(weight), f_adj * dr.rcp(bs.pdf), 0.0)
        weight = dr.select(delta, weight * adjoint_correction(v.si, wo), smooth)
    else:
        pdf_rev_w = v.reverse_pdf(wo, active) if ctx.weights.chains else mi.Float(0.0)
    # Lanes that stop keep garbage from here on; nothing reads it.
    if ctx.moments is not None:
        state.d_end = mis.end_after_scatter(state.d_end, state.d_vcm, state.d_vc, cos_out, bs.pdf,
                                            pdf_rev_w, delta, state.depth == 1, importance)
    if state.d_vm is not None:
        state.d_vm = mis.vm_after_scatter(state.d_vm, cos_out, bs.pdf, pdf_rev_w, delta,
                                          ctx.weights.vm_moment(v.surface))
    state.d_vcm, state.d_vc = ctx.weights.after_scatter(state.d_vcm, state.d_vc, cos_out,
                                                        bs.pdf, pdf_rev_w, delta, state.depth,
                                                        v.surface)
    state.beta = mi.Spectrum(state.beta * weight)       # (spectral arithmetic may
    state.rr_beta = mi.Spectrum(state.rr_beta * weight) # give a plain Array4f)
    state.eta *= bs.eta
    state.prev = _point(v.p, v.si.n, v.si.time, v.si.wavelengths)
    state.ray = v.spawn_ray(wo)
    if ctx.media.present:
        state.medium = v.medium_toward(wo)
    state.depth += 1
    state.active = _roulette(ctx, state, u.roulette, active, importance)
    return delta, null


def _roulette(ctx, state: PathState, u, active, importance: bool) -> mi.Bool:
    """Russian roulette from vertex ``rr_depth`` on (Mitsuba's rule); left out of all
    MIS densities (see mis.py).  ``rr_beta`` carries the 1/q as Mitsuba's throughput
    does; without it q would shrink geometrically and rare survivors be fireflies."""
    q = dr.max(mi.unpolarized_spectrum(state.rr_beta))
    if not importance:
        q = q * dr.square(state.eta)
    q = dr.minimum(q, 0.95)
    roulette = active & (state.depth > ctx.settings.rr_depth)
    survive = u < q
    state.beta = mi.Spectrum(dr.select(roulette, state.beta * dr.rcp(q), state.beta))
    state.rr_beta = mi.Spectrum(dr.select(roulette, state.rr_beta * dr.rcp(q), state.rr_beta))
    return active & (~roulette | survive) & (dr.max(mi.unpolarized_spectrum(state.beta)) > 0)
