"""Which (s, t) strategies a render evaluates, and where their contributions go.

One ``StrategySet`` is built from the settings and answers every question about
strategies: is (s, t) on (for Python ints, and inside kernels for Dr.Jit
integers, so a symbolic loop over depths needs no per-depth kernels), how many
vertices each subpath needs, which light vertices must be stored for
connections, and whether MIS weights are applied.  ``add`` accumulates a
contribution into the radiance and, on request, into its strategy image.

Notation (Veach's): s light-subpath vertices y_0..y_{s-1}, t camera-subpath
vertices z_0..z_{t-1}, path length k = s + t - 1 edges.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .budgets import BDPT, Budget
from .settings import Settings

# Strategy-image layers: one per (s, t) up to this path length, then one per k up
# to DEEP_K, then one for every longer path (an EXR reader's channel limit is 1024).
LAYER_K = 8
DEEP_K = 16
MERGE_LAYER = ("vm", 0)      # every merge (merge.py), whatever its path length


class StrategySet:
    """The strategies of one budget (budgets.py): no light image without light
    subpaths, no connections without connection budget."""

    def __init__(self, settings: Settings, has_emitters: bool, budget: Budget = BDPT,
                 light_image_possible: bool = True):
        self.settings = settings
        self.budget = budget
        self.max_depth = settings.max_depth
        self.technique = settings.technique
        self.subset = settings.strategy_subset
        self.light_image = (settings.light_image and light_image_possible
                            and budget.light_ratio > 0)
        self.connects = budget.connects
        # Paths with a smooth z_1 are the light image's alone (budgets.Budget).
        self.light_first_hits = budget.light_first_hits
        if self.light_first_hits and not self.light_image:
            raise ValueError("bdpt: a budget that leaves first hits to the light image needs "
                             "the light image (light_image = true and a camera a light "
                             "vertex can be connected to)")
        self.hide_emitters = settings.hide_emitters
        self.has_emitters = has_emitters
        # Vertex merging (merge.py): camera surface vertices merge with stored light
        # vertices y_i, i >= 1; "ppm" merges alone, at a camera path's first smooth vertex.
        self.merging = bool(settings.merging) and has_emitters and budget.merges
        self.ppm = self.subset == "ppm"

    # -- which strategies are on ---------------------------------------------------
    def enabled(self, s, t):
        """Is (s, t) evaluated?  ``s``/``t`` are Python ints or Dr.Jit integers."""
        if not self.has_emitters:
            return False
        k = s + t - 1
        conds = [k >= 1]
        if self.max_depth >= 0:
            conds.append(k <= self.max_depth)
        if self.technique is not None:
            conds += [s == self.technique[0], t == self.technique[1]]
        if self.subset == "pt":
            conds += [s <= 1, t >= 2]
        elif self.subset == "lt":
            conds.append(t == 1)
        elif self.subset == "ppm":          # emitters seen through delta lobes only
            conds.append(s == 0)
        if not self.light_image:
            conds.append(t >= 2)
        if not self.connects:
            conds.append((s <= 1) | (t <= 1))
        if self.hide_emitters:
            conds.append(k != 1)
        out = conds[0]
        for c in conds[1:]:
            out = out & c
        return out

    def connects_at(self, t):
        """Does camera vertex z_{t-1} connect to stored light vertices at all?  Every
        depth here; per lane for MMLT's chains (mmlt.ChainStrategies), so that a lane
        walks its list of stored vertices only at its own t."""
        return True

    @property
    def use_mis(self) -> bool:
        """MIS weights apply unless one strategy per path length is left."""
        return self.technique is None and self.subset not in ("lt", "ppm")

    def max_camera_vertices(self) -> int | None:
        """The deepest camera vertex z_j (j = t - 1) any strategy uses; None: unbounded.
        At least z_1, which tells the film's alpha."""
        if self.technique is not None:
            return max(self.technique[1] - 1, 1)
        if self.subset == "lt" or not self.has_emitters:
            return 1
        return None if self.max_depth < 0 else max(self.max_depth, 1)

    def max_light_vertices(self) -> int | None:
        """The deepest light vertex y_i (i = s - 1) any strategy uses; None: unbounded;
        -1: no light subpath at all."""
        if not self.has_emitters:
            return -1
        if self.technique is not None:
            s, t = self.technique
            return s - 1 if (s >= 2 or (s == 1 and t == 1)) else -1
        if self.subset == "pt" or self.budget.light_ratio <= 0:
            return -1
        if not (self.light_image or self.connects or self.merging):
            return -1
        if self.max_depth < 0:
            return None
        return self.max_depth - (1 if self.light_image or self.merging else 2)

    @property
    def stores_vertices(self) -> bool:
        """Does some strategy store a light vertex (``stores``)?  Else no pool for them."""
        if self.technique is not None:
            return self.technique[0] >= 2 and self.technique[1] >= 2
        return self.merging or (self.subset == "all" and self.connects)

    def stores(self, s):
        """Must light vertex y_{s-1} be stored: is some (s, t >= 2) on?"""
        if self.technique is not None:
            return (s == self.technique[0]) & (self.technique[1] >= 2) & (s >= 2)
        merged = self.merges(s - 1, 1)
        if self.subset != "all" or not self.connects:
            return merged
        connected = self.enabled(s, 2) & (s >= 2)
        return connected if merged is False else connected | merged

    def merges(self, i, j):
        """Can light vertex y_i merge with camera vertex z_j (a path of i + j edges;
        ints or Dr.Jit integers)?  y_0 (on the emitter) and z_0 (the camera) never do."""
        if not (self.merging and self.has_emitters):
            return False
        ok = (i >= 1) & (j >= 1)
        if self.max_depth >= 0:
            ok = ok & (i + j <= self.max_depth)
        return ok

    def add(self, images, radiance, lane, s, t, value):
        """radiance + value, and value into (s, t)'s strategy-image layer if ``images``."""
        if images is not None:
            images.add(lane, s, t, value)
        return type(radiance)(radiance + value)

    def add_merge(self, images, radius, lane, value):
        """radius + value of the merges at a camera vertex (into the "vm" layer if
        ``images``: merges of every path length together)."""
        if images is not None:
            images.add_layer(lane, images.merge_layer, value)
        return type(radius)(radius + value)

    # -- strategy images -------------------------------------------------------------
    def layers(self) -> list:
        """The strategy-image layers a render can fill: (s, t) pairs up to k = LAYER_K,
        then ("k", k) for each longer k up to DEEP_K, then ("k", DEEP_K + 1) for all
        longer paths."""
        top = self.max_depth if self.max_depth >= 0 else DEEP_K + 1
        out = [(s, k + 1 - s) for k in range(1, min(top, LAYER_K) + 1) for s in range(k + 1)
               if self.enabled(s, k + 1 - s)]
        out += [("k", k) for k in range(LAYER_K + 1, min(top, DEEP_K + 1) + 1)]
        return out + ([MERGE_LAYER] if self.merging else [])

    def layer_table(self) -> mi.Int32:
        """Layer index by (k, s): k * (LAYER_K + 1) + s for k <= LAYER_K, then
        (LAYER_K + 1)^2 + k - LAYER_K - 1 for the deep groups; -1 where none."""
        index = {layer: i for i, layer in enumerate(self.layers())}
        n = LAYER_K + 1
        table = [index.get((s, k + 1 - s), -1) for k in range(n) for s in range(n)]
        table += [index.get(("k", k), -1) for k in range(LAYER_K + 1, DEEP_K + 2)]
        return mi.Int32(table)

    @staticmethod
    def layer_slot(s, t):
        """Where (s, t) sits in ``layer_table`` (Dr.Jit integers)."""
        k = s + t - 1
        n = LAYER_K + 1
        return dr.select(k <= LAYER_K, k * n + dr.minimum(s, LAYER_K),
                         n * n + dr.minimum(k, DEEP_K + 1) - n)


