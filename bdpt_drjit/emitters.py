"""Emitters as a BDPT sees them: where light subpaths start, and the pdfs MIS needs.

Mitsuba samples emitted rays but exposes no emission-direction pdf, so this module
models each supported emitter type (the issue's contract, Veach section 10.3):

=========  ==========================  ================================
type       position (pdf_pos, area)    direction (pdf_dir, solid angle)
=========  ==========================  ================================
area       uniform on its shape, 1/A   cosine hemisphere, cos / pi
point      delta (discrete, 1)         uniform sphere, 1 / (4 pi)
spot       delta (discrete, 1)         uniform cone, 1 / (2 pi (1 - cos_max))
constant,  uniform on a disk of the    the emitter's own direction
envmap,    scene's bounding sphere     sampling (uniform sphere; the
sunsky     radius R facing the ray,    envmap's luminance; sun and sky),
           1 / (pi R^2)                Mitsuba's ``pdf_direction``
direc-     the same disk               delta (discrete, 1)
tional
projector  delta (discrete, 1)         the texture's density pdf_uv over
                                       its image, pdf_uv / (A cos^3)
=========  ==========================  ================================

Environment and directional emitters start light subpaths at infinity (VCM
technical report, section 5.1 "infinite lights"; SmallVCM's background and
directional lights): y_0 on the disk only places the ray, its "distance" to y_1
enters no pdf, and the camera strategies that would see it (s = 0 on a ray that
escapes) use solid-angle densities.  A directional light cannot be hit at all.
Emitter selection uses Mitsuba's own pmf (``scene.sample_emitter``), so light paths
and next-event estimation agree on it.  Which emitters are refused, and why, is
decided in support.py.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from .emitter_kinds import AREA, DIRECTIONAL, ENV, KINDS, POINT, PROJECTOR, SPOT
from .support import UnsupportedPluginError, plugin_name, scene_bbox


def is_delta_position(kind):
    return (kind == POINT) | (kind == SPOT) | (kind == PROJECTOR)


@dataclass
class EmissionSample:
    """Light vertex y_0 and the ray leaving it (one per lane)."""
    p: mi.Point3f
    n: mi.Normal3f          # emitter normal (area), spot axis (spot), 0 (point),
                            # the ray direction (environment: the disk's normal)
    uv: mi.Point2f
    d: mi.Vector3f          # emitted direction
    emitter: mi.EmitterPtr
    delta_pos: mi.Bool
    infinite: mi.Bool       # environment or directional: y_0 lies at infinity
    delta_dir: mi.Bool      # directional: a single direction
    pos_pdf_a: mi.Float     # pmf * pdf_pos: density of y_0 when light paths start
    emission_pdf: mi.Float  # pos_pdf_a * pdf_dir(d)
    cos_emit: mi.Float      # |cos| at y_0 for area lights, 1 otherwise
    beta: mi.Spectrum       # Le(y_0, d) cos / emission_pdf: throughput leaving y_0
    valid: mi.Bool


class ProjectorModel:
    """A ``projector``: a pinhole at p sending radiant intensity
    I(d) = pi scale E(uv) / cos^3 through the point uv of its texture E.

    uv is an affine function of the point (x/z, y/z) where the local direction
    meets the plane z = 1, so a density pdf_uv over [0,1]^2 is the solid-angle
    density pdf_uv / (A cos^3), A the area of the image on that plane.  Light
    subpaths draw uv from the texture's ``sample_position``, as Mitsuba's
    ``sample_ray`` does.  The affine map is read from the emitter's own
    ``sample_direction`` (which returns the uv of a point), so it is Mitsuba's."""

    def __init__(self, emitter):
        params = mi.traverse(emitter)
        self.texture = next(obj for obj, (_, depth) in params.hierarchy.items()
                            if depth == 1 and isinstance(obj, mi.Texture))
        # Texture sampling tables are built on first use: build them here, outside
        # any recorded loop.
        self.texture.sample_position(mi.Point2f(0.5), True)
        self.texture.pdf_position(mi.Point2f(0.5), True)
        self.to_world = mi.AffineTransform4f(params["to_world"])
        self.to_local = self.to_world.inverse()
        it = dr.zeros(mi.Interaction3f, 3)
        it.p = self.to_world @ mi.Point3f([0, 1, 0], [0, 0, 1], [1, 1, 1])
        ds, _ = emitter.sample_direction(it, mi.Point2f(0.5), True)
        uv = ds.uv.numpy().reshape(2, 3).tolist()
        b = [[uv[r][1] - uv[r][0], uv[r][2] - uv[r][0]] for r in (0, 1)]
        det = b[0][0] * b[1][1] - b[0][1] * b[1][0]
        self.uv0 = mi.Point2f(float(uv[0][0]), float(uv[1][0]))
        # uv = uv0 + bx x + by y, and its inverse (rows ix, iy)
        self.bx, self.by = mi.Vector2f(b[0][0], b[1][0]), mi.Vector2f(b[0][1], b[1][1])
        self.ix = mi.Vector2f(b[1][1] / det, -b[0][1] / det)
        self.iy = mi.Vector2f(-b[1][0] / det, b[0][0] / det)
        self.inv_image_area = mi.Float(abs(det))
        dr.make_opaque(self.to_world, self.to_local, self.uv0, self.bx, self.by, self.ix,
                       self.iy, self.inv_image_area)

    def uv(self, d):
        """(uv, cos theta, inside) of the world direction d."""
        local = dr.normalize(self.to_local @ d)
        uv = self.uv0 + self.bx * (local.x / local.z) + self.by * (local.y / local.z)
        inside = (local.z > 0) & dr.all((uv >= 0) & (uv <= 1))
        return uv, local.z, inside

    def pdf_w(self, d, active=True):
        uv, cos, inside = self.uv(d)
        active = active & inside
        pdf_uv = self.texture.pdf_position(uv, active)
        return dr.select(active, pdf_uv * self.inv_image_area / (cos * cos * cos), 0.0)

    def sample(self, u, active=True):
        """(world direction, uv), uv drawn as Mitsuba's sample_ray draws it."""
        uv, _ = self.texture.sample_position(u, active)
        du = uv - self.uv0
        d = dr.normalize(self.to_world @ mi.Vector3f(dr.dot(self.ix, du), dr.dot(self.iy, du), 1.0))
        return d, uv


