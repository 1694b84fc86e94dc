"""The ``bdpt`` integrator plugin.

Bidirectional path tracer (Veach 1997, ch. 10; Lafortune & Willems 1993) that traces
camera and light subpaths as wavefronts and combines every (s, t) strategy with
multiple importance sampling.  s counts light-subpath vertices, t camera-subpath
vertices; a path of k = s + t - 1 edges can be made by up to k + 1 strategies:
s = 0 (a camera subpath hits an emitter), s = 1 (next-event estimation), t = 1
(light tracing, splatted onto the film: the "light image") and s, t >= 2 (a shadow
ray connects the two subpaths).

Cameras:

* ``perspective``: a pinhole (principal point offsets included).  Light paths cannot
  hit it, so there is no t = 0 strategy.
* ``thinlens`` (depth of field): every strategy above, with exact MIS.  Camera
  subpaths start at the lens point of their aperture sample, and the light image
  connects each light vertex to a lens point drawn uniformly on the aperture; the
  lens's position density 1 / (pi r^2) is common to all these strategies and cancels
  from the weights.  A light subpath could hit the lens (t = 0); that strategy is
  left out, as in pbrt-v4, and the MIS weights treat the lens as unhittable, so the
  other strategies still sum to one (no light reaches the image through it alone).
* ``orthographic``: its direction is a delta, so no light vertex can be connected to
  it: there is no light image (t = 1) and MIS renormalizes over the other strategies,
  as with ``light_image`` false; light subpaths serve connections only, and the
  ``auto`` budget never spends light subpaths without connections.  Each camera ray
  starts at its own point on the film plane.  ``strategy_subset`` ``lt`` and the
  techniques (s,1) are refused.

Participating media (``homogeneous``, ``heterogeneous``; the phase functions
``isotropic``, ``hg``, ``rayleigh``, ``tabphase``, ``blendphase``): medium vertices on
both subpaths, drawn by free flights as Mitsuba's ``volpath`` draws them (null
collisions in heterogeneous media), take part in every strategy: next-event
estimation and the light image from a point in fog (the volumetric caustics that
``volpath`` cannot render), connections between any mix of surface and medium
vertices.  Every connection carries its transmittance (closed form; ratio tracking in
heterogeneous media); ``null`` surfaces are medium boundaries, not vertices, and
``max_depth`` counts scattering vertices as ``volpath`` does.  Homogeneous media enter
the MIS weights with exact distance densities; heterogeneous ones leave them out (the
weights must be a function of the path).  The camera's medium is the sensor's
``medium`` (checked against where its rays start); light subpaths start in the medium
an emitter declares, or that its shape's media say, or that surrounds it.

Vertex merging (``merging``; the ``vcm`` plugin is ``bdpt`` with it on,
``integrators/vcm.py``): every camera surface vertex that scatters smoothly also merges
with the pass's light vertices within ``radius``, one more set of MIS strategies.
Consistent, not unbiased (the radius shrinks over passes by ``radius_alpha``); without
it (the default) bdpt is unbiased.

{params}

Supported: the ``perspective``, ``thinlens`` and ``orthographic`` sensors; ``area``,
``point``, ``spot``, ``projector``, ``constant``, ``envmap``, ``sunsky`` and
``directional`` emitters; every Mitsuba BSDF and shape; the media above; ``hdrfilm``.
Other sensors, emitters and media (``radiancemeter``, ``directionalarea``, the ``sggx``
phase function, ...) and ``specfilm`` raise an error naming the plugin (``bdpt_drjit/support.py``; ``bdpt info
SCENE.xml`` lists every verdict).

Example::

    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    import bdpt_drjit
    scene = mi.load_file("scenes/cornell-box.xml")
    img = mi.render(scene, integrator=mi.load_dict({"type": "bdpt", "max_depth": 8}), spp=64)

or in XML (after ``import bdpt_drjit``)::

    <integrator type="bdpt"><integer name="max_depth" value="8"/></integrator>
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from bdpt_drjit.settings import PARAM, Settings, canonical_name, rst_table  # noqa: E402

__doc__ = __doc__.replace("{params}", rst_table())

# One class per Mitsuba variant: a class derives from the variant's own
# SamplingIntegrator, and mi.render refuses integrators of another variant.
_CLASSES = {}

NESTING_ERROR = ("bdpt: cannot be nested in another integrator (such as 'aov' or 'moment'): "
                 "it traces wavefronts of whole subpaths and splats light paths onto the "
                 "film, so it cannot evaluate one camera ray at a time; render with bdpt "
                 "directly")
GRADIENT_ERROR = ("bdpt: gradients are not supported (render_%s): bdpt renders images "
                  "only; differentiate with Mitsuba's 'prb' or 'direct_projective' integrators")


def _settings_from(props: mi.Properties) -> dict:
    """The plugin's properties as settings (current, renamed or Mitsuba 0.5 names)."""
    settings = {}
    for key in props.keys():
        name = canonical_name(key)
        kind = PARAM[name].kind
        settings[name] = props[key] if kind is not bool else bool(props[key])
    return settings


