"""What bdpt renders: a verdict for every element of a loaded scene.

``check`` is what ``Renderer.__init__`` runs: it raises the first refusal as
``UnsupportedPluginError`` naming the plugin, and warns of the rest.  ``bdpt info``
lists every verdict of the same ``inspect``, so that info and render cannot disagree.

A verdict is *supported*, *refused* with a reason the user can act on (content that
bdpt would otherwise ignore or get wrong: sensors it has no camera model for,
emitters it has no densities for, media it has no phase function model for), or
*supported with a warning* (the image is
right but differs from what a user may expect of Mitsuba's ``path``).  README's
"What is supported" says the same for every plugin Mitsuba 3.9.1 ships.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .emitter_kinds import AREA, KINDS, PROJECTOR

SUPPORTED, WARNING, REFUSED = "supported", "warning", "REFUSED"

# XML plugin names of Mitsuba 3.9.1's classes (class_name() -> the name in a scene file).
_XML_NAMES = {
    # emitters
    "AreaLight": "area", "PointLight": "point", "SpotLight": "spot",
    "ConstantBackgroundEmitter": "constant", "EnvironmentMapEmitter": "envmap",
    "DirectionalEmitter": "directional", "Projector": "projector",
    "DirectionalArea": "directionalarea", "SunskyEmitter": "sunsky",
    "TimedSunskyEmitter": "timed_sunsky",
    # sensors and films
    "PerspectiveCamera": "perspective", "OrthographicCamera": "orthographic",
    "ThinLensCamera": "thinlens", "RadianceMeter": "radiancemeter",
    "IrradianceMeter": "irradiancemeter", "BatchSensor": "batch",
    "DistantSensor": "distant", "HDRFilm": "hdrfilm", "SpecFilm": "specfilm",
    # shapes
    "OBJMesh": "obj", "PLYMesh": "ply", "SerializedMesh": "serialized", "Cube": "cube",
    "Rectangle": "rectangle", "Disk": "disk", "Sphere": "sphere", "Cylinder": "cylinder",
    "BSplineCurve": "bsplinecurve", "LinearCurve": "linearcurve", "Instance": "instance",
    "SDFGrid": "sdfgrid", "Ellipsoids": "ellipsoids", "EllipsoidsMesh": "ellipsoidsmesh",
    "BlenderMesh": "blender", "ShapeGroupPlugin": "shapegroup", "Mesh": "mesh",
    # BSDFs
    "SmoothDiffuse": "diffuse", "TwoSidedBRDF": "twosided", "SmoothDielectric": "dielectric",
    "ThinDielectric": "thindielectric", "RoughDielectric": "roughdielectric",
    "SmoothConductor": "conductor", "RoughConductor": "roughconductor",
    "SmoothPlastic": "plastic", "RoughPlastic": "roughplastic", "Principled": "principled",
    "PrincipledThinBSDF": "principledthin", "BlendBSDF": "blendbsdf", "MaskBSDF": "mask",
    "Null": "null", "NullBSDF": "null", "BumpMap": "bumpmap", "NormalMap": "normalmap",
    "Hair": "hair", "HairBSDF": "hair", "LinearPolarizer": "polarizer",
    "LinearRetarder": "retarder", "CircularPolarizer": "circular",
    "MeasuredBSDF": "measured", "MeasuredPolarized": "measured_polarized",
    "PolarizedPlastic": "pplastic",
    # media and phase functions
    "HomogeneousMedium": "homogeneous", "HeterogeneousMedium": "heterogeneous",
    "IsotropicPhaseFunction": "isotropic", "HGPhaseFunction": "hg",
    "RayleighPhaseFunction": "rayleigh", "TabulatedPhaseFunction": "tabphase",
    "BlendPhaseFunction": "blendphase", "SGGXPhaseFunction": "sggx",
}

# Media and phase functions media.py handles (Mitsuba class names).  The phase
# functions are symmetric functions of the angle, so a light subpath scatters with
# the same value and density as a camera subpath (the adjoint of surface.Vertex).
SUPPORTED_MEDIA = ("HomogeneousMedium", "HeterogeneousMedium")
SUPPORTED_PHASES = ("IsotropicPhaseFunction", "HGPhaseFunction", "RayleighPhaseFunction",
                    "TabulatedPhaseFunction", "BlendPhaseFunction")
# The cameras camera.py models exactly (Mitsuba class names).
SUPPORTED_SENSORS = ("PerspectiveCamera", "ThinLensCamera", "OrthographicCamera")
_FILM = ("bdpt's film stage puts samples and light-image splats as hdrfilm lays them out "
         "(Mitsuba's ImageBlock.put rejects a specfilm block: 'non-standard image block "
         "configuration'); use hdrfilm")
_EMITTERS = {
    "directionalarea": "it emits only along its shape's normal (a delta direction on a "
                       "surface): camera paths can never reach it and bdpt has no "
                       "strategy for it; render it with Mitsuba's ptracer",
    "timed_sunsky": "Mitsuba 3.9.1 cannot trace it in JIT variants (its own path fails on "
                    "it: 'jit_var_schedule(): not permitted'); use 'sunsky' at a fixed time",
}


class UnsupportedPluginError(ValueError):
    """A scene uses a Mitsuba plugin that bdpt cannot render correctly (yet)."""


@dataclass(frozen=True)
class Verdict:
    kind: str            # sensor, film, emitter, shape, medium, scene
    name: str            # the plugin and its id, e.g. "area 'lamp' on rectangle"
    status: str          # SUPPORTED, WARNING or REFUSED
    reason: str = ""
    plugin: str = ""     # the plugin a refusal names

    def message(self) -> str:
        if self.status == REFUSED:
            return "%s plugin '%s' is not supported (%s): %s" % (
                self.kind, self.plugin, self.name, self.reason)
        return "%s %s: %s" % (self.kind, self.name, self.reason)


def _refused(kind: str, obj, name: str, reason: str) -> Verdict:
    return Verdict(kind, name, REFUSED, reason, plugin_name(obj))


def plugin_name(obj) -> str:
    """The XML plugin name of a Mitsuba object, as well as we can tell."""
    cls = obj.class_name()
    return _XML_NAMES.get(cls, cls)


def describe(obj) -> str:
    """Plugin name and, if the scene file gave one, the id: "area 'lamp'"."""
    ident = obj.id()
    named = ident and not ident.startswith("_unnamed")
    return plugin_name(obj) + (" '%s'" % ident if named else "")


def inspect(scene: mi.Scene, sensor: mi.Sensor) -> list:
    """Every verdict about ``scene`` rendered through ``sensor``."""
    from .media import scene_media
    media = scene_media(scene, sensor)
    out = _sensor_verdicts(sensor) + _emitter_verdicts(scene)
    for shape in all_shapes(scene):
        out += _shape_verdicts(shape, bool(media))
    return out + _media_verdicts(scene, sensor, media)


@dataclass
class SceneFacts:
    """What a render reads of a scene before its first pass (``facts``)."""
    # Its parameters that are no Dr.Jit array, (name, repr): a dielectric's eta, a
    # sensor's clip planes, a shape's transform.  Mitsuba bakes them into the kernels
    # that call its plugins, so a render puts them in its passes' context
    # (render.PassContext), whose values key the frozen walks' recordings: an eta
    # changed between renders then records anew instead of replaying the old one.
    values: tuple
    verdicts: list          # ``inspect``'s
    path_drops_light: bool  # ``mitsuba_path_drops_light``


class _LastScene:
    """The facts of the last scene asked about, while its state is the same: a render
    of a 64x64 film spent 0.8-1.2 ms of its 26 inspecting a scene it had inspected
    before.  The state is every parameter a traversal shows, its Python values by
    repr and its Dr.Jit arrays and transforms by variable index (an update through
    ``mi.traverse`` puts new arrays in), so a scene edited between renders is
    inspected anew.  Scenes cannot be weakly referenced: the last one is held, as
    frozen.py's recordings hold theirs."""
    key: tuple = ()
    facts: SceneFacts | None = None


