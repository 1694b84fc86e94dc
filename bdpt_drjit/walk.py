"""Subpath walks: light subpaths and camera subpaths, one depth step per kernel.

Each step intersects, updates the MIS state (mis.py), records the vertex, adds the
strategies that need nothing but this vertex (t = 1 splats on light subpaths; s = 0
and s = 1 on camera subpaths), samples the BSDF and applies Russian roulette.  A
camera step also connects its vertex z_j to the stored light vertices (s, t >= 2).
One ``dr.eval`` per depth; depth-dependent choices are Python branches that give a
handful of kernel variants, never a kernel per depth.

Sparse work is compacted (compact.py): once few camera lanes live, the camera
wavefront shrinks to them; light vertices alive in few lanes are connected as a list
of items.  Neither changes a sample: the same seed gives the same image.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from . import compact, connect, mis
from .compact import Draws, SparseLights, connect_sparse, send_sparse_home
from .emitters import DIRECTIONAL, ENV
from .records import (Vertex, adjoint_correction, compact_interaction, eval_adjoint,
                      gather_vertex, geometric_cosines, reverse_pdf)

RADIANCE, IMPORTANCE = connect.RADIANCE, connect.IMPORTANCE


def _interaction(si: mi.SurfaceInteraction3f) -> mi.Interaction3f:
    """The part of a vertex that pdf queries on the next vertex need."""
    it = dr.zeros(mi.Interaction3f)
    it.p, it.n, it.t, it.time, it.wavelengths = si.p, si.n, si.t, si.time, si.wavelengths
    return it


def _scatter(ctx, sampler, si, bsdf, mode_ctx, rev_ctx, d_vcm, d_vc, beta, alpha, eta,
             active, depth, importance: bool):
    """Sample the BSDF at the current vertex and extend the subpath by one ray;
    also returns whether a delta lobe was sampled."""
    bs, weight = bsdf.sample(mode_ctx, si, sampler.next_1d(active), sampler.next_2d(active), active)
    wo = si.to_world(bs.wo)
    _, cos_out, ok = geometric_cosines(si, wo)
    active = active & (ok & (bs.pdf > 0))
    delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
    if importance:
        # Smooth lobes: the adjoint from the BSDF itself (records.eval_adjoint); a delta
        # lobe cannot be evaluated, so it keeps the correction with si.sh_frame.
        # The same call gives the reverse (radiance-mode) pdf.
        f_adj, pdf_rev = eval_adjoint(bsdf, si, bs.wo, active)
        weight = dr.select(delta, weight * adjoint_correction(si, wo), f_adj * dr.rcp(bs.pdf))
    else:
        pdf_rev = reverse_pdf(bsdf, rev_ctx, si, bs.wo, active)
    d_vcm, d_vc = mis.after_scatter(ctx.h, d_vcm, d_vc, cos_out, bs.pdf, pdf_rev, delta)
    beta = beta * weight
    alpha = alpha * weight
    eta = eta * bs.eta
    # Russian roulette (Mitsuba's rule); left out of all MIS pdfs (see mis.py).
    if depth >= ctx.settings.rr_depth:
        q = dr.minimum(dr.max(mi.unpolarized_spectrum(alpha))
                       * (1.0 if importance else dr.square(eta)), 0.95)
        active = active & (sampler.next_1d(active) < q)
        # alpha carries the 1/q as Mitsuba's throughput does; without it q would
        # shrink geometrically and rare survivors become fireflies.
        beta = beta * dr.rcp(q)
        alpha = alpha * dr.rcp(q)
    active = active & (dr.max(mi.unpolarized_spectrum(beta)) > 0)
    ray = si.spawn_ray(wo)
    return ray, d_vcm, d_vc, beta, alpha, eta, active, delta


def trace_light_subpaths(ctx, max_vertex: int | None, sparse: SparseLights) -> list[Vertex | None]:
    """Light vertices y_1..y_n (n <= max_vertex), splatting t = 1 on the way.
    Entry i - 1 holds y_i, or None where no enabled strategy connects y_i to a
    camera vertex (such as the deepest one, used by t = 1 only), or where ``sparse``
    took it over."""
    sampler, scene = ctx.light_sampler, ctx.scene
    es = ctx.emitters.sample_emission(ctx.time, ctx.wavelengths, sampler.next_1d(),
                                      sampler.next_2d(), sampler.next_2d())
    # Samples are drawn whether or not a strategy is enabled, so that options
    # (hide_emitters, light_image, technique) keep the same random numbers.
    u_cam = sampler.next_2d()
    if ctx.enabled(1, 1):
        connect.emitter_to_camera(ctx, es, u_cam)
    d_vc = mis.light_start(ctx.h, es.emission_pdf, es.cos_emit, es.delta_pos | es.delta_dir)
    d_vcm = mi.Float(0.0)
    it0 = dr.zeros(mi.Interaction3f)
    it0.p, it0.n, it0.time, it0.wavelengths = es.p, es.n, ctx.time, ctx.wavelengths
    ray = it0.spawn_ray(es.d)
    beta, active, prev_p = es.beta, mi.Bool(es.valid), es.p
    alpha, eta = dr.ones(mi.Spectrum), mi.Float(1.0)
    sampler.schedule_state()
    dr.eval(es, ray, d_vc, ctx.rays)

    # Compaction (as in trace_camera_subpaths) once few light lanes live: only while
    # sparse vertices can be taken as items (their records are then compact).
    draws = Draws(sampler)
    width, lane = dr.width(active), None
    full_rays, camera_weight = ctx.rays, ctx.camera_weight
    vertices: list[Vertex] = []
    i = 1
    while max_vertex is None or i <= max_vertex:
        alive = dr.count(active)[0]
        if alive == 0:
            break
        if (i > 1 and sparse.on and alive < compact.COMPACT_BELOW * width
                and width >= compact.MIN_LANES):
            if lane is not None:
                dr.scatter_reduce(dr.ReduceOp.Add, full_rays, ctx.rays, lane)
            idx = dr.compress(active)
            ray, beta, alpha, eta, d_vcm, d_vc, prev_p = (
                dr.gather(type(x), x, idx) for x in (ray, beta, alpha, eta, d_vcm, d_vc, prev_p))
            lane = idx if lane is None else dr.gather(mi.UInt32, lane, idx)
            width = dr.width(idx)
            active = dr.full(mi.Bool, True, width)
            ctx.rays = dr.zeros(mi.UInt32, width)
            ctx.camera_weight = dr.gather(type(camera_weight), camera_weight, lane)
            draws.lane = lane
        if lane is not None:
            scatters = max_vertex is None or i < max_vertex
            draws.prefetch([2] + ([1, 2] if scatters else [])
                           + ([1] if scatters and i >= ctx.settings.rr_depth else []))
        ctx.rays += dr.select(active, 1, 0)
        pi = scene.ray_intersect_preliminary(ray, False, active)
        si = pi.compute_surface_interaction(ray, mi.RayFlags.All, active)
        active = active & (si.is_valid())
        cos_in = dr.abs(dr.dot(si.n, ray.d))
        dist2 = dr.squared_norm(si.p - prev_p)
        if i == 1:
            nee = ctx.emitters.nee_pdf_a(si, es.p, es.n, es.uv, es.emitter, es.delta_pos,
                                         ctx.time, active & ~es.infinite)
            if ctx.emitters.kinds_present & {ENV, DIRECTIONAL}:
                # y_0 at infinity: the solid-angle NEE density, and no distance
                # (tech. rep. section 5.1; SmallVCM skips dist^2 for infinite lights).
                nee_w, _ = ctx.emitters.environment_pdfs(es.emitter, si, -ray.d,
                                                         active & es.infinite)
                nee = dr.select(es.infinite, nee_w, nee)
                dist2 = dr.select(es.infinite, 1.0, dist2)
            d_vcm, d_vc = mis.light_first_hit(ctx.h, d_vc, nee, es.emission_pdf, dist2, cos_in)
        else:
            d_vcm, d_vc = mis.after_hit(ctx.h, d_vcm, d_vc, dist2, cos_in)
        bsdf = si.bsdf()
        connectible = active & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        vertex = Vertex(si=si, beta=beta, d_vcm=d_vcm, d_vc=d_vc, connectible=connectible)
        u_cam = draws.next_2d()
        if ctx.enabled(i + 1, 1):
            connect.light_vertex_to_camera(ctx, si, bsdf, vertex, i + 1, u_cam, connectible)
        if max_vertex is None or i < max_vertex:
            prev_p = si.p
            ray, d_vcm, d_vc, beta, alpha, eta, active, _ = _scatter(
                ctx, draws, si, bsdf, IMPORTANCE, RADIANCE, d_vcm, d_vc, beta, alpha,
                eta, active, i, importance=True)
        else:
            active = dr.zeros(mi.Bool, width)
        sampler.schedule_state()
        stored = None
        if ctx.connects(i):
            stored = Vertex(si=compact_interaction(si), beta=vertex.beta, d_vcm=vertex.d_vcm,
                            d_vc=vertex.d_vc, connectible=connectible)
        dr.eval(ray, d_vcm, d_vc, beta, alpha, eta, active, prev_p, ctx.rays,
                *([] if stored is None else [stored]))
        if stored is not None and sparse.add(i, stored, lane):
            stored = None
        vertices.append(stored)
        i += 1
    if lane is not None:
        dr.scatter_reduce(dr.ReduceOp.Add, full_rays, ctx.rays, lane)
        dr.eval(full_rays)
        ctx.rays, ctx.camera_weight = full_rays, camera_weight
    sparse.finish()
    return vertices


def trace_camera_subpaths(ctx, cam, max_vertex: int | None, light_vertices: list[Vertex],
                          sparse: SparseLights):
    """Camera vertices z_1..z_n with the s = 0 and s = 1 strategies, and each z_j
    connected to the stored light vertices (s, t >= 2) while its interaction is live;
    returns the per-lane radiance of all these strategies.

    When few lanes survive, the wavefront is compacted (``compact.COMPACT_BELOW``): its state
    is gathered at the live lanes, ``lane`` maps them home (pbrt-v4's wavefront
    work items carry their pixel index the same way), light vertices are gathered
    at ``lane``, and radiance and ray counts are scattered back."""
    sampler, scene, sensor = ctx.camera_sampler, ctx.scene, ctx.sensor
    draws = Draws(sampler)
    ray = mi.Ray3f(cam.ray)
    beta, active = mi.Spectrum(cam.weight), mi.Bool(True)
    alpha, eta = dr.ones(mi.Spectrum), mi.Float(1.0)
    d_vcm, d_vc = mi.Float(0.0), mi.Float(0.0)
    lw = mi.Float(1.0)               # mis="lafortune": prod of W(z_m) over m < j
    prev = None
    pos = cam.pos
    width = dr.width(ray.o)
    radiance = dr.zeros(mi.Spectrum, width)
    lane = None                      # compacted: the home lane of each lane
    full_radiance = full_rays = None

    def send_home():
        """Add the compacted lanes' radiance and ray counts to their home lanes."""
        dr.scatter_reduce(dr.ReduceOp.Add, full_radiance, radiance, lane)
        dr.scatter_reduce(dr.ReduceOp.Add, full_rays, ctx.rays, lane)

    j = 1
    while max_vertex is None or j <= max_vertex:
        if j > 1:
            alive = dr.count(active)[0]
            if alive == 0:
                break
            if alive < compact.COMPACT_BELOW * width and width >= compact.MIN_LANES:
                if lane is None:
                    full_radiance, full_rays = radiance, ctx.rays
                else:
                    send_home()
                idx = dr.compress(active)
                ray, beta, alpha, eta, d_vcm, d_vc, prev, lw, pos = (
                    dr.gather(type(x), x, idx)
                    for x in (ray, beta, alpha, eta, d_vcm, d_vc, prev, lw, pos))
                lane = idx if lane is None else dr.gather(mi.UInt32, lane, idx)
                width = dr.width(idx)
                active = dr.full(mi.Bool, True, width)
                radiance = dr.zeros(mi.Spectrum, width)
                ctx.rays = dr.zeros(mi.UInt32, width)
                draws.lane = lane
            if lane is not None:
                # This depth's draws, in the order below: NEE, then BSDF lobe and
                # direction and Russian roulette (see _scatter).
                scatters = max_vertex is None or j < max_vertex
                draws.prefetch([2] + ([1, 2] if scatters else [])
                               + ([1] if scatters and j >= ctx.settings.rr_depth else []))
        ctx.rays += dr.select(active, 1, 0)
        pi = scene.ray_intersect_preliminary(ray, False, active)
        si = pi.compute_surface_interaction(ray, mi.RayFlags.All, active)
        escaped = active & ~si.is_valid()
        active = active & (si.is_valid())
        if ctx.emitters.environment is not None and ctx.enabled(0, j + 1):
            # s = 0 on a ray that escaped: the environment (MIS state as left by the
            # last scatter: no distance to convert, tech. rep. section 5.1).
            c = connect.environment_hit(ctx, ray, beta, d_vcm, d_vc, prev, escaped, lw)
            radiance += c
            ctx.film.put_strategy(ctx.film.strategy_block(0, j + 1), pos, ray.wavelengths, c, escaped)
        cos_in = dr.abs(dr.dot(si.n, ray.d))
        if j == 1:
            # Camera pdf of z_1 (tech. rep. eq. 31): imp * d^2 = 1 / (A cos^3).
            ds, imp = sensor.sample_direction(si, mi.Point2f(0.5), active)
            cam_pdf_w = mi.unpolarized_spectrum(imp)[0] * dr.square(ds.dist)
            d_vcm, d_vc = mis.camera_start(ctx.h, cam_pdf_w, ctx.light_ratio, ctx.settings.light_image)
            d_vcm, d_vc = mis.after_hit(ctx.h, d_vcm, d_vc, dr.square(ds.dist), cos_in)
        else:
            d_vcm, d_vc = mis.after_hit(ctx.h, d_vcm, d_vc, dr.squared_norm(si.p - prev.p), cos_in)
        bsdf = si.bsdf()
        connectible = active & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        vertex = Vertex(si=si, beta=beta, d_vcm=d_vcm, d_vc=d_vc, connectible=connectible, lw=lw)
        if ctx.enabled(0, j + 1):
            c = connect.emission_hit(ctx, si, beta, d_vcm, d_vc, prev, active, lw)
            radiance += c
            ctx.film.put_strategy(ctx.film.strategy_block(0, j + 1), pos, ray.wavelengths, c, active)
        u_light = draws.next_2d()
        if ctx.enabled(1, j + 1):
            c = connect.next_event(ctx, si, bsdf, vertex, u_light, connectible)
            radiance += c
            ctx.film.put_strategy(ctx.film.strategy_block(1, j + 1), pos, ray.wavelengths, c, active)
        # s, t >= 2: z_j to every light vertex y_i, in this kernel.  Dead lanes are
        # masked; compacting the pairs themselves (dr.compress per pair + gathers)
        # measured 13% slower than this at max_depth 8.
        sparse_now = lane is None and sparse.lane is not None and any(
            ctx.enabled(i + 1, j + 1) for i in sparse.indices)
        cam_record = None
        if sparse_now:                # for connect_sparse, after this kernel
            cam_record = Vertex(si=compact_interaction(si), beta=beta, d_vcm=d_vcm, d_vc=d_vc,
                                connectible=connectible, lw=lw)
        for i in range(1, len(light_vertices) + 1):
            lv = light_vertices[i - 1]
            if not ctx.enabled(i + 1, j + 1):
                continue
            if lane is None:
                if lv is None:       # not stored, or among the sparse items
                    continue
            elif lv is not None:
                lv = gather_vertex(lv, lane)
            else:                    # sparse: connect_compacted below
                continue
            c = connect.connect_vertices(ctx, lv, vertex, bsdf)
            radiance += c
            ctx.film.put_strategy(ctx.film.strategy_block(i + 1, j + 1), pos,
                                  ray.wavelengths, c, True)
        if lane is not None:
            radiance += compact.connect_compacted(ctx, sparse, vertex, bsdf, lane, j + 1)
        if max_vertex is None or j < max_vertex:
            prev = _interaction(si)
            ray, d_vcm, d_vc, beta, alpha, eta, active, delta = _scatter(
                ctx, draws, si, bsdf, RADIANCE, IMPORTANCE, d_vcm, d_vc, beta, alpha,
                eta, active, j, importance=False)
            if ctx.h.is_lafortune:
                lw = lw * mis.lafortune_specularity(bsdf.flags(), delta)
        else:
            active = dr.zeros(mi.Bool, width)
        sampler.schedule_state()
        dr.eval(radiance, ray, d_vcm, d_vc, beta, alpha, eta, active, prev, lw, ctx.rays,
                *([] if cam_record is None else [cam_record]))
        if cam_record is not None:
            connect_sparse(ctx, sparse, cam_record, j + 1)
        j += 1
    if lane is not None:
        send_home()
        radiance, ctx.rays = full_radiance, full_rays
    if sparse.lane is not None:
        send_sparse_home(sparse, radiance, ctx.rays)
    dr.eval(radiance, ctx.rays)
    return radiance
