"""The ``pssmlt`` integrator plugin: primary sample space Metropolis light transport
(Kelemen et al. 2002) over this package's BDPT, as Mitsuba 0.6's ``pssmlt`` with
its bidirectional option (bdpt_drjit/mlt.py).

Thousands of Markov chains run side by side, one per lane of the wavefront.  A
chain's state is a vector of primary samples (the random numbers of a camera
subpath and of a light subpath, two streams); its path sample is a full BDPT sample
(every (s,t) strategy with its MIS weight), whose records are the camera sample's
value and the light image's splats, and whose target is the sum of their
luminances.  Each iteration proposes a large step (all numbers redrawn) with
probability ``large_step_probability``, else a small step (Kelemen's exponential
perturbation of every stored number); both states are splatted with Veach's
expected-value weights, and the proposal is accepted with min(1, f(y)/f(x)).  A
bootstrap of ``bootstrap_samples`` independent BDPT samples estimates the image's
brightness b and draws the chains' first states in proportion to f.

The sample count (``spp`` of ``mi.render``, else the sensor's sampler) is the mean
number of mutations per pixel unless ``mutations_per_pixel`` is given, as in
Mitsuba 0.6.  A fixed budget of stored numbers (12 depths per subpath) is mutated
eagerly; deeper vertices draw fresh numbers at every evaluation (still exact, see
pss.py).  Refused: spectral and monochrome variants, heterogeneous media,
``mis=lafortune``, and the BDPT budget parameters (a chain's sample is one camera
sample and one light subpath).

.. list-table::
   :header-rows: 1

   * - Parameter
     - Description
   * - mutations_per_pixel
     - Mean mutations per pixel; ``spp`` of ``mi.render`` overrides it (Default: 0, the
       sensor's sample count)
   * - large_step_probability
     - Probability of a large step (Default: 0.3; Mitsuba 0.6: ``pLarge``)
   * - bootstrap_samples
     - Independent samples that estimate b and seed the chains; 0 = max(100000, 8 x
       chains) (Default: 0; Mitsuba 0.6: ``luminanceSamples``)
   * - large_step_mis
     - Weight large-step proposals also as independent samples (Kelemen 2002's MIS)
       (Default: true)
   * - chains
     - Markov chains (lanes); 0 = min(262144, max(4096, mutations / 16)), at
       most 2x the bootstrap's effective sample size (Default: 0)
   * - direct_samples
     - Paths of 1 and 2 edges (emitters seen directly, direct illumination) by this
       many independent BDPT samples per pixel per iteration, and the chains only on
       longer paths; 0 = automatic: chains x the bootstrap's share of those lengths in
       the brightness (a power of two, at least 1024) where that share is at least 25%,
       else none; -1 = none (Default: 0; Mitsuba 0.6: ``directSamples``, per pixel in
       all)
   * - max_depth, rr_depth, mis, light_image, hide_emitters
     - As for ``bdpt``
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from integrators.bdpt import GRADIENT_ERROR, NESTING_ERROR, seed_value

# Mitsuba 0.6's names of the same parameters.
LEGACY = {"pLarge": "large_step_probability", "luminanceSamples": "bootstrap_samples",
          "maxDepth": "max_depth", "rrDepth": "rr_depth", "hideEmitters": "hide_emitters",
          "lightImage": "light_image", "directSamples": "direct_samples"}
LEGACY_REFUSED = {
    "bidirectional": "the chains' samples are always BDPT samples",
}
_CLASSES = {}


def settings_from(props: mi.Properties, name: str = "pssmlt") -> dict:
    from bdpt_drjit import mlt
    out = {}
    for key in props.keys():
        if key == "twoStage" and name == "mlt":
            out["two_stage"] = props[key]
            continue
        if key == "twoStage":
            raise ValueError("%s: Mitsuba 0.6 parameter 'twoStage' has no equivalent: "
                             "two-stage MLT is the mlt integrator's (two_stage)" % name)
        if key in LEGACY_REFUSED:
            raise ValueError("%s: Mitsuba 0.6 parameter '%s' has no equivalent: %s"
                             % (name, key, LEGACY_REFUSED[key]))
        out[LEGACY.get(key, key)] = props[key]
    mlt.mlt_settings(out, name)            # fail at load time on bad values
    return out


def _make_class(base: type, name: str = "pssmlt", doc: str = __doc__,
                class_name: str = "PSSMLTIntegrator") -> type:
    """The plugin class of ``name``: pssmlt (mlt.render) or mlt (mmlt.render)."""
    def render_with(scene, **kwargs):
        from bdpt_drjit import mlt, mmlt
        return (mmlt.render if name == "mlt" else mlt.render)(scene, **kwargs)

    class MLTIntegrator(base):
        def __init__(self, props: mi.Properties):
            super().__init__(props)
            self.settings = settings_from(props, name)

        def render(self, scene: mi.Scene, sensor=0, seed=0, spp: int = 0,
                   develop: bool = True, evaluate: bool = True) -> mi.TensorXf:
            if not develop:
                raise ValueError("%s: develop=False is not supported" % name)
            settings = dict(self.settings)
            if spp:
                settings["mutations_per_pixel"] = spp
            with dr.suspend_grad():
                return render_with(scene, seed=seed_value(seed), sensor=sensor,
                                   **settings).tensor

        def sample(self, *args, **kwargs):
            raise NotImplementedError(NESTING_ERROR.replace("bdpt", name))

        def render_forward(self, *args, **kwargs):
            raise NotImplementedError(GRADIENT_ERROR.replace("bdpt", name) % "forward")

        def render_backward(self, *args, **kwargs):
            raise NotImplementedError(GRADIENT_ERROR.replace("bdpt", name) % "backward")

        def to_string(self):
            return "%s[%s]" % (class_name, ", ".join("%s=%r" % kv for kv in self.settings.items()))

    MLTIntegrator.__doc__ = doc
    MLTIntegrator.__name__ = MLTIntegrator.__qualname__ = class_name
    return MLTIntegrator


def register() -> None:
    """Register ``pssmlt`` for the current variant (``mlt``: integrators/mlt.py)."""
    variant = mi.variant()
    if variant not in _CLASSES:
        _CLASSES[variant] = _make_class(mi.SamplingIntegrator)
    cls = _CLASSES[variant]
    mi.register_integrator("pssmlt", lambda props: cls(props))
