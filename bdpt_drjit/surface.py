"""What the walks and strategies need at a vertex: the live vertex (``Vertex``: a
surface with its BSDF, or a point in a medium with its phase function), a compact
record of it (``VertexRecord``, stored for light vertices), cosines against the
geometric normal, the adjoint BSDF of light subpaths, and reverse densities.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi


@dataclass
class VertexRecord:
    """The part of a SurfaceInteraction3f that BSDF evaluation reads: position,
    normals, shading frame and tangents (normal and bump maps), uv (textures), shape
    and primitive (mesh attributes, the BSDF pointer) and wi.  Storing it costs ~60
    bytes more per light vertex than storing the ray and preliminary intersection,
    but rebuilding the interaction (a virtual call over the scene's shapes) for every
    connection was the largest cost of a connection after its shadow ray.  Curvature
    and ray differentials stay zero, as on every interaction of the walks.
    A medium vertex keeps p, wi (as sh_frame's normal) and its medium."""
    p: mi.Point3f
    n: mi.Normal3f
    uv: mi.Point2f
    sh_frame: mi.Frame3f
    dp_du: mi.Vector3f
    dp_dv: mi.Vector3f
    wi: mi.Vector3f
    shape: mi.ShapePtr
    instance: mi.ShapePtr
    prim_index: mi.UInt32
    medium: mi.MediumPtr             # see Vertex.medium
    in_medium: mi.Bool               # a medium vertex

    @staticmethod
    def of(v: "Vertex") -> "VertexRecord":
        si = v.si
        return VertexRecord(p=si.p, n=si.n, uv=si.uv, sh_frame=si.sh_frame, dp_du=si.dp_du,
                            dp_dv=si.dp_dv, wi=si.wi, shape=si.shape, instance=si.instance,
                            prim_index=si.prim_index, medium=mi.MediumPtr(v.medium),
                            in_medium=mi.Bool(v.in_medium))

    def vertex(self, time, wavelengths, media: bool) -> "Vertex":
        si = self.interaction(time, wavelengths)
        return Vertex(si, si.bsdf(), self.medium, self.in_medium, media)

    def interaction(self, time, wavelengths) -> mi.SurfaceInteraction3f:
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.p, si.n, si.uv, si.sh_frame = self.p, self.n, self.uv, self.sh_frame
        si.dp_du, si.dp_dv, si.wi = self.dp_du, self.dp_dv, self.wi
        si.shape, si.instance, si.prim_index = self.shape, self.instance, self.prim_index
        si.time, si.wavelengths = time, wavelengths
        return si


def geometric_cosines(si: mi.SurfaceInteraction3f, wo_world: mi.Vector3f):
    """(cos_in, cos_out, ok) w.r.t. the geometric normal for wi = si.wi and wo.

    ``ok`` is False where a shading normal puts a direction on the other side than
    the geometric normal does; such configurations are given zero contribution in
    every strategy and walk (as Mitsuba's ptracer does to prevent light leaks), so
    all strategies estimate the same integrand.
    """
    wo_local = si.to_local(wo_world)
    wi_geo = dr.dot(si.n, si.to_world(si.wi))
    wo_geo = dr.dot(si.n, wo_world)
    ok = ((wi_geo * mi.Frame3f.cos_theta(si.wi) > 0)
          & (wo_geo * mi.Frame3f.cos_theta(wo_local) > 0))
    return dr.abs(wi_geo), dr.abs(wo_geo), ok


def adjoint_correction(si: mi.SurfaceInteraction3f, wo_world: mi.Vector3f):
    """Shading-normal correction of the adjoint BSDF (Veach p. 155, eq. 5.17):
    |cos_s(wi) cos_g(wo)| / |cos_s(wo) cos_g(wi)|, applied to light subpaths."""
    wo_local = si.to_local(wo_world)
    num = mi.Frame3f.cos_theta(si.wi) * dr.dot(si.n, wo_world)
    den = mi.Frame3f.cos_theta(wo_local) * dr.dot(si.n, si.to_world(si.wi))
    c = dr.abs(num / den)
    return dr.select(dr.isfinite(c), c, 0.0)


def reverse_pdf(bsdf: mi.BSDF, ctx: mi.BSDFContext, si: mi.SurfaceInteraction3f,
                wo_local: mi.Vector3f, active) -> mi.Float:
    """Density of sampling si.wi at this vertex had the path arrived from wo."""
    # Copy: a struct member read from Python is a reference to its storage.
    wi = mi.Vector3f(si.wi)
    si.wi = wo_local
    pdf = bsdf.pdf(ctx, si, wi, active)
    si.wi = wi
    return pdf


def spectrum_nonzero(x) -> mi.Bool:
    return dr.max(mi.unpolarized_spectrum(x)) > 0


def finite(x):
    """Zero where a value is not finite: the guard behind every contribution."""
    return dr.select(dr.isfinite(x), x, 0.0)


def eval_adjoint(bsdf: mi.BSDF, si: mi.SurfaceInteraction3f, wo_local: mi.Vector3f, active):
    """What a light subpath needs at this vertex for the direction wo (Veach eq. 5.17),
    and the reverse density, both from one ``eval_pdf`` call (one virtual call).

    Value: f*(wi -> wo) |cos_s(wi)| |cos_g(wo)| / |cos_g(wi)|, from the radiance-mode
    BSDF with the two directions swapped, f(wo -> wi) |cos_s(wi)|: the BSDF applies its
    own shading normal (a normal or bump map perturbs it inside the BSDF, where
    si.sh_frame does not see it), and the value is exactly what a path tracer integrates.
    Reverse pdf: the radiance-mode density of sampling si.wi had the path come from wo
    (what ``reverse_pdf(bsdf, RADIANCE, ...)`` returns)."""
    wi = mi.Vector3f(si.wi)
    si.wi = wo_local
    f, pdf_rev = bsdf.eval_pdf(mi.BSDFContext(mi.TransportMode.Radiance), si, wi, active)
    si.wi = wi
    num = dr.abs(dr.dot(si.n, si.to_world(wo_local)))
    den = dr.abs(dr.dot(si.n, si.to_world(wi)))
    return f * finite(num / den), pdf_rev


RADIANCE = mi.BSDFContext(mi.TransportMode.Radiance)
IMPORTANCE = mi.BSDFContext(mi.TransportMode.Importance)


# One virtual call for two queries of the same BSDF (``dr.dispatch``): on a GPU each
# call inside a loop spills the live state; a connection asked four.
def _forward_and_reverse(bsdf, si, wo_local, active):
    """(f cos, density of wo) in radiance mode, and the density of si.wi had the path
    arrived from wo (importance mode): what a camera vertex gives a connection."""
    f, pdf_w = bsdf.eval_pdf(RADIANCE, si, wo_local, active)
    return f, pdf_w, reverse_pdf(bsdf, IMPORTANCE, si, wo_local, active)


def _adjoint_and_forward(bsdf, si, wo_local, active):
    """``eval_adjoint``'s (value, reverse density) and the importance-mode density of
    wo: what a light vertex gives a connection."""
    f, rev_w = eval_adjoint(bsdf, si, wo_local, active)
    return f, rev_w, bsdf.pdf(IMPORTANCE, si, wo_local, active)


class Vertex:
    """A scattering vertex of a walk: a surface with its BSDF, or (``in_medium``) a
    point in a medium with its phase function.  Walks and strategies ask it for values
    and densities of world directions, whichever it is.  Without media in the scene
    (``media`` False) the medium branches are left out of the kernels.

    A medium vertex lives in ``si`` as p, time, wavelengths, a zero normal (so rays
    leave it without an offset) and wi as ``sh_frame``'s normal.  ``medium``: a medium
    vertex's medium; a surface's, the medium the path arrived in (the medium on both
    sides unless the shape declares media, ``medium_toward``)."""

    def __init__(self, si, bsdf, medium=None, in_medium=False, media: bool = False):
        self.si, self.bsdf = si, bsdf
        self.medium, self.in_medium, self.media = medium, in_medium, media

    @staticmethod
    def in_walk(si, mei, in_medium, medium, media: bool) -> "Vertex":
        """The vertex a walk's ray reached: the surface ``si`` or the collision ``mei``."""
        if not media:
            return Vertex(si, si.bsdf())
        at = dr.zeros(mi.SurfaceInteraction3f, dr.width(in_medium))
        at.p, at.time, at.wavelengths = mei.p, mei.time, mei.wavelengths
        at.sh_frame, at.wi = mi.Frame3f(mei.wi), mi.Vector3f(0.0, 0.0, 1.0)
        si = dr.select(in_medium, at, si)
        return Vertex(si, si.bsdf(), medium, in_medium, True)

    # -- geometry ------------------------------------------------------------------
    @property
    def p(self):
        return self.si.p

    def wi_world(self):
        return self.si.to_world(self.si.wi)

    def cosine(self, w):
        """(|cos| of direction w against the geometric normal, w usable): a medium
        vertex has no normal, 1 and True (see ``geometric_cosines``)."""
        _, cos, ok = geometric_cosines(self.si, w)
        if not self.media:
            return cos, ok
        return dr.select(self.in_medium, 1.0, cos), ok | self.in_medium

    def medium_toward(self, d) -> mi.MediumPtr:
        """The medium a ray leaving this vertex along d travels in."""
        si = self.si
        crosses = ~self.in_medium & si.is_medium_transition()
        return dr.select(crosses, si.target_medium(d), self.medium)

    def sigma_t(self):
        """sigma_t here for a homogeneous medium vertex, else 1: the collision term of
        a distance density into this vertex (media.py)."""
        if not self.media:
            return mi.Spectrum(1.0)
        homogeneous = self.in_medium & self.medium.is_homogeneous()
        mei = self.medium_interaction(self.wi_world())
        _, _, sigma_t = self.medium.get_scattering_coefficients(mei, homogeneous)
        return dr.select(homogeneous, mi.Spectrum(sigma_t), 1.0)

    def spawn_ray(self, d):
        return self.si.spawn_ray(d)

    def spawn_ray_to(self, p):
        return self.si.spawn_ray_to(p)

    @property
    def surface(self):
        """A surface vertex (True), not a point in a medium: only these merge."""
        return ~self.in_medium if self.media else True

    @property
    def smooth(self):
        """A connection can be made here (no delta lobes alone)."""
        smooth = mi.has_flag(self.bsdf.flags(), mi.BSDFFlags.Smooth)
        return smooth | self.in_medium if self.media else smooth

    # -- the phase function --------------------------------------------------------
    def medium_interaction(self, wi):
        mei = dr.zeros(mi.MediumInteraction3f, dr.width(self.si.p))
        mei.p, mei.time, mei.wavelengths = self.si.p, self.si.time, self.si.wavelengths
        mei.wi, mei.sh_frame, mei.medium = wi, mi.Frame3f(wi), self.medium
        return mei

    def _phase(self, wi, wo, active):
        """(value, density) of the phase function scattering from wi to wo."""
        on = active & self.in_medium
        ctx = mi.PhaseFunctionContext(None)
        phase = self.medium.phase_function()
        return phase.eval_pdf(ctx, self.medium_interaction(wi), wo, on)

    def _mix(self, surface, wo, active, swap):
        """A surface value (pair) with the phase function's where in a medium."""
        if not self.media:
            return surface
        wi = self.wi_world()
        f, pdf = self._phase(wo if swap else wi, wi if swap else wo, active)
        return (dr.select(self.in_medium, mi.Spectrum(f), surface[0]),
                dr.select(self.in_medium, pdf, surface[1]))

    # -- values and densities ----------------------------------------------------------
    def eval(self, w, active):
        """(f cos, solid-angle density of sampling w) in radiance mode."""
        f, pdf = self.bsdf.eval_pdf(RADIANCE, self.si, self.si.to_local(w), active)
        return self._mix((f, pdf), w, active, False)

    def eval_adjoint(self, w, active):
        """(adjoint value toward w, reverse density): see ``eval_adjoint``."""
        return self._mix(eval_adjoint(self.bsdf, self.si, self.si.to_local(w), active),
                         w, active, True)

    def eval_and_reverse(self, w, active):
        """``eval(w)`` and ``reverse_pdf(w)`` in one call: (f cos, pdf_w, rev_w)."""
        f, pdf_w, rev_w = dr.dispatch(self.bsdf, _forward_and_reverse, self.si,
                                      self.si.to_local(w), active)
        f, pdf_w = self._mix((f, pdf_w), w, active, False)
        return f, pdf_w, self._mix((f, rev_w), w, active, True)[1]

    def eval_adjoint_and_pdf(self, w, active):
        """``eval_adjoint(w)`` and ``pdf(w)`` in one call: (f_adj, rev_w, pdf_w)."""
        f, rev_w, pdf_w = dr.dispatch(self.bsdf, _adjoint_and_forward, self.si,
                                      self.si.to_local(w), active)
        f, rev_w = self._mix((f, rev_w), w, active, True)
        return f, rev_w, self._mix((f, pdf_w), w, active, False)[1]

    def pdf(self, w, active, mode=IMPORTANCE):
        """The density of sampling w here."""
        pdf = self.bsdf.pdf(mode, self.si, self.si.to_local(w), active)
        return self._mix((mi.Spectrum(0.0), pdf), w, active, False)[1]

    def reverse_pdf(self, w, active, mode=IMPORTANCE):
        """The density of sampling wi here had the path arrived from w."""
        pdf = reverse_pdf(self.bsdf, mode, self.si, self.si.to_local(w), active)
        return self._mix((mi.Spectrum(0.0), pdf), w, active, True)[1]

    def sample(self, mode, u_lobe, u_dir, active):
        """(bs, weight, wo in world space) of sampling a direction here; a medium vertex
        fills bs with the phase function's sample (never delta, eta 1)."""
        bs, weight = self.bsdf.sample(mode, self.si, u_lobe, u_dir, active)
        wo = self.si.to_world(bs.wo)
        if not self.media:
            return bs, weight, wo
        on = active & self.in_medium
        mei = self.medium_interaction(self.wi_world())
        wo_m, w_m, pdf_m = self.medium.phase_function().sample(
            mi.PhaseFunctionContext(None), mei, u_lobe, u_dir, on)
        wo = dr.select(self.in_medium, wo_m, wo)
        bs.wo = dr.select(self.in_medium, self.si.to_local(wo_m), bs.wo)
        bs.pdf = dr.select(self.in_medium, pdf_m, bs.pdf)
        bs.eta = dr.select(self.in_medium, 1.0, bs.eta)
        bs.sampled_type = dr.select(self.in_medium, mi.UInt32(+mi.BSDFFlags.Smooth),
                                    bs.sampled_type)
        return bs, dr.select(self.in_medium, mi.Spectrum(w_m), weight), wo
