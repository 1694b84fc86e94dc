"""Per-vertex records of the subpath walks (struct-of-arrays, one entry per lane).

Only light vertices are stored: camera vertices are connected to them inside the
camera walk, while their surface interaction is live.  A stored vertex keeps what
connections and MIS need: the parts of its SurfaceInteraction that BSDFs and
textures read (``compact_interaction``), the throughput up to it, and the two MIS
quantities of mis.py.  Storing the surface costs ~60 bytes more per vertex than
storing the ray and preliminary intersection, but rebuilding the interaction (a
virtual call over the scene's shapes) for every pair was the largest cost of a
connection kernel after its shadow ray.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi


def compact_interaction(si: mi.SurfaceInteraction3f) -> mi.SurfaceInteraction3f:
    """A copy of ``si`` holding only what BSDF evaluation reads: position, normals,
    shading frame and tangents (normal and bump maps), uv (textures), shape and
    primitive (mesh attributes, the BSDF pointer), wi, time and wavelengths.
    (Not the distance t: the record is never tested with ``is_valid``.)
    Curvature (dn_du, dn_dv) and ray differentials stay zero, as on every
    interaction of the walks (no ray differentials are traced)."""
    c = dr.zeros(mi.SurfaceInteraction3f)
    c.p, c.n, c.uv, c.sh_frame = si.p, si.n, si.uv, si.sh_frame
    c.dp_du, c.dp_dv, c.wi = si.dp_du, si.dp_dv, si.wi
    c.shape, c.instance, c.prim_index = si.shape, si.instance, si.prim_index
    c.time, c.wavelengths = si.time, si.wavelengths
    return c


@dataclass
class Vertex:
    """Subpath vertex z_j (camera) or y_i (light), i, j >= 1."""
    si: mi.SurfaceInteraction3f        # light vertices: compact_interaction(si)
    beta: mi.Spectrum                  # throughput from the subpath's start to here
    d_vcm: mi.Float                    # MIS recursion state (mis.py)
    d_vc: mi.Float
    connectible: mi.Bool               # exists and has a non-delta BSDF lobe
    lw: mi.Float = None                # camera vertices, mis="lafortune": prod of W before it


def gather_vertex(v: Vertex, index: mi.UInt32, active=True) -> Vertex:
    """The stored vertex of the lanes ``index`` (a compacted wavefront's home lanes).
    Only lanes where the vertex is connectible read its record: deep vertices are
    mostly dead, and each gathered field is a cache miss."""
    live = dr.gather(mi.Bool, v.connectible, index, active)
    return Vertex(si=dr.gather(mi.SurfaceInteraction3f, v.si, index, live),
                  beta=dr.gather(mi.Spectrum, v.beta, index, live),
                  d_vcm=dr.gather(mi.Float, v.d_vcm, index, live),
                  d_vc=dr.gather(mi.Float, v.d_vc, index, live),
                  connectible=live,
                  lw=None if v.lw is None else dr.gather(mi.Float, v.lw, index, live))


def _concat(parts):
    """Concatenate Dr.Jit values (arrays, nested arrays, structs) lane-wise."""
    x = parts[0]
    tp = type(x)
    if hasattr(tp, "DRJIT_STRUCT"):
        out = dr.zeros(tp)
        for name in tp.DRJIT_STRUCT:
            setattr(out, name, _concat([getattr(p, name) for p in parts]))
        return out
    if dr.depth_v(x) > 1:
        return tp(*[_concat([p[k] for p in parts]) for k in range(len(x))])
    return dr.concat(parts)


def concat_vertices(parts: list[Vertex]) -> Vertex:
    """The records of several vertex lists, one after the other."""
    return Vertex(si=_concat([v.si for v in parts]), beta=_concat([v.beta for v in parts]),
                  d_vcm=_concat([v.d_vcm for v in parts]), d_vc=_concat([v.d_vc for v in parts]),
                  connectible=_concat([v.connectible for v in parts]))


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
