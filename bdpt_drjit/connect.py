"""The four kinds of strategies: each returns (or splats) one MIS-weighted
contribution per lane.

=============  ============================================  ==================
strategy       how the path is completed                     where it lands
=============  ============================================  ==================
s = 0          camera subpath hits an emitter                camera block
s = 1          fresh emitter sample at z_{t-1} (NEE)         camera block
t = 1          light vertex connected through the pinhole    light block (splat)
s, t >= 2      shadow ray between y_{s-1} and z_{t-1}        camera block
=============  ============================================  ==================

Contribution of (s, t) (Veach eq. 10.8, pbrt-v3 section 16.3.3):
    C = beta_L(y_{s-1}) f_L(y_{s-2} -> y_{s-1} -> z) G f_E(y -> z_{t-1} -> z_{t-2}) beta_E(z_{t-1})
with Mitsuba's ``bsdf.eval`` already holding each endpoint's shading cosine, so G
reduces to 1 / d^2.  Light-side BSDFs are evaluated in importance mode with the
shading-normal adjoint correction.  Every contribution passes ``finite``.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from . import mis
from .emitters import DIRECTIONAL
from .records import (Vertex, eval_adjoint, finite, geometric_cosines,
                      reverse_pdf, spectrum_nonzero)

RADIANCE = mi.BSDFContext(mi.TransportMode.Radiance)
IMPORTANCE = mi.BSDFContext(mi.TransportMode.Importance)


def _count(ctx, mask):
    """Count a traced ray per lane (rays-per-sample statistics)."""
    ctx.rays += dr.select(mask, 1, 0)


def emission_hit(ctx, si, beta, d_vcm, d_vc, prev: mi.Interaction3f | None, active, lw=None):
    """s = 0, t = j + 1: the camera ray arriving at z_j hit an area emitter.

    ``prev`` is z_{j-1} (None when it is the pinhole, j = 1)."""
    emitter = si.emitter(ctx.scene, active)
    hit = active & (emitter != None)  # noqa: E711  (Dr.Jit pointer comparison)
    contrib = beta * emitter.eval(si, hit)
    if ctx.use_mis and ctx.h.is_lafortune:
        contrib *= mis.weight_lafortune(lw, None, "hit")
    elif ctx.use_mis:
        n = si.sh_frame.n
        to_prev = si.to_world(si.wi)
        pos_pdf, emission_pdf, _, _ = ctx.emitters.emission_pdfs(emitter, n, to_prev, hit)
        if prev is None:
            # The rival s = 1 strategy is (1,1): y_0 chosen by emission sampling.
            direct_pdf = pos_pdf if ctx.enabled(1, 1) else mi.Float(0.0)
        else:
            direct_pdf = ctx.emitters.nee_pdf_a(prev, si.p, n, si.uv, emitter,
                                                mi.Bool(False), si.time, hit)
        if ctx.pt_only:             # rivals: NEE only (no light vertices beyond y_0)
            d_vc = mi.Float(0.0)
        contrib *= mis.weight_emission_hit(ctx.h, d_vcm, d_vc, direct_pdf, emission_pdf)
    return dr.select(hit, finite(contrib), 0.0)


def environment_hit(ctx, ray, beta, d_vcm, d_vc, prev: mi.Interaction3f | None, active, lw=None):
    """s = 0, t = j + 1: the camera ray leaving z_{j-1} escaped to the environment.

    ``d_vcm``, ``d_vc``: the camera state after the last scatter (solid angle at
    z_{j-1}); the rival strategies' densities are solid-angle ones too (SmallVCM's
    background light).  A camera ray that escapes at once (``prev`` None) has no
    rival: y_0 at infinity cannot be connected to the pinhole."""
    env = ctx.emitters.environment
    le = ctx.emitters.environment_radiance(env, -ray.d, ray.wavelengths, ray.time, active)
    contrib = beta * le
    if ctx.use_mis and ctx.h.is_lafortune:
        contrib *= mis.weight_lafortune(lw, None, "hit")
    elif ctx.use_mis and prev is not None:
        direct_pdf, emission_pdf = ctx.emitters.environment_pdfs(
            mi.EmitterPtr(env), prev, ray.d, active)
        if ctx.pt_only:             # rivals: NEE only
            d_vc = mi.Float(0.0)
        contrib *= mis.weight_emission_hit(ctx.h, d_vcm, d_vc, direct_pdf, emission_pdf)
    return dr.select(active, finite(contrib), 0.0)


def next_event(ctx, si, bsdf, vertex: Vertex, sample, active):
    """s = 1, t = j + 1: sample a point on an emitter from z_j (Mitsuba's own light
    sampling, so its pdf includes the selection pmf) and connect to it."""
    scene = ctx.scene
    ds, spec = scene.sample_emitter_direction(si, sample, False, active)
    active = active & ((ds.pdf > 0) & spectrum_nonzero(spec))
    _, cos_cam, ok = geometric_cosines(si, ds.d)
    active = active & ok
    wo = si.to_local(ds.d)
    f, bsdf_pdf = bsdf.eval_pdf(RADIANCE, si, wo, active)
    contrib = vertex.beta * f * spec
    active = active & spectrum_nonzero(contrib)
    _count(ctx, active)
    active = active & ~scene.ray_test(si.spawn_ray_to(ds.p), active)
    if ctx.use_mis and ctx.h.is_lafortune:
        contrib *= mis.weight_lafortune(vertex.lw, mis.lafortune_specularity(bsdf.flags()),
                                        "nee", ds.delta)
    elif ctx.use_mis:
        bsdf_pdf = dr.select(ds.delta, 0.0, bsdf_pdf)
        bsdf_rev = reverse_pdf(bsdf, IMPORTANCE, si, wo, active)
        _, emission_pdf, cos_light, _ = ctx.emitters.emission_pdfs(ds.emitter, ds.n, -ds.d, active)
        # The weight uses Mitsuba's pdf_emitter_direction, not ds.pdf: the s = 0
        # strategy and the light subpaths can only query the former, and for some
        # shapes (a sphere seen from inside) the two differ slightly.  Equal pdfs
        # in every strategy keep the weights summing to one.
        # A delta-position emitter's pdf is the pmf per unit *area* measure; in solid
        # angle at z_{t-1} it becomes pmf * d^2 (cos_light = 1), as in SmallVCM.
        nee_pdf = dr.select(ds.delta, ds.pdf * dr.square(ds.dist),
                            scene.pdf_emitter_direction(si, ds, active & ~ds.delta))
        if DIRECTIONAL in ctx.emitters.kinds_present:
            # A directional light: a discrete direction picked with its pmf, at
            # infinity (no distance), tech. rep. section 5.1.
            is_dir = ctx.emitters.kind_of(ds.emitter, active) == DIRECTIONAL
            nee_pdf = dr.select(is_dir, ds.pdf, nee_pdf)
        d_vcm, d_vc = vertex.d_vcm, vertex.d_vc
        if ctx.pt_only:             # rivals: the emitter hit only
            d_vcm, d_vc = mi.Float(0.0), mi.Float(0.0)
        contrib *= mis.weight_nee(ctx.h, d_vcm, d_vc, bsdf_pdf, nee_pdf,
                                  emission_pdf, cos_cam, cos_light, bsdf_rev)
    return dr.select(active, finite(contrib), 0.0)


def light_vertex_to_camera(ctx, si, bsdf, vertex: Vertex, s: int, sample, active):
    """t = 1, s = i + 1: connect light vertex y_i to the pinhole and splat."""
    scene = ctx.scene
    ds, importance = ctx.sensor.sample_direction(si, sample, active)
    active = active & (ds.pdf > 0)
    _, cos_out, ok = geometric_cosines(si, ds.d)
    active = active & ok
    wo = si.to_local(ds.d)
    f, rev = eval_adjoint(bsdf, si, wo, active)
    contrib = vertex.beta * f * importance * ctx.camera_weight
    active = active & spectrum_nonzero(contrib)
    _count(ctx, active)
    active = active & ~scene.ray_test(si.spawn_ray_to(ds.p), active)
    if ctx.use_mis:
        # imp = pdf_w(camera) / d^2, so the camera's area density at y_i is imp * cos.
        cam_pdf_a = mi.unpolarized_spectrum(importance)[0] * cos_out / ctx.light_ratio
        contrib *= mis.weight_light_to_camera(ctx.h, vertex.d_vcm, vertex.d_vc, cam_pdf_a, rev)
    ctx.film.splat(s, ds.uv, si.wavelengths, finite(contrib), active)


def emitter_to_camera(ctx, es, sample):
    """(1,1): the emitter point y_0 of the light subpath seen through the pinhole.

    Delta-position emitters are skipped: a pinhole sees a point light with
    probability zero (Mitsuba's path tracer and ptracer do not show them either).
    So are environments: y_0 at infinity is seen by camera rays that escape (s = 0).
    """
    active = es.valid & ~es.delta_pos & ~es.infinite
    it = dr.zeros(mi.Interaction3f)
    it.p, it.n, it.time, it.wavelengths = es.p, es.n, ctx.time, ctx.wavelengths
    ds, importance = ctx.sensor.sample_direction(it, sample, active)
    active = active & (ds.pdf > 0)
    le = ctx.emitters.emitted(es.emitter, es.p, es.n, es.uv, ds.d, mi.Bool(False),
                              ctx.wavelengths, ctx.time, active)
    cos_e = dr.abs(dr.dot(es.n, ds.d))
    contrib = le * cos_e / es.pos_pdf_a * importance * ctx.camera_weight
    active = active & spectrum_nonzero(contrib)
    _count(ctx, active)
    active = active & ~ctx.scene.ray_test(it.spawn_ray_to(ds.p), active)
    if ctx.use_mis:
        cam_pdf_a = mi.unpolarized_spectrum(importance)[0] * cos_e / ctx.light_ratio
        contrib *= mis.weight_emitter_to_camera(ctx.h, cam_pdf_a, es.pos_pdf_a)
    ctx.film.splat(1, ds.uv, ctx.wavelengths, finite(contrib), active)


def connect_vertices(ctx, light: Vertex, cam: Vertex, bsdf_c):
    """s, t >= 2: connect a stored light vertex y_{s-1} to the camera vertex z_{t-1}
    the camera walk is at (``cam.si``, ``bsdf_c``: its live interaction and BSDF)."""
    active = light.connectible & cam.connectible
    si_c = cam.si
    si_l = mi.SurfaceInteraction3f(light.si)    # a copy: eval_adjoint swaps its wi
    bsdf_l = si_l.bsdf()
    d = si_l.p - si_c.p
    dist2 = dr.squared_norm(d)
    w = d * dr.rsqrt(dist2)                     # from z_{t-1} toward y_{s-1}
    active = active & (dist2 > 0)
    _, cos_c, ok_c = geometric_cosines(si_c, w)
    _, cos_l, ok_l = geometric_cosines(si_l, -w)
    active = active & (ok_c & ok_l)
    wc, wl = si_c.to_local(w), si_l.to_local(-w)
    f_c, pdf_c = bsdf_c.eval_pdf(RADIANCE, si_c, wc, active)
    f_l, rev_l = eval_adjoint(bsdf_l, si_l, wl, active)
    contrib = cam.beta * f_c * f_l * light.beta / dist2
    active = active & spectrum_nonzero(contrib)
    _count(ctx, active)
    active = active & ~ctx.scene.ray_test(si_c.spawn_ray_to(si_l.p), active)
    if ctx.use_mis and ctx.h.is_lafortune:
        contrib *= mis.weight_lafortune(cam.lw, mis.lafortune_specularity(bsdf_c.flags()), "connect")
    elif ctx.use_mis:
        pdf_l = bsdf_l.pdf(IMPORTANCE, si_l, wl, active)
        rev_c = reverse_pdf(bsdf_c, IMPORTANCE, si_c, wc, active)
        contrib *= mis.weight_connect(ctx.h, light.d_vcm, light.d_vc, cam.d_vcm, cam.d_vc,
                                      pdf_c * cos_l / dist2, rev_c,
                                      pdf_l * cos_c / dist2, rev_l)
    return dr.select(active, finite(contrib), 0.0)