def facts(scene: mi.Scene, sensor: mi.Sensor) -> SceneFacts:
    """``scene``'s facts through ``sensor``, inspected anew where its state changed."""
    params = mi.traverse(scene)
    state, structs = [], []
    for name in params.keys():
        v = params[name]
        indices = dr.detail.collect_indices(v)
        if indices:         # Dr.Jit arrays, and transforms, which hold them
            state.append((name, tuple(indices)))
            if not dr.is_jit_v(v):
                structs.append(name)
        else:
            state.append((name, repr(v)))
    key = (scene, sensor, tuple(state))
    last = _LastScene
    if last.facts is None or key[0] is not last.key[0] or key[1] is not last.key[1] \
            or key[2] != last.key[2]:
        # A transform's repr reads every entry back, one sync each (288 for the glass
        # pane's 4 transforms, 1-3 ms): only here, where the state changed.
        values = dict(item for item in state if isinstance(item[1], str))
        values.update((name, repr(params[name])) for name in structs)
        out = SceneFacts(tuple(values.items()), inspect(scene, sensor),
                         mitsuba_path_drops_light(scene))
        if any(v.status == REFUSED for v in out.verdicts):
            # Not held: the render stops here, and a scene kept alive joins Dr.Jit's
            # virtual calls over every emitter and shape of the process (an area light
            # on an instance then failed another scene's light walk).
            last.facts, last.key = None, ()
            return out
        last.facts, last.key = out, key
    return last.facts


