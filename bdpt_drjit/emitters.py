"""Emitters as a BDPT sees them: where light subpaths start, and the pdfs MIS needs.

Mitsuba samples emitted rays but exposes no emission-direction pdf, so this module
models each supported emitter type (the issue's contract, Veach section 10.3):

=========  ==========================  ================================
type       position (pdf_pos, area)    direction (pdf_dir, solid angle)
=========  ==========================  ================================
area       uniform on its shape, 1/A   cosine hemisphere, cos / pi
point      delta (discrete, 1)         uniform sphere, 1 / (4 pi)
spot       delta (discrete, 1)         uniform cone, 1 / (2 pi (1 - cos_max))
=========  ==========================  ================================

Emitter selection uses Mitsuba's own pmf (``scene.sample_emitter``), so light paths
and next-event estimation agree on it.  Infinite emitters (constant, envmap,
directional) and the others are refused with an error naming the plugin.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

AREA, POINT, SPOT = 0, 1, 2
_KINDS = {"AreaLight": AREA, "PointLight": POINT, "SpotLight": SPOT}
_XML_NAMES = {"AreaLight": "area", "PointLight": "point", "SpotLight": "spot",
              "ConstantBackgroundEmitter": "constant", "EnvironmentMapEmitter": "envmap",
              "DirectionalEmitter": "directional", "Projector": "projector",
              "DirectionalArea": "directionalarea", "SkyEmitter": "sunsky",
              "PerspectiveCamera": "perspective", "OrthographicCamera": "orthographic",
              "ThinLensCamera": "thinlens", "RadianceMeter": "radiancemeter",
              "IrradianceMeter": "irradiancemeter", "BatchSensor": "batch",
              "DistantSensor": "distant"}


class UnsupportedPluginError(ValueError):
    """A scene uses a Mitsuba plugin that bdpt cannot render correctly (yet)."""


def plugin_name(obj) -> str:
    """The XML plugin name of a Mitsuba object, as well as we can tell."""
    cls = obj.class_name()
    return _XML_NAMES.get(cls, cls)


@dataclass
class EmissionSample:
    """Light vertex y_0 and the ray leaving it (one per lane)."""
    p: mi.Point3f
    n: mi.Normal3f          # emitter normal (area), spot axis (spot), 0 (point)
    uv: mi.Point2f
    d: mi.Vector3f          # emitted direction
    emitter: mi.EmitterPtr
    delta_pos: mi.Bool
    pos_pdf_a: mi.Float     # pmf * pdf_pos: density of y_0 when light paths start
    emission_pdf: mi.Float  # pos_pdf_a * pdf_dir(d)
    cos_emit: mi.Float      # |cos| at y_0 for area lights, 1 otherwise
    beta: mi.Spectrum       # Le(y_0, d) cos / emission_pdf: throughput leaving y_0
    valid: mi.Bool


class Emitters:
    """Per-scene tables of emitter type, area and cone, gathered by emitter index."""

    def __init__(self, scene: mi.Scene):
        self.scene = scene
        emitters = scene.emitters()
        self.count = len(emitters)
        kinds, inv_area, cos_cutoff = [], [], []
        for e in emitters:
            cls = e.class_name()
            if cls not in _KINDS:
                kind_word = ("infinite (environment/directional) emitters"
                             if mi.has_flag(e.flags(), mi.EmitterFlags.Infinite)
                             else "this emitter type")
                raise UnsupportedPluginError(
                    "bdpt: emitter plugin '%s' is not supported yet (%s cannot start "
                    "light subpaths here); supported emitters: area, point, spot"
                    % (plugin_name(e), kind_word))
            kind = _KINDS[cls]
            kinds.append(kind)
            shape = e.get_shape()
            area = shape.surface_area()[0] if kind == AREA else 1.0
            # A zero-area emitter emits nothing: pdf_pos 0 makes its light paths invalid.
            inv_area.append(1.0 / area if area > 0 else 0.0)
            cos_cutoff.append(self._spot_cos_cutoff(e) if kind == SPOT else -1.0)
        if self.count:
            self.ptrs = scene.emitters_dr()
            # Emitter pointers in a JIT variant are registry ids, not indices:
            # a table maps an id (e.g. from si.emitter(scene)) back to the index.
            ids = dr.reinterpret_array(mi.UInt32, self.ptrs).numpy().tolist()
            table = [0] * (max(ids) + 1)
            for index, ident in enumerate(ids):
                table[ident] = index
            self.index_of_id = mi.UInt32(table)
            self.kind = mi.UInt32(kinds)
            self.inv_area = mi.Float(inv_area)
            self.cos_cutoff = mi.Float(cos_cutoff)
            self.kinds_present = set(kinds)

    @staticmethod
    def _spot_cos_cutoff(e) -> float:
        """cos(cutoff angle) of a spot light, recovered from its own ray sampling.

        Mitsuba's spot samples a uniform cone, so weight = I(d) / pdf_cone; the
        intensity along that direction comes from ``eval_direction``.
        """
        ray, w = e.sample_ray(0.0, 0.5, mi.Point2f(0.5, 0.5), mi.Point2f(0.1, 0.0))
        it = dr.zeros(mi.Interaction3f)
        it.p = ray.o + ray.d
        ds = dr.zeros(mi.DirectionSample3f)
        ds.p, ds.d, ds.dist, ds.pdf, ds.delta = ray.o, -ray.d, 1.0, 1.0, True
        intensity = e.eval_direction(it, ds)
        pdf = intensity[0][0] / w[0][0]
        cos_max = 1.0 - 1.0 / (2.0 * math.pi * pdf)
        if not (-1.0 <= cos_max < 1.0):
            raise UnsupportedPluginError("bdpt: could not determine the cone of spot "
                                         "emitter %s" % e.id())
        return cos_max

    # -- lookups ----------------------------------------------------------------
    def index(self, emitter: mi.EmitterPtr, active=True) -> mi.UInt32:
        ident = dr.reinterpret_array(mi.UInt32, emitter)
        return dr.gather(mi.UInt32, self.index_of_id, ident, active)

    def pdf_direction(self, kind, cos_cutoff, n, d):
        """Emission-direction pdf (solid angle) of direction d leaving y_0.

        For a spot the cone pdf is constant wherever the spot emits at all, so no
        axis is needed (Mitsuba's direct-sampling records carry none)."""
        cone = dr.rcp(2.0 * dr.pi * (1.0 - cos_cutoff))
        return dr.select(kind == AREA, dr.maximum(dr.dot(n, d), 0.0) * dr.inv_pi,
                         dr.select(kind == SPOT, cone, 0.25 * dr.inv_pi))

    def emission_pdfs(self, emitter, n, d_out, active=True):
        """(pos_pdf_a, emission_pdf, cos_emit, delta_pos) of emitting along d_out
        from a point with normal n on ``emitter`` (pmf included)."""
        idx = self.index(emitter, active)
        kind = dr.gather(mi.UInt32, self.kind, idx, active)
        pos = (self.scene.pdf_emitter(idx, active)
               * dr.gather(mi.Float, self.inv_area, idx, active))
        cos_cut = dr.gather(mi.Float, self.cos_cutoff, idx, active)
        pdf_dir = self.pdf_direction(kind, cos_cut, n, d_out)
        is_area = kind == AREA
        cos_emit = dr.select(is_area, dr.abs(dr.dot(n, d_out)), 1.0)
        return pos, pos * pdf_dir, cos_emit, ~is_area

    def emitted(self, emitter, p, n, uv, d_out, delta_pos, wavelengths, time, active=True):
        """Radiance (area) or intensity (point, spot) leaving p along d_out.

        Uses ``eval_direction`` from a point at unit distance, which returns exactly
        these quantities for all three types (and 0 behind an area emitter).
        """
        it = dr.zeros(mi.Interaction3f)
        it.p = p + d_out
        it.time = time
        it.wavelengths = wavelengths
        ds = dr.zeros(mi.DirectionSample3f)
        ds.p, ds.n, ds.uv, ds.time = p, n, uv, time
        ds.d, ds.dist, ds.pdf, ds.delta = -d_out, 1.0, 1.0, delta_pos
        ds.emitter = emitter
        return emitter.eval_direction(it, ds, active)

    # -- sampling ---------------------------------------------------------------
    def sample_emission(self, time, wavelengths, u_sel, u_pos, u_dir, active=True) -> EmissionSample:
        """Start light subpaths: pick an emitter, a point y_0 and a direction."""
        scene = self.scene
        idx, _, _ = scene.sample_emitter(u_sel, active)
        pmf = scene.pdf_emitter(idx, active)
        emitter = dr.gather(mi.EmitterPtr, self.ptrs, idx, active)
        kind = dr.gather(mi.UInt32, self.kind, idx, active)
        cos_cut = dr.gather(mi.Float, self.cos_cutoff, idx, active)
        is_area = kind == AREA

        # Area lights: the shape's uniform position sampling, whose density 1/A is
        # also what the s = 0 and s = 1 weights assume for any point on the light.
        shape_ps = emitter.get_shape().sample_position(time, u_pos, active & is_area)
        delta_ps, _ = emitter.sample_position(time, u_pos, active & ~is_area)
        ps = dr.select(is_area, shape_ps, delta_ps)
        pos_pdf = pmf * dr.select(is_area, shape_ps.pdf, 1.0)

        frame = mi.Frame3f(dr.select(kind == POINT, mi.Vector3f(0, 0, 1), ps.n))
        local = dr.select(is_area, mi.warp.square_to_cosine_hemisphere(u_dir),
                          mi.warp.square_to_uniform_cone(u_dir, cos_cut))
        d = dr.select(kind == POINT, mi.warp.square_to_uniform_sphere(u_dir),
                      frame.to_world(local))
        pdf_dir = self.pdf_direction(kind, cos_cut, ps.n, d)
        emission_pdf = pos_pdf * pdf_dir
        cos_emit = dr.select(is_area, dr.abs(dr.dot(ps.n, d)), 1.0)
        le = self.emitted(emitter, ps.p, ps.n, ps.uv, d, ~is_area, wavelengths, time, active)
        beta = le * dr.select(emission_pdf > 0, cos_emit / emission_pdf, 0.0)
        valid = active & (emission_pdf > 0) & (dr.max(mi.unpolarized_spectrum(beta)) > 0)
        return EmissionSample(p=ps.p, n=ps.n, uv=ps.uv, d=d, emitter=emitter,
                              delta_pos=~is_area, pos_pdf_a=pos_pdf,
                              emission_pdf=emission_pdf, cos_emit=cos_emit,
                              beta=beta, valid=valid)

    def nee_pdf_a(self, ref: mi.Interaction3f, p, n, uv, emitter, delta_pos, time, active=True):
        """P_nee(y | ref) in area measure at y (pmf included) for a point y on an
        emitter; the pmf for delta-position emitters."""
        d = p - ref.p
        dist2 = dr.squared_norm(d)
        dist = dr.sqrt(dist2)
        ds = dr.zeros(mi.DirectionSample3f)
        ds.p, ds.n, ds.uv, ds.time = p, n, uv, time
        ds.d = d / dist
        ds.dist = dist
        ds.emitter = emitter
        pdf_w = self.scene.pdf_emitter_direction(ref, ds, active & ~delta_pos)
        pmf = self.scene.pdf_emitter(self.index(emitter, active), active)
        area = pdf_w * dr.abs(dr.dot(n, ds.d)) / dist2
        return dr.select(delta_pos, pmf, dr.select(dist2 > 0, area, 0.0))
