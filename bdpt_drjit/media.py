"""Participating media: free flights in the walks, transmittance on connections, the
phase function at medium vertices, and the medium a subpath starts in.

Sampling follows Mitsuba's ``volpath``, so that ``max_depth`` and every estimate mean
the same in both:
  * A ray in a medium draws a free-flight distance with ``Medium.sample_interaction``
    (the majorant of one colour channel, drawn per ray segment) and weighs it by the
    transmittance over the channels' average density (one-sample spectral MIS, as
    Tungsten and ``volpathmis`` do; spectral variants use the hero wavelength, as
    ``volpath`` does).  Heterogeneous media use the null-collision scheme: a tentative
    collision is real with probability mean(sigma_t / majorant), else null (the ray
    goes on, no vertex).
  * Surfaces whose BSDF is ``null`` are medium boundaries, not vertices; the medium
    changes across them where the shape has interior or exterior media.  Depth
    counts scattering vertices, on surfaces and in media (``volpath``'s rule).
    (In a scene without media a null BSDF stays what it is for Mitsuba's ``path``:
    a delta vertex.)
  * Connections carry the transmittance between their endpoints: closed form in
    homogeneous media, ratio tracking in heterogeneous ones; a surface with a
    non-null BSDF in between blocks them.

MIS (mis.py, ``after_hit``): the density of a vertex reached through media carries
the density of the distances drawn on its way, per segment mean_c(T_c) through a
segment and mean_c(sigma_t,c T_c) into a medium vertex; the reverse density of the
same edge is the same product with the collision term at the other end.  Only
homogeneous segments contribute: in a heterogeneous medium the transmittance is known
only as a random estimate, and a weight that depends on one would no longer sum to
one over the strategies of a path (Veach eq. 9.3 needs a function of the path).
Their distance densities are left out of every strategy (pbrt-v3's choice for all
media): the weights stay a partition of unity, the render unbiased, only less well
balanced inside such a medium.

A light subpath starts in the medium around its emitter point: the medium a shape
with media declares on the side the ray leaves, or the emitter's own ``medium``,
otherwise the medium found by following the ray to the first medium boundary it
crosses (``locate``; a boundary face lying in the plane of an opaque surface makes
that search ambiguous: declare the emitter's medium there).  The camera's medium is
the sensor's ``medium``; at load time the same search checks that it is the medium
around the camera, so the two subpaths agree about where they are.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from .emitter_kinds import AREA
from .surface import spectrum_nonzero


def channel_mean(x) -> mi.Float:
    """The density a free flight was drawn with, from per-channel values: the mean
    over RGB channels (the channel is drawn uniformly), the hero wavelength's
    otherwise (``sample_interaction`` uses channel 0 outside RGB)."""
    x = mi.unpolarized_spectrum(x)
    if mi.is_rgb:
        return (x[0] + x[1] + x[2]) * (1.0 / 3.0)
    return x[0]


def _safe_div(a, b):
    r = a / b
    return dr.select((b > 0) & dr.isfinite(r), r, 0.0)


def draw_channel(u) -> mi.UInt32:
    if not mi.is_rgb:
        return mi.UInt32(0)
    return dr.minimum(mi.UInt32(u * 3.0), 2)


def connection_key(ctx, depth, s) -> mi.UInt32:
    """A number per lane, connection and pass: ratio tracking's random numbers along
    a connection are ``sample_tea_float32(key, i)``."""
    key, _ = mi.sample_tea_32(ctx.lane, ctx.noise_key ^ (mi.UInt32(depth) << 16) ^ mi.UInt32(s), 4)
    return key


def hidden(si: mi.SurfaceInteraction3f) -> mi.Bool:
    """An area emitter's surface, which the camera's first rays pass with hide_emitters:
    Mitsuba's path and volpath skip every area emitter along a camera ray (3.6 on;
    ``Integrator.skip_area_emitters``), so a hidden light shows what lies behind it,
    not its shape.  The light image's connections to the camera pass them too, and a
    light vertex on one is not seen (walk.py, splat.py)."""
    return si.is_valid() & (si.shape.emitter() != None)  # noqa: E711


def camera_passes_emitters(ctx) -> bool:
    """hide_emitters with area emitters: the camera's first ray and the light image's
    connections to the camera pass them (``hidden``)."""
    return ctx.settings.hide_emitters and AREA in ctx.emitters.kinds_present


def is_boundary(si: mi.SurfaceInteraction3f) -> mi.Bool:
    """A surface whose BSDF has a null lobe and nothing else (``null``): a medium
    boundary, crossed and not a vertex.  A mask or a thin dielectric, whose null lobe
    sits beside lobes that scatter, stays a vertex, as in a scene without media."""
    flags = si.bsdf().flags()
    scatters = (mi.has_flag(flags, mi.BSDFFlags.Smooth)
                | mi.has_flag(flags, mi.BSDFFlags.DeltaReflection)
                | mi.has_flag(flags, mi.BSDFFlags.DeltaTransmission))
    return mi.has_flag(flags, mi.BSDFFlags.Null) & ~scatters


def scene_media(scene: mi.Scene, sensor: mi.Sensor) -> list:
    """Every medium of the scene (shapes' interior and exterior, sensor, emitters)."""
    found = [sensor.get_medium()] + [e.get_medium() for e in scene.emitters()]
    for shape in scene.shapes():
        found += [shape.interior_medium(), shape.exterior_medium()]
    out = []
    for m in found:
        if m is not None and all(m is not o for o in out):
            out.append(m)
    return out


@dataclass
class Flight:
    """Where a walk's ray found its next vertex, past null collisions and null
    surfaces; ``surface``, ``medium`` and ``escaped`` are exclusive."""
    si: mi.SurfaceInteraction3f   # the surface reached (or the last one tried)
    mei: mi.MediumInteraction3f | None   # the collision (media only)
    surface: mi.Bool       # a surface vertex (its BSDF is not null)
    medium: mi.Bool        # a real collision: a medium vertex
    escaped: mi.Bool       # no surface ahead
    weight: mi.Spectrum    # throughput factor of the free flights (1 outside media)
    dens_fwd: mi.Float     # the edge's distance densities, forward and reverse (mis.py)
    dens_rev: mi.Float
    rays: mi.UInt32        # rays traced


class Media:
    """The media of one render's scene; everything here is a no-op without them."""

    def __init__(self, scene: mi.Scene, sensor: mi.Sensor):
        self.scene = scene
        self.all = scene_media(scene, sensor)
        self.present = bool(self.all)
        self.camera = sensor.get_medium()
        self.unbounded = None
        if self.present:
            self.unbounded = self._check_camera(sensor)

    def camera_start(self) -> mi.MediumPtr:
        return mi.MediumPtr(self.camera)

    # -- where a subpath is ---------------------------------------------------------
    def locate(self, p, d, time, active) -> mi.MediumPtr:
        """The medium around p: follow the ray (p, d) to the first surface of a shape
        with media, and take the medium on the side the ray arrives from; the
        unbounded region's medium if there is none."""
        found, medium, _ = self._boundary_ahead(mi.Ray3f(p, d, time), active)
        return dr.select(found, medium, dr.select(active, mi.MediumPtr(self.unbounded),
                                                  mi.MediumPtr(None)))

    def _boundary_ahead(self, ray, active):
        """(found, medium behind it, shape): the first medium boundary along ``ray``."""
        def body(ray, found, medium, shape, going):
            si = self.scene.ray_intersect(ray, going)
            hit = going & si.is_valid() & si.is_medium_transition()
            found |= hit
            medium = dr.select(hit, si.target_medium(-ray.d), medium)
            shape = dr.select(hit, si.shape, shape)
            going &= si.is_valid() & ~hit
            ray = dr.select(going, si.spawn_ray(ray.d), ray)
            return ray, found, medium, shape, going

        n = dr.width(active)
        state = (mi.Ray3f(ray), dr.zeros(mi.Bool, n), dr.zeros(mi.MediumPtr, n),
                 dr.zeros(mi.ShapePtr, n), mi.Bool(active))
        _, found, medium, shape, _ = dr.while_loop(state, lambda *s: s[-1], body,
                                                   label="find medium boundary")
        return found, medium, shape

    def _check_camera(self, sensor):
        """The unbounded region's medium, from where the camera's rays start (at its
        near clip distance); refuses a sensor whose ``medium`` is not the medium there.
        Nine rays over the film: each finds the first medium boundary ahead and the
        medium before it; a ray that finds none shows the camera in the unbounded
        region."""
        u = [0.02, 0.5, 0.98]
        pos = mi.Point2f([x for x in u for _ in u], [y for _ in u for y in u])
        rays, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
        found, around, shape = self._boundary_ahead(mi.Ray3f(rays), dr.full(mi.Bool, True, 9))
        declared = dr.reinterpret_array(mi.UInt32, mi.MediumPtr(self.camera))
        wrong = found & (dr.reinterpret_array(mi.UInt32, around) != declared)
        if dr.any(wrong):
            i = int(dr.compress(wrong)[0])
            raise ValueError(
                "bdpt: the sensor's medium is %s, but its rays start inside %s (the first medium "
                "boundary ahead of them is shape '%s'; the camera lies inside it, or within "
                "near_clip of its boundary): declare the medium around the camera as the sensor's <ref "
                "name=\"medium\"/>, or move the camera, or the camera and light subpaths "
                "would disagree about where they travel"
                % (_name(self.camera), _name(around[i]), shape[i].id()))
        return self.camera if not dr.all(found) else None

    def start_medium(self, es, time, active) -> mi.MediumPtr:
        """The medium a light subpath leaves y_0 in (module docstring): an area light on
        a shape with media, the side the ray leaves by; an emitter's own ``medium``;
        else the medium ``locate`` finds."""
        declared = es.emitter.get_medium()
        search = active & ~es.infinite & (declared == None)  # noqa: E711
        located = self.locate(es.p, es.d, time, search)
        shape = es.emitter.get_shape()
        transition = active & (shape != None) & shape.is_medium_transition()  # noqa: E711
        by_side = dr.select(dr.dot(es.n, es.d) > 0, shape.exterior_medium(),
                            shape.interior_medium())
        medium = dr.select(transition, by_side, dr.select(search, located, declared))
        return dr.select(es.infinite, mi.MediumPtr(self.unbounded), medium)

    # -- the walks' free flights ----------------------------------------------------------
    def next_vertex(self, state, sampler, active, past_emitters=None) -> Flight:
        """Follow ``state.ray`` (in ``state.medium``) to the next vertex: a surface with
        a non-null BSDF or a real collision, one free flight per loop iteration.  Null
        collisions and null surfaces move the ray on (``state.ray``, ``state.medium``).
        Each segment draws its channel, distance and collision type from ``sampler``.
        ``past_emitters`` (a mask, or None): those lanes' rays pass through the
        surfaces of area emitters as through null ones (hide_emitters: ``hidden``)."""
        n = dr.width(active)
        one = dr.ones(mi.Float, n)
        if not self.present:
            si = self.scene.ray_intersect(state.ray, mi.RayFlags.All, False, active)
            rays = dr.select(active, 1, 0)
            if past_emitters is not None:
                si, more = self._past_emitters(state.ray, si, active & past_emitters)
                rays += more
            return Flight(si=si, mei=None, surface=active & si.is_valid(),
                          medium=dr.zeros(mi.Bool, n), escaped=active & ~si.is_valid(),
                          weight=dr.ones(mi.Spectrum, n), dens_fwd=one, dens_rev=one,
                          rays=rays)
        loop = _Segments(ray=mi.Ray3f(state.ray), medium=mi.MediumPtr(state.medium),
                         weight=dr.ones(mi.Spectrum, n), dens_fwd=one, dens_rev=mi.Float(one),
                         first=dr.ones(mi.Bool, n), going=mi.Bool(active),
                         rays=dr.zeros(mi.UInt32, n), si=dr.zeros(mi.SurfaceInteraction3f, n),
                         mei=dr.zeros(mi.MediumInteraction3f, n), real=dr.zeros(mi.Bool, n),
                         past_emitters=(dr.zeros(mi.Bool, n) if past_emitters is None
                                        else mi.Bool(past_emitters)))
        behind = mi.Spectrum(state.sigma_prev)

        def body(loop, sampler):
            self._segment(loop, behind, sampler)
            return loop, sampler

        loop, _ = dr.while_loop((loop, sampler), lambda loop, sampler: loop.going, body,
                                label="free flights")
        state.ray, state.medium = loop.ray, loop.medium
        found = active & ~loop.real & loop.si.is_valid()
        return Flight(si=loop.si, mei=loop.mei, surface=found, medium=active & loop.real,
                      escaped=active & ~loop.real & ~loop.si.is_valid(), weight=loop.weight,
                      dens_fwd=loop.dens_fwd, dens_rev=loop.dens_rev, rays=loop.rays)

    def _past_emitters(self, ray, si, active):
        """The first surface along ``ray`` that is not an area emitter's, from its first
        hit ``si``: Mitsuba's ``skip_area_emitters``.  Returns it and the rays traced."""
        def body(ray, si, going, rays):
            going &= hidden(si)
            ray = dr.select(going, si.spawn_ray(ray.d), ray)
            found = self.scene.ray_intersect(ray, mi.RayFlags.All, False, going)
            return ray, dr.select(going, found, si), going, rays + dr.select(going, 1, 0)

        n = dr.width(active)
        _, si, _, rays = dr.while_loop((mi.Ray3f(ray), si, mi.Bool(active), dr.zeros(mi.UInt32, n)),
                                       lambda *s: s[2], body, label="past emitters")
        return si, rays

    def _segment(self, loop: "_Segments", behind, sampler) -> None:
        """One free flight of ``next_vertex`` (module docstring; Mitsuba's volpath)."""
        going, ray, medium = loop.going, loop.ray, loop.medium
        u_channel, u_distance, u_collision = (sampler.next_1d(going), sampler.next_1d(going),
                                              sampler.next_1d(going))
        loop.rays += dr.select(going, 1, 0)
        si = self.scene.ray_intersect(ray, mi.RayFlags.All, False, going)
        in_medium = going & (medium != None)  # noqa: E711
        mei = medium.sample_interaction(ray, u_distance, draw_channel(u_channel), in_medium)
        mei.t = dr.select(in_medium & (si.t < mei.t), dr.inf, mei.t)
        tr, pdf = medium.transmittance_eval_pdf(mei, si, in_medium)
        weight = mi.Spectrum(dr.select(in_medium, tr * _safe_div(1.0, channel_mean(pdf)), 1.0))
        collided = in_medium & mei.is_valid()
        p_null = channel_mean(_safe_div(mei.sigma_n, mei.combined_extinction))
        null = collided & (u_collision < p_null)
        real = collided & ~null
        weight *= mi.Spectrum(dr.select(null, mei.sigma_n * _safe_div(1.0, p_null),
                                        dr.select(real, mei.sigma_s * _safe_div(1.0, 1.0 - p_null),
                                                  1.0)))
        homogeneous = in_medium & medium.is_homogeneous()
        sigma_behind = dr.select(loop.first, behind, 1.0)
        loop.weight = dr.select(going, loop.weight * weight, loop.weight)
        loop.dens_fwd = dr.select(homogeneous, loop.dens_fwd * channel_mean(pdf), loop.dens_fwd)
        loop.dens_rev = dr.select(homogeneous, loop.dens_rev * channel_mean(tr * sigma_behind),
                                  loop.dens_rev)
        null_surface = going & ~collided & si.is_valid() & (
            is_boundary(si) | (loop.past_emitters & hidden(si)))
        # A null collision or a null surface: the ray goes on from there.
        moved = mi.Ray3f(ray)
        moved.o = dr.select(null_surface, si.spawn_ray(ray.d).o, mei.p)
        moved.maxt = dr.inf
        passing = null | null_surface
        loop.ray = dr.select(passing, moved, ray)
        loop.medium = dr.select(null_surface & si.is_medium_transition(),
                                si.target_medium(ray.d), medium)
        loop.si = dr.select(going, si, loop.si)
        loop.mei = dr.select(going, mei, loop.mei)
        loop.real = dr.select(going, real, loop.real)
        loop.first &= ~passing
        loop.going = going & passing & spectrum_nonzero(loop.weight)

    # -- connections --------------------------------------------------------------
    def transmittance(self, origin, target_p, target_sigma, key, active,
                      past_emitters: bool = False):
        """(T, dens_fwd, dens_rev, rays) of the segment from vertex ``origin`` (surface.
        Vertex) to the point ``target_p``; T is 0 where a non-null surface is in
        between.  ``target_sigma``: sigma_t at the target if it is a homogeneous medium
        vertex, else 1 (the distance density into it, module docstring).  ``key``
        numbers the connection, for ratio tracking's random numbers.  ``past_emitters``:
        the surfaces of area emitters pass as null ones (a connection to the camera
        with hide_emitters, as its camera rays pass them: ``hidden``)."""
        ray = origin.spawn_ray_to(target_p)
        n = dr.width(active)
        if not self.present and past_emitters:
            return self._march(ray, target_p, dr.zeros(mi.MediumPtr, n), 1.0, 1.0, key,
                               active, True)
        if not self.present:
            traced = mi.Bool(active)
            blocked = self.scene.ray_test(ray, traced)
            one = dr.ones(mi.Float, n)
            return (dr.select(traced & ~blocked, dr.ones(mi.Spectrum, n), 0.0), one, one,
                    dr.select(traced, 1, 0))
        medium = origin.medium_toward(ray.d)
        return self._march(ray, target_p, medium, origin.sigma_t(), target_sigma, key, active,
                           past_emitters)

    def _march(self, ray, target_p, medium, origin_sigma, target_sigma, key, active,
               past_emitters: bool = False):
        """The segments of a connection, one per loop iteration (see ``transmittance``).

        Past a null surface the next segment is a shadow ray of its own, spawned from
        the surface toward ``target_p`` (``spawn_ray_to``: its own offset and
        shadow epsilon), as the first one is from the origin vertex.  Going on along
        the old direction with ``maxt - si.t`` left the target inside the ray: the
        origin's offset along the surface normal brings the target's plane closer by
        offset / |cos|, which beat the shadow epsilon (1e-3 of the distance) at grazing
        crossings, and the target's own surface then blocked the connection
        (next-event rays from fog whose null top face lies 0.09 under an area light lost
        7% of their transmittance, path tracing rendered the scene 7% dark).  Mitsuba's
        volpath has that flaw (tests/test_media.py, ``_lamp_over_fog``).  A null
        collision of ratio tracking lies on the ray, without offset: there the ray
        goes on."""
        n = dr.width(active)
        tr = dr.select(active, dr.ones(mi.Spectrum, n), 0.0)
        dens_fwd, dens_rev = dr.ones(mi.Float, n), dr.ones(mi.Float, n)
        state = (mi.Ray3f(ray), mi.MediumPtr(medium), tr, dens_fwd, dens_rev,
                 dr.ones(mi.Bool, n), mi.Bool(active), dr.zeros(mi.UInt32, n))

        def body(ray, medium, tr, dens_fwd, dens_rev, first, going, rays):
            rays += dr.select(going, 1, 0)
            si = self.scene.ray_intersect(ray, mi.RayFlags.All, False, going)
            in_medium = going & (medium != None)  # noqa: E711
            homogeneous = in_medium & medium.is_homogeneous()
            u = mi.sample_tea_float32(key, rays, 4)
            mei = medium.sample_interaction(ray, u, 0, in_medium & ~homogeneous)
            end = dr.minimum(si.t, ray.maxt)
            # Heterogeneous: ratio tracking (a tentative collision multiplies by
            # sigma_n / majorant; Mitsuba's heterogeneous medium has one majorant).
            tracked = in_medium & ~homogeneous & mei.is_valid() & (mei.t < end)
            tr[tracked] *= mi.Spectrum(_safe_div(mei.sigma_n, mei.combined_extinction))
            # Homogeneous: the closed form over the whole segment.
            last = going & ~tracked & ~(si.t < ray.maxt)
            seg = mi.Spectrum(self._homogeneous_tr(ray, medium, end, homogeneous))
            tr[homogeneous] *= seg
            dens_fwd[homogeneous] *= channel_mean(seg * dr.select(last, target_sigma, 1.0))
            dens_rev[homogeneous] *= channel_mean(seg * dr.select(first, origin_sigma, 1.0))
            at_surface = going & ~tracked & (si.t < ray.maxt)
            passes = at_surface & is_boundary(si)
            if past_emitters:
                passes |= at_surface & hidden(si)
            tr[at_surface & ~passes] = 0.0
            changes = passes & si.is_medium_transition()
            medium = dr.select(changes, si.target_medium(ray.d), medium)
            aimed = si.spawn_ray_to(target_p)
            nxt = mi.Ray3f(ray)
            nxt.o = dr.select(tracked, mei.p, aimed.o)
            nxt.d = dr.select(tracked, ray.d, aimed.d)
            nxt.maxt = dr.select(tracked, ray.maxt - mei.t, aimed.maxt)
            first &= ~passes
            going &= (tracked | passes) & spectrum_nonzero(tr)
            return dr.select(going, nxt, ray), medium, tr, dens_fwd, dens_rev, first, going, rays

        out = dr.while_loop(state, lambda *s: s[6], body, label="transmittance")
        return out[2], out[3], out[4], out[7]

    @staticmethod
    def _homogeneous_tr(ray, medium, end, active):
        mei = medium.sample_interaction(ray, 0.0, 0, active)
        return dr.exp(-mei.combined_extinction * dr.maximum(end - mei.mint, 0.0))


@dataclass
class _Segments:
    """The loop state of ``Media.next_vertex``."""
    ray: mi.Ray3f                  # the current segment's ray
    medium: mi.MediumPtr           # the medium it travels in
    weight: mi.Spectrum            # product of the segments' throughput factors
    dens_fwd: mi.Float             # product of their distance densities (MIS)
    dens_rev: mi.Float
    first: mi.Bool                 # the segment leaves the previous vertex
    going: mi.Bool                 # the ray passed a null collision or surface
    rays: mi.UInt32                # rays traced
    si: mi.SurfaceInteraction3f    # the last segment's surface
    mei: mi.MediumInteraction3f    # the last segment's collision
    real: mi.Bool                  # the last segment ended in a real collision
    past_emitters: mi.Bool         # the ray passes area emitters' surfaces (hidden)


def _name(obj) -> str:
    if obj is None:
        return "none (vacuum)"
    return "'%s' (%s)" % (obj.id() or "unnamed", obj.class_name())
