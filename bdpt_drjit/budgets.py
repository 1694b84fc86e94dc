"""Technique budgets: how many light subpaths and connections a pass spends.

A budget is the pair (N_L / N_C, connections per camera vertex):

* ``light_ratio``: light subpaths per camera sample.  0 is path tracing with
  next-event estimation (no light walk at all); camera sample i takes light subpath
  i mod N_L, so camera samples of one pixel never share a light subpath.
* ``connections``: ``"all"`` connects each camera vertex to every stored vertex of
  its light subpath (Veach's BDPT); a count M connects it to M vertices drawn from
  all the pass's stored light vertices (a light vertex cache, Davidovic et al.
  2014); 0 connects nothing (light tracing and path tracing, MIS'ed together).
* ``light_first_hits``: the light image alone renders every path whose first camera
  vertex z_1 scatters smoothly (or is an emitter seen directly); the camera walk
  goes past z_1 only through a delta lobe, where no light vertex can be connected
  to the camera.  This is light tracing (Mitsuba's ``ptracer``) made unbiased in any
  scene: whether z_1 is delta is a property of the path, so the strategies allowed
  to sample each path still have MIS weights that sum to one (mis.Weights).

Every budget is a valid MIS combination (mis.py's rates), so any sequence of
budgets gives an unbiased image.  With ``light_paths`` / ``connections`` left at
"auto", optimizer.py chooses the budget from a pilot pass.
"""
from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Budget:
    light_ratio: float = 1.0         # N_L / N_C
    connections: object = "all"      # "all" or a count M >= 0
    light_first_hits: bool = False   # smooth first camera vertices: light image only
    merging: bool | None = None      # vertex merging: None as the settings say (a fixed
                                     # budget); True / False: the optimizer's choice
    radius_scale: float = 1.0        # merging: the radius, times each pass's r_i
                                     # (merge.pass_radius; the optimizer's choice)

    def light_subpaths(self, camera_samples: int) -> int:
        """N_L for a pass of ``camera_samples`` lanes."""
        if self.light_ratio <= 0:
            return 0
        return max(1, int(round(self.light_ratio * camera_samples)))

    @property
    def connects(self) -> bool:
        return self.light_ratio > 0 and self.connections != 0

    @property
    def caches(self) -> bool:
        """Connections to vertices drawn from the pass's pool (a light vertex cache)."""
        return self.connects and self.connections != "all"

    def kappa(self, light_subpaths: int, stored_vertices: float) -> float:
        """The connection rate of mis.py: 1 for "all"; for M vertices drawn from a pool
        of V, the density of connecting a given stored vertex relative to "all":
        M N_L / V."""
        if not self.connects:
            return 0.0
        if self.connections == "all":
            return 1.0
        return self.connections * light_subpaths / max(stored_vertices, 1.0)

    def __str__(self) -> str:
        ratio = ("%g" % self.light_ratio) if not math.isnan(self.light_ratio) else "?"
        first = " first_hits=light_image" if self.light_first_hits else ""
        merging = "" if self.merging is None else " merging=%s" % ("on" if self.merging else "off")
        if self.merging and self.radius_scale != 1.0:
            merging += " radius=%gr" % self.radius_scale
        return "light_paths=%s connections=%s%s%s" % (ratio, self.connections, first, merging)

    @property
    def merges(self) -> bool:
        """Merging is on wherever the budget does not turn it off (and settings ask)."""
        return self.merging is not False and self.light_ratio > 0


BDPT = Budget(1.0, "all")
PATH_TRACING = Budget(0.0, 0)


def fixed_budget(settings) -> Budget | None:
    """The budget the settings fix, or None when the optimizer chooses."""
    if settings.technique is not None or settings.mis == "lafortune":
        return BDPT
    if settings.strategy_subset == "pt":
        return PATH_TRACING
    if settings.strategy_subset == "lt":
        return Budget(1.0, 0)
    if settings.strategy_subset == "ppm":      # merging alone: no connections
        return Budget(1.0, 0)
    if settings.light_paths == "auto" or settings.connections == "auto":
        return None
    return Budget(float(settings.light_paths), settings.connections,
                  settings.first_hits == "light_image")