def check(scene: mi.Scene, sensor: mi.Sensor, verdicts: list | None = None) -> list:
    """Raise the first refusal; warn of every warning; return the verdicts (those
    given, else ``inspect``'s)."""
    verdicts = inspect(scene, sensor) if verdicts is None else verdicts
    for v in verdicts:
        if v.status == REFUSED:
            raise UnsupportedPluginError("bdpt: " + v.message())
    for v in verdicts:
        if v.status == WARNING:
            warnings.warn("bdpt: " + v.message(), stacklevel=3)
    return verdicts


def warn_of_light_tracing_paths(scene: mi.Scene, settings) -> None:
    """Without the light image (``light_image`` false, ``mis`` lafortune), a path from
    a point-like light through mirrors or glass to a surface the camera sees (a
    caustic of a point or spot light) has no strategy left: say so, where the scene has
    such a light and a BSDF with a delta lobe.  (``strategy_subset`` pt asks for path
    tracing, which misses them too, as Mitsuba's ``path`` does.)"""
    if settings.light_image or settings.strategy_subset == "pt":
        return
    lights = [e for e in scene.emitters()
              if mi.has_flag(e.flags(), mi.EmitterFlags.DeltaPosition)]
    delta = [s for s in all_shapes(scene) if s.bsdf() is not None
             and mi.has_flag(s.bsdf().flags(), mi.BSDFFlags.Delta)]
    if lights and delta:
        why = "mis='lafortune' has" if settings.mis == "lafortune" else "light_image is off:"
        warnings.warn("bdpt: %s no light image (t = 1), the only strategy for light from %s "
                      "reaching a surface the camera sees through %s (a caustic): that light "
                      "is missing from the image" % (why, describe(lights[0]),
                                                     describe(delta[0].bsdf())), stacklevel=3)


def sensor_refusal(sensor: mi.Sensor) -> str | None:
    """Why bdpt cannot render through ``sensor`` (None: it can)."""
    if sensor.class_name() in SUPPORTED_SENSORS:
        return None
    return ("it does not form an image bdpt can model (bdpt renders through 'perspective', "
            "'thinlens' and 'orthographic' cameras); use Mitsuba's path")


def all_shapes(scene: mi.Scene) -> list:
    """The scene's shapes, and those inside shape groups (which scene.shapes() hides
    behind their instances)."""
    shapes = list(scene.shapes())
    known = {id(s) for s in shapes}
    for obj in mi.traverse(scene).hierarchy:
        if isinstance(obj, mi.Shape) and id(obj) not in known:
            shapes.append(obj)
            known.add(id(obj))
    return shapes


def load_file(path, **params) -> mi.Scene:
    """A scene file as the API, the command line and a cluster's workers load it:
    without Mitsuba's merging of shapes that share a BSDF (``optimize=False``).  In
    Mitsuba 3.9 the merge orders the scene's shapes, and so ``scene.emitters()``,
    differently from process to process; an emitter is drawn by its place in that list
    (``scene.sample_emitter``), so one seed rendered different images in different
    processes (Veach's bidirectional room, two area lights: 4 of 16 processes drew
    them in the other order, Mitsuba's own ``path`` included)."""
    return mi.load_file(str(path), optimize=False, **params)


def scene_bbox(scene: mi.Scene) -> mi.ScalarBoundingBox3f:
    """The scene's bounding box, its merged meshes included: Mitsuba (3.9) merges shapes
    that share a BSDF into one mesh whose bbox() is invalid, and scene.bbox() then
    leaves it out (a floor and a wall with the same diffuse BSDF beside a sphere: the
    sphere's box alone, so a directional light's or an environment's light subpaths,
    which start on a disk that covers the box, missed the floor and the wall)."""
    box = mi.ScalarBoundingBox3f(scene.bbox())
    for shape in scene.shapes():
        if shape.bbox().valid() or not shape.is_mesh():
            continue
        p = np.array(mi.traverse(shape)["vertex_positions"], dtype=np.float64).reshape(-1, 3)
        if len(p):
            box.expand(mi.ScalarPoint3f(*p.min(axis=0)))
            box.expand(mi.ScalarPoint3f(*p.max(axis=0)))
    return box


