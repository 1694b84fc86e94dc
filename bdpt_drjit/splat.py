"""The light image: strategies with t = 1, connecting a light vertex to the camera.

A light vertex y_{s-1} (or the emitter point y_0 for (1,1)) is connected to the
camera through ``camera.Camera.connect``, at a lens point drawn from the depth's
lens sample (the pinhole itself for a perspective sensor), which gives the film
position it projects to and the sensor's importance.  Visible, nonzero
contributions are appended to the pass's splat pool (vertices.Splat) and put on the
film's light block after the walks (film.py), normalized like Mitsuba's ``ptracer``:
by the film's pixel count over the number of light subpaths.  Without a light image
(an orthographic camera, whose direction is a delta, or light_image = false) these
functions trace nothing.

Each function returns the rays it traced per lane (statistics).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from . import mis
from .emitters import AREA
from .media import camera_passes_emitters, connection_key, hidden
from .surface import Vertex, finite, spectrum_nonzero
from .vertices import Splat


def light_vertex_to_camera(ctx, store, v, vertex, sample, active) -> mi.UInt32:
    """t = 1, s = i + 1: light vertex y_i (``v``, its record ``vertex``) seen by the
    camera."""
    if not ctx.strategies.light_image:      # no t = 1 strategy (an orthographic camera)
        return mi.UInt32(0)
    cam = ctx.camera.connect(v.p, sample, active)
    cos_out, ok = v.cosine(cam.d)
    active = cam.valid & ok
    hides = camera_passes_emitters(ctx)
    if hides:                   # the camera's rays pass area emitters (media.hidden)
        active &= ~(v.surface & hidden(v.si))
    f, rev_w = v.eval_adjoint(cam.d, active)
    contrib = vertex.beta * f * cam.importance * ctx.camera_weight
    traced = active & spectrum_nonzero(contrib)
    tr, _, dens_rev, rays = ctx.media.transmittance(
        v, cam.p, 1.0, connection_key(ctx, vertex.s - 1, 1), traced, hides)
    contrib *= tr
    active = traced & spectrum_nonzero(tr)
    # importance = pdf_w(camera) / d^2, so the camera's area density at y_i is
    # importance * cos (tech. rep. eq. 46), times the density of the camera ray's
    # distances through media.
    cam_pdf_a = cam.importance * cos_out * dens_rev
    contrib *= ctx.weights.light_to_camera(vertex.d_vcm, vertex.d_vc, vertex.s - 1, cam_pdf_a, rev_w,
                                           v.surface)
    u_pt, u_lt, u_vm = (0.0, 0.0, 0.0) if ctx.moments is None else _light_image_groups(
        ctx, mis.groups_light_image(vertex.d_vcm, ctx.weights.moment_d_vc(vertex.d_vc, vertex.d_vm),
                                    vertex.d_end, vertex.s == 2, cam_pdf_a, rev_w,
                                    ctx.weights.light_ratio, ctx.weights.rate(vertex.s - 1),
                                    vertex.d_vm, ctx.weights.vm_moment(v.surface)))
    store.splats.append(Splat(pos=cam.uv, value=mi.Spectrum(finite(contrib)), s=vertex.s,
                              lane=ctx.lane, u_pt=mi.Float(u_pt), u_lt=mi.Float(u_lt),
                              u_vm=mi.Float(u_vm)), active)
    return rays


def emitter_to_camera(ctx, store, es, medium, sample, active) -> mi.UInt32:
    """(1,1): the emitter point y_0 of the light subpath seen by the camera.

    Delta-position emitters are skipped, as Mitsuba's path tracer and ptracer skip
    them (a camera ray never hits a point light; through a thin lens (1,1) could
    connect one, and ptracer leaves that out too).
    So are environments: y_0 at infinity is seen by camera rays that escape (s = 0).
    ``medium``: the medium the light subpath starts in (media.Media.start_medium).
    Without area emitters nothing is left, and nothing is evaluated here: the emission
    sample is then computed in the light walk's kernel (a kernel of its own wrote and
    read it back, 100 of 1650 ms on the point caustic).
    """
    if not ctx.strategies.light_image or AREA not in ctx.emitters.kinds_present:
        return mi.UInt32(0)
    active = active & ~es.delta_pos & ~es.infinite
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.p, si.n, si.time, si.wavelengths = es.p, es.n, ctx.time, ctx.wavelengths
    if ctx.media.present:            # (the medium toward the camera: Vertex.medium_toward)
        si.shape = es.emitter.get_shape()
    y0 = Vertex(si, None, medium, mi.Bool(False), ctx.media.present)
    cam = ctx.camera.connect(es.p, sample, active)
    active = cam.valid
    le = ctx.emitters.emitted(es.emitter, es.p, es.n, es.uv, cam.d, mi.Bool(False),
                              ctx.wavelengths, ctx.time, active)
    cos_e = dr.abs(dr.dot(es.n, cam.d))
    contrib = le * cos_e / es.pos_pdf_a * cam.importance * ctx.camera_weight
    traced = active & spectrum_nonzero(contrib)
    tr, _, dens_rev, rays = ctx.media.transmittance(y0, cam.p, 1.0,
                                                    connection_key(ctx, 0, 1), traced)
    contrib *= tr
    active = traced & spectrum_nonzero(tr)
    cam_pdf_a = cam.importance * cos_e * dens_rev
    contrib *= ctx.weights.emitter_to_camera(cam_pdf_a, es.pos_pdf_a)
    # The only rival, (0,2), is path tracing; the light image's rate as in its weight.
    rival = cam_pdf_a / (es.pos_pdf_a * ctx.weights.light_ratio)
    u_pt, u_lt, u_vm = _light_image_groups(ctx, (rival / (1.0 + rival), 1.0 / (1.0 + rival), 0.0))
    record = Splat(pos=cam.uv, value=mi.Spectrum(finite(contrib)), s=mi.UInt32(1),
                   lane=ctx.lane, u_pt=mi.Float(u_pt), u_lt=mi.Float(u_lt), u_vm=mi.Float(u_vm))
    # Outside a loop an append's mask is evaluated at once: evaluate everything in one
    # kernel first, or the emission sample is computed twice (two large kernels).
    dr.eval(record, active, rays, es)
    store.splats.append(record, active)
    return rays


def _light_image_groups(ctx, groups):
    """(u_pt, u_lt, u_vm) of a light-image contribution: with light_first_hits the light
    image alone samples its paths (its weight is 1)."""
    return (0.0, 1.0, 0.0) if ctx.weights.light_first_hits else groups