def seed_value(seed) -> int:
    """``seed`` as a Python int: Mitsuba passes an ``int`` or a ``mi.UInt32`` of size 1."""
    if dr.is_array_v(seed):
        if dr.width(seed) != 1:
            raise ValueError("bdpt: seed must be a single value, got an array of %d"
                             % dr.width(seed))
        return int(seed[0])
    return int(seed)


def _make_class(base: type, defaults: dict | None = None, doc: str = __doc__,
                name: str = "BDPTIntegrator") -> type:
    """The plugin class, derived from one variant's ``mi.SamplingIntegrator``;
    ``defaults``: settings it has unless the properties say otherwise (``vcm``'s
    merging)."""

    class BDPTIntegrator(base):
        def __init__(self, props: mi.Properties):
            super().__init__(props)
            self.settings = {**(defaults or {}), **_settings_from(props)}
            Settings(**self.settings)          # fail at load time on bad values

        def render(self, scene: mi.Scene, sensor=0, seed=0, spp: int = 0,
                   develop: bool = True, evaluate: bool = True) -> mi.TensorXf:
            from bdpt_drjit.api import render
            if not develop:
                raise ValueError("bdpt: develop=False is not supported")
            with dr.suspend_grad():
                return render(scene, spp=spp or None, seed=seed_value(seed), sensor=sensor,
                              **self.settings).tensor

        def sample(self, *args, **kwargs):
            # What integrators that nest another ('aov', 'moment') call per camera ray.
            raise NotImplementedError(NESTING_ERROR)

        def render_forward(self, *args, **kwargs):
            raise NotImplementedError(GRADIENT_ERROR % "forward")

        def render_backward(self, *args, **kwargs):
            raise NotImplementedError(GRADIENT_ERROR % "backward")

        def aov_names(self):
            from bdpt_drjit import aovs
            return aovs.channel_names(aovs.parse(self.settings.get("aovs", "")))

        def to_string(self):
            return "%s[%s]" % (name, ", ".join("%s=%r" % kv for kv in self.settings.items()))

    BDPTIntegrator.__doc__ = doc
    BDPTIntegrator.__name__ = BDPTIntegrator.__qualname__ = name
    return BDPTIntegrator


def integrator_class() -> type:
    """The plugin class for the current Mitsuba variant."""
    variant = mi.variant()
    if variant not in _CLASSES:
        _CLASSES[variant] = _make_class(mi.SamplingIntegrator)
    return _CLASSES[variant]


def __getattr__(name):
    if name == "BDPTIntegrator":           # the class of the current variant
        return integrator_class()
    raise AttributeError("module %r has no attribute %r" % (__name__, name))


def register() -> None:
    """Register ``bdpt`` (and ``vcm``, integrators/vcm.py) for the current variant."""
    cls = integrator_class()
    mi.register_integrator("bdpt", lambda props: cls(props))
    from integrators.vcm import register as register_vcm
    register_vcm()