class Emitters:
    """Per-scene tables of emitter type, area and cone, gathered by emitter index."""

    def __init__(self, scene: mi.Scene):
        self.scene = scene
        emitters = scene.emitters()
        # Environment light subpaths start on a disk just outside the scene's
        # bounding sphere (a little larger, so y_0 is never inside geometry).
        bsphere = scene_bbox(scene).bounding_sphere() if scene.shapes() else None
        self.env_center = mi.ScalarPoint3f(bsphere.center) if bsphere else mi.ScalarPoint3f(0)
        self.env_radius = max(float(bsphere.radius) * 1.01, 1e-3) if bsphere else 1.0
        self.count = len(emitters)
        kinds, inv_area, cos_cutoff = [], [], []
        self.kinds_present = set()
        # (index, shape) of textured area lights, (index, ProjectorModel) of projectors:
        # both are called directly, masked by emitter index (see sample_position).
        self.textured_area_shapes, self.projectors = [], []
        for index, e in enumerate(emitters):
            kind = KINDS.get(e.class_name())
            if kind is None:       # support.check refuses these first, with the reason
                raise UnsupportedPluginError("bdpt: emitter plugin '%s' is not supported"
                                             % plugin_name(e))
            kinds.append(kind)
            area = 1.0
            if kind == AREA:
                area = e.get_shape().surface_area()[0]
                if mi.has_flag(e.flags(), mi.EmitterFlags.SpatiallyVarying):
                    self.textured_area_shapes.append((index, e.get_shape()))
            elif kind in (ENV, DIRECTIONAL):
                area = math.pi * self.env_radius ** 2     # the disk y_0 starts on
            elif kind == PROJECTOR:
                self.projectors.append((index, ProjectorModel(e)))
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
        self.environment = scene.environment()      # at most one (Mitsuba's rule)

    @staticmethod
    def _spot_cos_cutoff(e) -> float:
        """cos(cutoff angle) of a spot light, from its ``cutoff_angle`` parameter (in
        degrees): not from its sampled rays' weights, which in spectral variants also
        hold the density of their wavelengths."""
        params = mi.traverse(e)
        if "cutoff_angle" not in params:
            raise UnsupportedPluginError("bdpt: spot emitter %s exposes no cutoff_angle"
                                         % e.id())
        angle = float(params["cutoff_angle"][0])
        return math.cos(math.radians(angle))

    # -- lookups ----------------------------------------------------------------
    def index(self, emitter: mi.EmitterPtr, active=True) -> mi.UInt32:
        ident = dr.reinterpret_array(mi.UInt32, emitter)
        return dr.gather(mi.UInt32, self.index_of_id, ident, active)

    def pdf_direction(self, emitter, idx, kind, cos_cutoff, n, d, active=True):
        """Emission-direction pdf (solid angle) of direction d leaving y_0.

        For a spot the cone pdf is constant wherever the spot emits at all, so no
        axis is needed (Mitsuba's direct-sampling records carry none).  For an
        environment it is the emitter's own density of the direction -d it comes
        from (pmf excluded); for a projector its texture's density (ProjectorModel)."""
        cone = dr.rcp(2.0 * dr.pi * (1.0 - cos_cutoff))
        pdf = dr.select(kind == AREA, dr.maximum(dr.dot(n, d), 0.0) * dr.inv_pi,
                        dr.select(kind == SPOT, cone, 0.25 * dr.inv_pi))
        pdf = dr.select(kind == DIRECTIONAL, 1.0, pdf)
        if ENV in self.kinds_present:
            is_env = active & (kind == ENV)
            it = dr.zeros(mi.Interaction3f)
            it.p = mi.Point3f(self.env_center)
            ds = dr.zeros(mi.DirectionSample3f)
            ds.d, ds.emitter = -d, emitter
            pdf = dr.select(is_env, emitter.pdf_direction(it, ds, is_env), pdf)
        for i, projector in self.projectors:
            on = active & (idx == i)
            pdf = dr.select(on, projector.pdf_w(d, on), pdf)
        return pdf

    def emission_pdfs(self, emitter, n, d_out, active=True):
        """(pos_pdf_a, emission_pdf, cos_emit, delta_pos) of emitting along d_out
        from a point with normal n on ``emitter`` (pmf included)."""
        idx = self.index(emitter, active)
        kind = dr.gather(mi.UInt32, self.kind, idx, active)
        pos = (self.scene.pdf_emitter(idx, active)
               * dr.gather(mi.Float, self.inv_area, idx, active))
        cos_cut = dr.gather(mi.Float, self.cos_cutoff, idx, active)
        pdf_dir = self.pdf_direction(emitter, idx, kind, cos_cut, n, d_out, active)
        is_area = kind == AREA
        cos_emit = dr.select(is_area, dr.abs(dr.dot(n, d_out)), 1.0)
        return pos, pos * pdf_dir, cos_emit, is_delta_position(kind)

    def emitted(self, emitter, p, n, uv, d_out, delta_pos, wavelengths, time, active=True):
        """Radiance (area) or intensity (point, spot, projector) leaving p along d_out.

        Uses ``eval_direction`` from a point at unit distance, which returns exactly
        these quantities for these types (and 0 behind an area emitter).  A
        projector reads its texture at ``uv``, which must be the uv of d_out
        (``ProjectorModel.uv``): Mitsuba's eval_direction does not recompute it.
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
    def sample_position(self, idx, emitter, time, u_pos, active=True) -> mi.PositionSample3f:
        """y_0 on the chosen emitter: uniform on an area light's shape (density 1/A,
        which the s = 0 and s = 1 weights assume for any point on the light), the
        emitter's own point for delta-position lights.

        One virtual call over the *emitters*: AreaLight::sample_position calls its own
        shape directly.  ``emitter.get_shape().sample_position`` traced the call for
        every shape Dr.Jit has registered (every scene alive in the process), and
        curves and instances have no position sampling: any scene with an area light
        and a curve or an instance failed with "Shape::sample_position(): not
        implemented!".  A textured area light would sample its texture instead, so
        its shape is called directly (masked) to keep 1/A; there are few of them."""
        textured = mi.Bool(False)
        for i, _ in self.textured_area_shapes:
            textured |= idx == i
        ps, _ = emitter.sample_position(time, u_pos, active & ~textured)
        for i, shape in self.textured_area_shapes:
            on = active & (idx == i)
            ps = dr.select(on, shape.sample_position(time, u_pos, on), ps)
        return ps

    def _sample_direction(self, idx, kind, cos_cut, ps, u_dir, active):
        """The direction leaving a finite y_0: cosine-weighted (area), uniform sphere
        (point), uniform cone (spot), the texture's own sampling (projector; ps.uv
        becomes the uv of the direction, which ``emitted`` reads)."""
        frame = mi.Frame3f(dr.select(kind == POINT, mi.Vector3f(0, 0, 1), ps.n))
        local = dr.select(kind == AREA, mi.warp.square_to_cosine_hemisphere(u_dir),
                          mi.warp.square_to_uniform_cone(u_dir, cos_cut))
        d = dr.select(kind == POINT, mi.warp.square_to_uniform_sphere(u_dir),
                      frame.to_world(local))
        for i, projector in self.projectors:
            on = active & (idx == i)
            d_i, uv_i = projector.sample(u_dir, on)
            d, ps.uv = dr.select(on, d_i, d), dr.select(on, uv_i, ps.uv)
        return d

    def _sample_infinite(self, emitter, kind, ps, d, time, wavelengths, u_pos, u_dir, active):
        """Environment and directional lights: the direction from the emitter's own
        sampling, then y_0 on the disk of radius R facing it, a distance R beyond the
        center.  Returns d and the directional light's irradiance."""
        is_inf = (kind == ENV) | (kind == DIRECTIONAL)
        it = dr.zeros(mi.Interaction3f)
        it.p, it.time, it.wavelengths = mi.Point3f(self.env_center), time, wavelengths
        ds_env, e_dir = emitter.sample_direction(it, u_dir, active & is_inf)
        disk = mi.warp.square_to_uniform_disk_concentric(u_pos) * self.env_radius
        towards = mi.Frame3f(ds_env.d)
        p_env = it.p + ds_env.d * self.env_radius + towards.s * disk.x + towards.t * disk.y
        d = dr.select(is_inf, -ds_env.d, d)
        ps.p = dr.select(is_inf, p_env, ps.p)
        ps.n = dr.select(is_inf, d, ps.n)
        ps.uv = dr.select(is_inf, 0.0, ps.uv)
        return d, e_dir

    def sample_emission(self, time, wavelengths, u_sel, u_pos, u_dir, active=True) -> EmissionSample:
        """Start light subpaths: pick an emitter, a point y_0 and a direction."""
        scene = self.scene
        idx, _, _ = scene.sample_emitter(u_sel, active)
        pmf = scene.pdf_emitter(idx, active)
        emitter = dr.gather(mi.EmitterPtr, self.ptrs, idx, active)
        kind = dr.gather(mi.UInt32, self.kind, idx, active)
        cos_cut = dr.gather(mi.Float, self.cos_cutoff, idx, active)
        ps = self.sample_position(idx, emitter, time, u_pos, active)
        # pmf x (1/A on an area light, 1 at a delta position, 1/(pi R^2) on the disk)
        pos_pdf = pmf * dr.gather(mi.Float, self.inv_area, idx, active)
        d = self._sample_direction(idx, kind, cos_cut, ps, u_dir, active)
        is_delta = is_delta_position(kind)
        is_env, is_dir = kind == ENV, kind == DIRECTIONAL
        if self.kinds_present & {ENV, DIRECTIONAL}:
            d, e_dir = self._sample_infinite(emitter, kind, ps, d, time, wavelengths,
                                             u_pos, u_dir, active)
        pdf_dir = self.pdf_direction(emitter, idx, kind, cos_cut, ps.n, d, active)
        emission_pdf = pos_pdf * pdf_dir
        cos_emit = dr.select(kind == AREA, dr.abs(dr.dot(ps.n, d)), 1.0)
        le = self.emitted(emitter, ps.p, ps.n, ps.uv, d, is_delta, wavelengths, time,
                          active & ~is_env)
        if ENV in self.kinds_present:
            le = dr.select(is_env, self.environment_radiance(emitter, d, wavelengths, time,
                                                             active & is_env), le)
        if DIRECTIONAL in self.kinds_present:
            le = dr.select(is_dir, e_dir, le)      # irradiance (its direction pdf is 1)
        beta = le * dr.select(emission_pdf > 0, cos_emit / emission_pdf, 0.0)
        valid = active & (emission_pdf > 0) & (dr.max(mi.unpolarized_spectrum(beta)) > 0)
        return EmissionSample(p=ps.p, n=ps.n, uv=ps.uv, d=d, emitter=emitter,
                              delta_pos=is_delta, infinite=is_env | is_dir, delta_dir=is_dir,
                              pos_pdf_a=pos_pdf, emission_pdf=emission_pdf, cos_emit=cos_emit,
                              beta=beta, valid=valid)

    @staticmethod
    def environment_radiance(emitter, d, wavelengths, time, active=True):
        """Radiance an environment emitter sends along direction d (travelling away
        from it), i.e. what a ray escaping along -d sees."""
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.wi, si.wavelengths, si.time = d, wavelengths, time
        return emitter.eval(si, active)

    def environment_nee_pdf_w(self, emitter, ref: mi.Interaction3f, d_escape, active=True):
        """The solid-angle density with which next-event estimation from ``ref`` picks
        the direction ``d_escape`` toward an environment or directional emitter (pmf
        included; a directional light's one direction is picked with its pmf alone)."""
        ds = dr.zeros(mi.DirectionSample3f)
        ds.d, ds.emitter, ds.time = d_escape, emitter, ref.time
        nee = self.scene.pdf_emitter_direction(ref, ds, active)
        if DIRECTIONAL in self.kinds_present:
            is_dir = self.kind_of(emitter, active) == DIRECTIONAL
            pmf = self.scene.pdf_emitter(self.index(emitter, active), active)
            nee = dr.select(is_dir, pmf, nee)
        return nee

    def environment_pdfs(self, emitter, ref: mi.Interaction3f, d_escape, active=True):
        """(P_nee in solid angle, emission density) of an environment direction: see
        ``environment_nee_pdf_w``; the emission density is that of the ray coming
        back along ``d_escape``."""
        _, emission, _, _ = self.emission_pdfs(emitter, -d_escape, -d_escape, active)
        return self.environment_nee_pdf_w(emitter, ref, d_escape, active), emission

    def kind_of(self, emitter, active=True) -> mi.UInt32:
        return dr.gather(mi.UInt32, self.kind, self.index(emitter, active), active)

    def past_the_scene(self, p: mi.Point3f, d: mi.Vector3f) -> mi.Point3f:
        """A point along d from p (inside the scene) beyond its bounding sphere: where a
        shadow ray toward an environment or a directional light ends.  Mitsuba's own
        direction samples end 2 R from p with R from scene.bbox(), which leaves out
        merged meshes (support.scene_bbox)."""
        reach = dr.norm(p - mi.Point3f(self.env_center)) + self.env_radius
        return p + d * reach

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