def mitsuba_path_drops_light(scene: mi.Scene) -> bool:
    """Whether Mitsuba's ``path`` (3.9) loses light in this scene: it returns 0 for a
    path that never samples a non-null lobe at a surface (its ``valid_ray``), so what
    next-event estimation gathered at a surface that scatters and lets light pass (a
    mask, a blend with ``null``) is dropped when the null lobe is sampled there and the
    ray then escapes: a mask of opacity 0.5 over the void renders at 25% of its
    opaque brightness in ``path``, 50% in ``volpath`` and here."""
    for shape in all_shapes(scene):
        bsdf = shape.bsdf()
        if bsdf is not None and all(mi.has_flag(bsdf.flags(), flag)
                                    for flag in (mi.BSDFFlags.Null, mi.BSDFFlags.Smooth)):
            return True
    return False


# -- sensors -------------------------------------------------------------------------
def _sensor_verdicts(sensor) -> list:
    name = describe(sensor)
    refusal = sensor_refusal(sensor)
    out = [_refused("sensor", sensor, name, refusal) if refusal else Verdict("sensor", name, SUPPORTED)]
    film = sensor.film()
    name = "%s with %s filter, %s sampler" % (
        describe(film), film.rfilter().class_name(), sensor.sampler().class_name())
    if film.class_name() != "HDRFilm":
        out.append(_refused("film", film, name, _FILM))
    else:
        out.append(Verdict("film", name, SUPPORTED))
    return out


# -- emitters ------------------------------------------------------------------------
def _emitter_verdicts(scene) -> list:
    emitters = scene.emitters()
    if not emitters:
        return [Verdict("scene", "without emitters", WARNING,
                        "the scene has no emitters; the image is black")]
    out = []
    for e in emitters:
        out.append(_emitter_verdict(e))
    return out


def _emitter_verdict(e) -> Verdict:
    name, kind = describe(e), KINDS.get(e.class_name())
    if kind is None:
        return _refused("emitter", e, name, _EMITTERS.get(
            plugin_name(e), "bdpt has no model of its emission densities; use Mitsuba's path"))
    if kind == AREA:
        name += " on " + describe(e.get_shape())
        reason = _area_shape_refusal(e.get_shape())
        if reason:                # the shape is what cannot be: the refusal names it
            return _refused("shape", e.get_shape(), name, reason)
    if kind == PROJECTOR:
        reason = _projector_refusal(e)
        if reason:
            return _refused("emitter", e, name, reason)
    return Verdict("emitter", name, SUPPORTED)


def _area_shape_refusal(shape) -> str | None:
    """Light subpaths start uniformly on an area light's shape, density 1/A, and the
    MIS weights assume it: a shape without uniform position sampling cannot emit."""
    try:
        area = float(shape.surface_area()[0])
        u = mi.Point2f([0.1, 0.5, 0.9], [0.7, 0.2, 0.5])
        pdf = shape.sample_position(0.0, u).pdf.numpy()
    except RuntimeError:
        return ("it cannot carry an area emitter: light subpaths start on the emitter's "
                "surface and Mitsuba cannot sample points on a %s; put the emitter on a "
                "mesh, rectangle, disk, sphere or cylinder" % plugin_name(shape))
    if area > 0 and not np.allclose(pdf * area, 1.0, rtol=1e-3):
        return ("it cannot carry an area emitter: Mitsuba's position sampling on a %s is "
                "not uniform (density %s, 1/area %g), which bdpt's weights assume; put "
                "the emitter on a mesh"
                % (plugin_name(shape), pdf, 1.0 / area))
    return None


def _projector_refusal(e) -> str | None:
    """Mitsuba's projector emits inconsistently under a scaled to_world: sample_ray
    leaves the scale out, sample_direction squares it.  Only rigid frames are exact."""
    m = np.array(mi.traverse(e)["to_world"].matrix.numpy()).reshape(4, 4)[:3, :3]
    if not np.allclose(m.T @ m, np.eye(3), atol=1e-4):
        return ("its to_world scales or shears; Mitsuba's projector then emits different "
                "light in path and ptracer, so it has no right image: use lookat/rotate/translate")
    return None


