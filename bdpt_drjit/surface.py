"""What the walks and strategies need at a surface vertex: a compact record of it
(``SurfaceRecord``, stored for light vertices), cosines against the geometric
normal, the adjoint BSDF of light subpaths, and reverse densities.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi


@dataclass
class SurfaceRecord:
    """The part of a SurfaceInteraction3f that BSDF evaluation reads: position,
    normals, shading frame and tangents (normal and bump maps), uv (textures), shape
    and primitive (mesh attributes, the BSDF pointer) and wi.  Storing it costs ~60
    bytes more per light vertex than storing the ray and preliminary intersection,
    but rebuilding the interaction (a virtual call over the scene's shapes) for every
    connection was the largest cost of a connection after its shadow ray.  Curvature
    and ray differentials stay zero, as on every interaction of the walks."""
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

    @staticmethod
    def of(si: mi.SurfaceInteraction3f) -> "SurfaceRecord":
        return SurfaceRecord(p=si.p, n=si.n, uv=si.uv, sh_frame=si.sh_frame, dp_du=si.dp_du,
                             dp_dv=si.dp_dv, wi=si.wi, shape=si.shape, instance=si.instance,
                             prim_index=si.prim_index)

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
