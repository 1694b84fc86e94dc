"""The ``mlt`` integrator plugin: multiplexed Metropolis light transport (MMLT,
Hachisuka, Kaplanyan and Dachsbacher 2014) over this package's BDPT, as pbrt's
``mlt`` (bdpt_drjit/mmlt.py); ``pssmlt`` is its primary-sample-space sibling whose
chains evaluate every strategy.

Thousands of Markov chains run side by side, one per lane of the wavefront.  Each
chain has a path length k (edges), fixed for its life, and its state is three
streams of primary samples: the camera subpath's, the light subpath's, and one number
that picks the strategy (s, t) among the k + 1 of that length.  Its path sample
evaluates that one strategy, with its MIS weight over all strategies of the path
(as a BDPT sample weighs it), times k + 1; the walks stop at the strategy's last
vertices, so a mutation costs a fraction of a BDPT sample.  Each iteration proposes a
large step (all numbers redrawn) with probability ``large_step_probability``, else
Kelemen's small step on every stored number; both states are splatted with Veach's
expected-value weights and the proposal is accepted with min(1, f(y)/f(x)).  A
bootstrap of ``bootstrap_samples`` independent samples, split evenly over the path
lengths 1 .. max_depth, estimates each length's brightness b_k, and draws the chains'
first states, and so their lengths, in proportion to f (pbrt's bootstrap per depth).

The sample count (``spp`` of ``mi.render``, else the sensor's sampler) is the mean
number of mutations per pixel unless ``mutations_per_pixel`` is given.  ``max_depth``
must be finite (the chains run per path length).  Refused: spectral and monochrome
variants, heterogeneous media, ``mis=lafortune``, and the BDPT budget parameters.

.. list-table::
   :header-rows: 1

   * - Parameter
     - Description
   * - mutations_per_pixel
     - Mean mutations per pixel; ``spp`` of ``mi.render`` overrides it (Default: 0, the
       sensor's sample count)
   * - large_step_probability
     - Probability of a large step; -1 = automatic: 0.1 with ``multiplex`` ``strategy``
       (its large steps are rarely accepted), 0.3 with ``length`` (as pbrt and
       ``pssmlt``) (Default: -1; Mitsuba 0.6: ``pLarge``)
   * - bootstrap_samples
     - Independent samples, over all path lengths, that estimate each b_k and seed the
       chains; 0 = max(100000, 8 x chains) (Default: 0; Mitsuba 0.6:
       ``luminanceSamples``; pbrt's ``bootstrapsamples`` counts per length)
   * - large_step_mis
     - Weight large-step proposals also as independent samples (Kelemen 2002's MIS)
       (Default: true)
   * - chains
     - Markov chains (lanes); 0 = min(262144, max(4096, mutations / 16)), at
       most 2x the bootstrap's effective sample size (Default: 0)
   * - multiplex
     - What a chain fixes besides its path length: ``strategy`` (its (s, t), from a
       stream of its own: Hachisuka 2014, pbrt), ``length`` (every strategy of its
       length, each with its MIS weight) or ``auto``: ``length`` where the bootstrap's
       strategies of the chains' lengths have an effective sample size of at least
       half its samples (an easy scene), else ``strategy`` (Default: auto)
   * - direct_samples
     - Paths of 1 and 2 edges (emitters seen directly, direct illumination) by this
       many independent BDPT samples per pixel per iteration, and the chains only on
       longer paths; 0 = automatic: chains x the bootstrap's share of those lengths in
       the brightness (a power of two, at least 1024) where that share is at least 25%,
       else none; -1 = none (Default: 0; Mitsuba 0.6: ``directSamples``, per pixel in
       all)
   * - two_stage
     - Two-stage MLT (Hoberock and Hart 2010): a first stage of independent samples
       (one per planned chain, at least 65536) estimates the image's brightness L on
       blocks of 8 x 8 pixels (smaller where its samples allow: at least 32 effective
       samples a block), and the chains' target is their luminance over L of the
       record's pixel, so that they spend their time evenly over dark and bright
       pixels (Default: true; Mitsuba 0.6: ``twoStage``)
   * - max_depth
     - Longest path in edges, finite (Default: none: must be given)
   * - rr_depth, mis, light_image, hide_emitters
     - As for ``bdpt``

Example::

    img = mi.render(scene, integrator=mi.load_dict({"type": "mlt", "max_depth": 8}),
                    spp=256)
"""
from __future__ import annotations

import mitsuba as mi

_CLASSES = {}


def integrator_class() -> type:
    """The ``mlt`` plugin class for the current Mitsuba variant."""
    from integrators.pssmlt import _make_class
    variant = mi.variant()
    if variant not in _CLASSES:
        _CLASSES[variant] = _make_class(mi.SamplingIntegrator, "mlt", __doc__, "MMLTIntegrator")
    return _CLASSES[variant]


def register() -> None:
    """Register ``mlt`` for the current variant."""
    cls = integrator_class()
    mi.register_integrator("mlt", lambda props: cls(props))
