"""The ``vcm`` integrator plugin: vertex connection and merging.

``bdpt`` with ``merging`` on (Georgiev, Krivanek, Davidovic and Slusallek 2012): the
same engine, strategies and parameters, plus vertex merging.  Every camera surface
vertex that scatters smoothly also merges with the light vertices of its pass (all
N_L light subpaths) within a radius r, and the merges join the connections in one
MIS combination (bdpt_drjit/mis.py, merge.py).  Merging renders what no connection
can: specular-diffuse-specular paths, such as a caustic seen in a mirror.

It is *consistent, not unbiased*: a merge blurs over a disc of radius r, so the image
converges to the right answer only as the radius shrinks over passes (r_i = r_1
i^((alpha - 1) / 2) for pass i; ``radius_alpha`` 1 keeps it fixed and biased).  The
default ``bdpt`` has no merging and stays unbiased.  Medium vertices connect but do
not merge; spectral variants are refused (a light vertex's throughput holds its own
wavelengths).  Budgets: with ``light_paths``/``connections`` ``auto``, merging is one
more choice of the pilot's decision (bdpt_drjit/optimizer.py): kept where its moments
pay for its counted work (the SDS scene), left off where they do not (a diffuse box,
Veach's room), and then no pass after the pilot builds a grid or merges; with both
fixed, every pass merges.  ``strategy_subset`` ``ppm`` is progressive photon
mapping (merging alone, at each camera path's first smooth vertex).

{params}

Example::

    img = mi.render(scene, integrator=mi.load_dict({"type": "vcm", "max_depth": 8,
                                                    "radius": 0.01}), spp=64)

or ``<integrator type="vcm"><float name="radius" value="0.01"/></integrator>``.
"""
from __future__ import annotations

import mitsuba as mi

from bdpt_drjit.settings import rst_table

__doc__ = __doc__.replace("{params}", rst_table())

_CLASSES = {}


def integrator_class() -> type:
    """The ``vcm`` plugin class for the current Mitsuba variant."""
    from integrators.bdpt import _make_class
    variant = mi.variant()
    if variant not in _CLASSES:
        _CLASSES[variant] = _make_class(mi.SamplingIntegrator, {"merging": True}, __doc__,
                                        "VCMIntegrator")
    return _CLASSES[variant]


def register() -> None:
    """Register ``vcm`` for the current variant."""
    cls = integrator_class()
    mi.register_integrator("vcm", lambda props: cls(props))