class StrategyImages:
    """A pass's camera-side strategy-image values: one Spectrum per (layer, lane),
    written by the walks (each slot by its own lane, so no two adds race) and put
    on the film's layer blocks after the camera walk (film.put_camera)."""

    def __init__(self, strategies: StrategySet, lanes: int):
        self.table = strategies.layer_table()
        self.lanes = lanes
        layers = strategies.layers()
        self.values = dr.zeros(mi.Spectrum, lanes * len(layers))
        self._lanes = dr.opaque(mi.UInt32, lanes)
        self.merge_layer = layers.index(MERGE_LAYER) if MERGE_LAYER in layers else None

    def add_layer(self, lane, layer: int, value, active=True):
        dr.scatter_reduce(dr.ReduceOp.Add, self.values, value,
                          dr.opaque(mi.UInt32, layer) * self._lanes + lane, active)

    def add(self, lane, s, t, value):
        layer = dr.gather(mi.Int32, self.table, StrategySet.layer_slot(s, t))
        dr.scatter_reduce(dr.ReduceOp.Add, self.values, value,
                          mi.UInt32(layer) * self._lanes + lane, layer >= 0)

    def layer_of(self, s, t=1):
        return dr.gather(mi.Int32, self.table, StrategySet.layer_slot(s, t))
