"""AOVs (arbitrary output variables) beside the image, as Mitsuba's ``aov`` integrator
writes them: albedo, normals and depth for a denoiser, and the rest of its list.

``aov`` cannot nest bdpt (it evaluates its inner integrator one camera ray at a time,
and bdpt's light image splats anywhere), so bdpt writes them itself: the ``aovs``
parameter takes ``aov``'s syntax, ``"name:type,name:type"``, and each AOV is the
average over a pixel's camera samples of what the camera ray's first surface shows,
filtered as the image is.  Channels follow the image's, named as ``aov`` names them
(``albedo.R``, ``nn.X``, ``dd.T``).  ``duv_dx``/``duv_dy`` need ray differentials,
which bdpt's camera rays do not carry: they are refused, naming the type.
``sh_normal`` is the surface's shading normal; Mitsuba 3.9.1's Python bindings lack
``BSDF::sh_frame``, so a ``normalmap`` or ``bumpmap`` does not tilt it (``aov`` does).
``shape_index`` is 1 + the place of the instance or shape hit in ``scene.shapes()``
(0: nothing), as ``aov`` writes it in scalar variants; its JIT variants write an
object id that depends on what else the process has loaded.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

# type -> the suffixes of its channels (Mitsuba's aov.cpp)
TYPES = {"albedo": "RGB", "depth": "T", "position": "XYZ", "uv": "UV", "geo_normal": "XYZ",
         "sh_normal": "XYZ", "dp_du": "XYZ", "dp_dv": "XYZ", "prim_index": "I",
         "shape_index": "I"}
REFUSED = {"duv_dx": "needs ray differentials, which bdpt's camera rays do not carry",
           "duv_dy": "needs ray differentials, which bdpt's camera rays do not carry"}


def parse(spec: str) -> list:
    """[(name, type)] from ``"name:type,..."``; an empty string is no AOVs."""
    out = []
    for token in (t.strip() for t in spec.split(",")):
        if not token:
            continue
        name, sep, kind = token.partition(":")
        if not sep or not name or not kind:
            raise ValueError("bdpt: aovs: %r is not a <name>:<type> pair" % token)
        if kind in REFUSED:
            raise ValueError("bdpt: aovs: type %r %s" % (kind, REFUSED[kind]))
        if kind not in TYPES:
            raise ValueError("bdpt: aovs: unknown type %r (choose one of %s)"
                             % (kind, ", ".join(TYPES)))
        out.append((name, kind))
    return out


def channel_names(aovs: list) -> list:
    return ["%s.%s" % (name, c) for name, kind in aovs for c in TYPES[kind]]


class AOVs:
    """The AOV values of a pass's camera rays."""

    def __init__(self, scene: mi.Scene, aovs: list):
        self.scene, self.aovs = scene, aovs
        # shape_index: 1 + the shape's place in scene.shapes(), 0 where nothing is hit
        # (as aov.cpp); a table from the shapes' registry ids to that number.
        shapes = scene.shapes()
        ids = [int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s))[0]) for s in shapes]
        table = [0] * (max(ids, default=0) + 1)
        for i, key in enumerate(ids):
            table[key] = i + 1
        self.shape_table = mi.UInt32(table)

    def values(self, ray: mi.Ray3f) -> list:
        """One Float per AOV channel, per camera ray."""
        si = self.scene.ray_intersect(ray, mi.RayFlags.All, True)
        valid = si.is_valid()
        bsdf = si.bsdf()
        out = []
        for _, kind in self.aovs:
            if kind == "albedo":
                v = _color(bsdf.eval_diffuse_reflectance(si, valid), ray.wavelengths, valid)
            elif kind == "depth":
                v = [si.t]
            elif kind == "sh_normal":
                v = si.sh_frame.n
            elif kind == "prim_index":
                v = [mi.Float(si.prim_index)]
            elif kind == "shape_index":
                hit = dr.select(si.instance != None, si.instance, si.shape)  # noqa: E711
                key = dr.reinterpret_array(mi.UInt32, hit)
                v = [mi.Float(dr.gather(mi.UInt32, self.shape_table, key, valid))]
            else:
                v = {"position": si.p, "uv": si.uv, "geo_normal": si.n, "dp_du": si.dp_du,
                     "dp_dv": si.dp_dv}[kind]
            out += [dr.select(valid, mi.Float(c), 0.0) for c in v]
        return out


def _color(spectrum, wavelengths, active) -> mi.Color3f:
    """An albedo as the RGB aov.cpp writes: the spectrum itself in RGB variants."""
    spectrum = mi.unpolarized_spectrum(spectrum)
    if mi.is_monochromatic:
        return mi.Color3f(spectrum[0])
    if mi.is_rgb:
        return mi.Color3f(spectrum)
    pdf = mi.pdf_rgb_spectrum(wavelengths)
    spectrum = spectrum * dr.select(pdf != 0, dr.rcp(pdf), 0.0)
    return mi.spectrum_to_srgb(spectrum, wavelengths, active)