# -- shapes ----------------------------------------------------------------------------
def _shape_verdicts(shape, media: bool) -> list:
    name = describe(shape)
    out = []
    bsdf = shape.bsdf()
    if bsdf is not None and shape.class_name() not in ("Instance", "ShapeGroupPlugin"):
        name += " with " + describe(bsdf)
        if mi.has_flag(bsdf.flags(), mi.BSDFFlags.Null) and not (
                media and bsdf.class_name() in ("Null", "NullBSDF")):
            out.append(Verdict("shape", name, WARNING, NULL_LOBE))
    if shape.is_mesh():
        fraction = reversed_normals(shape)
        if fraction > 0.5:
            out.append(Verdict("shape", name, WARNING, REVERSED_NORMALS % (100 * fraction)))
    if not out:
        out.append(Verdict("shape", name, SUPPORTED))
    return out


NULL_LOBE = ("its BSDF lets light pass through (a null lobe: null, mask, thindielectric, "
             "hair, polarizers): each pass counts as a bounce toward max_depth, as in "
             "Mitsuba's path (volpath does not count it), and no connection crosses it "
             "(more noise; light from a point, spot or directional light that crosses it "
             "before reaching a surface seen only through such a surface is missing, as in "
             "path); in a scene with media a 'null' BSDF is a medium boundary instead, "
             "crossed by connections and not counted")
REVERSED_NORMALS = ("its vertex normals oppose its triangle winding on %.0f%% of its area: "
                    "where shading and geometric normals disagree, bdpt gives light zero "
                    "weight (as Mitsuba's ptracer does; its path does not), so this mesh "
                    "renders much darker than in path; flip its winding or its normals")


# -- media ---------------------------------------------------------------------------
def _media_verdicts(scene, sensor, media: list) -> list:
    out = []
    for medium in media:
        name = "%s with %s phase function" % (describe(medium), describe(medium.phase_function()))
        if medium.class_name() not in SUPPORTED_MEDIA:
            out.append(_refused("medium", medium, name, "bdpt has no free-flight model for it "
                                "(it renders 'homogeneous' and 'heterogeneous'); use volpath"))
        elif medium.phase_function().class_name() not in SUPPORTED_PHASES:
            out.append(_refused("medium", medium.phase_function(), name,
                                "bdpt's light subpaths need a phase function that is "
                                "symmetric in its two directions (isotropic, hg, rayleigh, "
                                "tabphase, blendphase of those); use volpath"))
        else:
            out.append(Verdict("medium", name, SUPPORTED, MEDIUM_NOTE))
    if media:
        out += _medium_layout_verdicts(scene, sensor)
    return out


MEDIUM_NOTE = ("volumetric BDPT: medium vertices take part in every strategy; homogeneous "
               "media weight them with exact distance densities, heterogeneous ones leave "
               "distance densities out of the weights (media.py)")


def _medium_layout_verdicts(scene, sensor) -> list:
    """The camera must sit in its sensor's medium, and light from infinity cannot reach
    a scene inside an unbounded medium."""
    from .media import Media
    try:
        media = Media(scene, sensor)
    except ValueError as e:
        return [_refused("sensor", sensor, describe(sensor), str(e).replace("bdpt: ", ""))]
    if media.unbounded is None:
        return []
    out = []
    for e in scene.emitters():
        if e.is_environment() or e.class_name() == "DirectionalEmitter":
            out.append(_refused("emitter", e, describe(e),
                                "it lies at infinity, and the medium %s around the camera has "
                                "no boundary: no light from infinity crosses it (volpath lets "
                                "next-event rays through a finite distance and so disagrees "
                                "with its own escaping rays); bound the medium with a shape"
                                % describe(media.unbounded)))
    return out


def reversed_normals(mesh) -> float:
    """The fraction of a mesh's area whose interpolated vertex normals point against
    the normal of the triangle's winding (0 without vertex normals).  Computed where the
    mesh lives, in one kernel: NumPy over the buffers read back took 55 ms per render for
    half a million triangles."""
    if not mesh.has_vertex_normals() or mesh.face_count() == 0:
        return 0.0
    faces = mesh.faces_buffer()
    face = dr.arange(mi.UInt32, mesh.face_count())
    corner = [dr.gather(mi.UInt32, faces, 3 * face + k) for k in range(3)]

    def at(buffer, index):
        return mi.Vector3f(*(dr.gather(mi.Float, buffer, 3 * index + k) for k in range(3)))

    p = [at(mesh.vertex_positions_buffer(), i) for i in corner]
    winding = dr.cross(p[1] - p[0], p[2] - p[0])
    shading = sum(at(mesh.vertex_normals_buffer(), i) for i in corner)
    area = dr.norm(winding)
    against = dr.select(dr.dot(winding, shading) < 0, area, 0.0)
    total, reversed_area = dr.sum(area), dr.sum(against)
    dr.eval(total, reversed_area)
    total = float(total[0])
    return float(reversed_area[0]) / total if total > 0 else 0.0
