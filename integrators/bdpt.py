"""The ``bdpt`` integrator plugin.

Bidirectional path tracer (Veach 1997, ch. 10; Lafortune & Willems 1993) that traces
camera and light subpaths as wavefronts and combines every (s, t) strategy with
multiple importance sampling.  s counts light-subpath vertices, t camera-subpath
vertices; a path of k = s + t - 1 edges can be made by up to k + 1 strategies:
s = 0 (a camera subpath hits an emitter), s = 1 (next-event estimation), t = 1
(light tracing, splatted onto the film: the "light image") and s, t >= 2 (a shadow
ray connects the two subpaths).  Light paths hitting the lens (t = 0) cannot occur
with the pinhole camera.

.. list-table::
   :header-rows: 1

   * - Parameter
     - Type
     - Description
   * - max_depth
     - integer
     - Longest path, in edges (1: emitters seen directly; 2: direct light).
       -1 = unbounded, ended by Russian roulette. (Default: -1)
   * - rr_depth
     - integer
     - Subpath vertex at which Russian roulette starts. (Default: 5)
   * - mis
     - string
     - MIS heuristic: ``power`` (exponent 2), ``balance``, ``uniform`` (all
       strategies that can make a path weigh the same) or ``lafortune``
       (Lafortune & Willems' specularity-based weights; no light image).
       (Default: power)
   * - light_image
     - boolean
     - Include the t = 1 (light tracing) strategies; without them MIS
       renormalizes over the rest. (Default: true)
   * - hide_emitters
     - boolean
     - Hide emitters seen directly by the camera. (Default: false)
   * - technique
     - string
     - Render a single strategy ``"s,t"`` without MIS weighting (for tests and
       for studying strategies). (Default: all strategies)
   * - strategies
     - string
     - ``all``; ``pt`` = only path tracing with next-event estimation (s <= 1),
       ``lt`` = only light tracing (t = 1): the same engine without MIS's other
       strategies, to show what they buy. (Default: all)
   * - samples_per_pass
     - integer
     - Samples per pixel per pass; 0 chooses it so the vertex buffers fit
       ``memory_budget`` (2 GiB). (Default: 0)

Supported: the ``perspective`` sensor; ``area``, ``point``, ``spot``, ``constant``,
``envmap`` and ``directional`` emitters; every Mitsuba BSDF.  Other sensors and
emitters (``orthographic``, ``projector``, ...) raise an error naming the plugin.

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

_PARAMS = {"max_depth": int, "rr_depth": int, "mis": str, "light_image": bool,
           "hide_emitters": bool, "technique": str, "strategies": str, "samples_per_pass": int,
           "memory_budget": int}


def _settings_from(props: mi.Properties) -> dict:
    settings = {}
    for key in props.keys():
        if key not in _PARAMS:
            raise ValueError("bdpt: unknown parameter '%s' (known: %s)"
                             % (key, ", ".join(sorted(_PARAMS))))
        settings[key] = _PARAMS[key](props[key])
    return settings


class BDPTIntegrator(mi.SamplingIntegrator):
    __doc__ = __doc__

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        from bdpt_drjit.render import Settings
        self.settings = _settings_from(props)
        Settings(**self.settings)          # fail at load time on bad values

    def render(self, scene: mi.Scene, sensor=0, seed: int = 0, spp: int = 0,
               develop: bool = True, evaluate: bool = True) -> mi.TensorXf:
        from bdpt_drjit.render import render
        if not develop:
            raise ValueError("bdpt: develop=False is not supported")
        with dr.suspend_grad():
            return render(scene, spp=spp or None, seed=int(seed), sensor=sensor,
                          **self.settings).tensor

    def aov_names(self):
        return []

    def to_string(self):
        return "BDPTIntegrator[%s]" % ", ".join("%s=%r" % kv for kv in self.settings.items())


def register() -> None:
    mi.register_integrator("bdpt", lambda props: BDPTIntegrator(props))
