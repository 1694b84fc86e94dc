"""``bdpt_drjit.render``: one call that renders here (render.Renderer) or on Ray
workers (cluster.py).  It sits above both: render.py knows nothing of clusters and
cluster.py imports render.Renderer, so imports run one way (tests/test_layout.py)."""
from __future__ import annotations

import os

import mitsuba as mi

from . import support
from .render import Renderer, RenderResult


def render(scene, spp: int | None = None, seed: int = 0, sensor=0,
           strategy_images: bool = False, cluster: str | None = None,
           scene_params: dict | None = None, integrator: str = "bdpt",
           **settings) -> RenderResult:
    """Render ``scene`` (a ``mi.Scene`` or a path to an XML file) with BDPT.

    Keyword settings: see ``bdpt_drjit.settings.PARAMS`` (max_depth, rr_depth, mis,
    light_image, hide_emitters, technique, strategy_subset, samples_per_pass,
    memory_budget).  With ``strategy_images=True`` the result's
    ``strategy_images[(s, t)]`` holds every strategy's MIS-weighted image; they sum
    to ``image``.  ``scene_params``: the XML file's parameters ($name).
    ``cluster``: render the passes on Ray workers (``"local:N"``, ``"auto"`` or a Ray
    address; ``scene`` must then be a file path): the same estimator (cluster.py).
    ``integrator="pssmlt"``: Metropolis light transport over BDPT samples (mlt.py);
    ``integrator="mlt"``: multiplexed MLT, a strategy or a path length per chain
    (mmlt.py, needs a finite max_depth); ``spp`` is then the mean mutations per pixel,
    and their own settings are ``mlt.MLT_PARAMS`` (``mlt``: and ``mlt.MMLT_PARAMS``)
    with max_depth, rr_depth, mis, light_image, hide_emitters.
    """
    if integrator not in ("bdpt", "pssmlt", "mlt"):
        raise ValueError("bdpt: unknown integrator %r (bdpt, mlt or pssmlt)" % (integrator,))
    if integrator != "bdpt" and (cluster is not None or strategy_images):
        raise ValueError("%s: cluster rendering and strategy images are not supported "
                         "(a chain's records are its own)" % integrator)
    if cluster is not None:
        from .cluster import render_on_cluster
        return render_on_cluster(scene, cluster, spp=spp, seed=seed, sensor=sensor,
                                 strategy_images=strategy_images, scene_params=scene_params,
                                 **settings)
    if isinstance(scene, (str, os.PathLike)):
        scene = support.load_file(scene, **(scene_params or {}))
    elif scene_params:
        raise ValueError("bdpt: scene_params apply to a scene file, not to a loaded mi.Scene")
    if integrator != "bdpt":
        from . import mlt, mmlt
        if spp:
            settings["mutations_per_pixel"] = spp
        return (mmlt if integrator == "mlt" else mlt).render(scene, seed=seed, sensor=sensor,
                                                             **settings)
    r = Renderer(scene, sensor=sensor, spp=spp, seed=seed, strategy_images=strategy_images,
                 **settings)
    while not r.done:
        r.run_pass()
    return r.result()
