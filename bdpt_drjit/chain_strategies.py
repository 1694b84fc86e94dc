"""Per-lane strategy sets of the Markov chains (mmlt.py, mlt.py): a chain's one
strategy (MMLT), a path length, the lengths up to one (the separate direct samples),
or the lengths past one (PSSMLT's chains beside those direct samples)."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi


class ChainStrategies:
    """The render's StrategySet with one strategy (s, t) per lane (``set_lanes``):
    ``enabled``, ``stores`` and ``connects_at`` are masked per lane, and the walks stop
    at y_{s-1} and z_{t-1}; everything else (the MIS weights' strategy set among it:
    mis.Weights is built from the base) is the base's.  ``set_lanes(None, None)``:
    every strategy, as the base (the bootstrap's full BDPT samples); ``set_past(L)``:
    every strategy of more than L edges, full walks."""

    def __init__(self, base):
        self.base = base
        self.s = self.t = self.k = None
        self.up_to, self.past = False, 0

    def __getattr__(self, name):
        return getattr(self.base, name)

    def set_lanes(self, s, t) -> None:
        self.s, self.t = (None, None) if s is None else (mi.UInt32(s), mi.UInt32(t))
        self.k, self.up_to, self.past = None, False, 0
        dr.eval(self.s, self.t)

    def set_past(self, length: int) -> None:
        """Every strategy of more than ``length`` edges (0: every strategy)."""
        self.set_lanes(None, None)
        self.past = length

    def set_lengths(self, k, up_to: bool = False) -> None:
        """Every strategy of path length k per lane (``multiplex="length"``); with
        ``up_to``, of every length 1 .. k (the separate direct samples).  The walks
        stop at the same vertices for both."""
        self.s = self.t = None
        self.k, self.up_to, self.past = mi.UInt32(k), up_to, 0
        dr.eval(self.k)

    @property
    def per_lane(self) -> bool:
        return self.s is not None or self.k is not None

    def enabled(self, s, t):
        on = self.base.enabled(s, t)
        if self.k is not None:
            return on & ((s + t - 1 <= self.k) if self.up_to else (s + t - 1 == self.k))
        if self.s is None:
            return on & (s + t - 1 > self.past) if self.past else on
        return on & (self.s == s) & (self.t == t)

    def stores(self, s):
        on = self.base.stores(s)
        if self.k is not None:              # (s, t >= 2) of length k: s <= k - 1
            return on & (s + 1 <= self.k)
        return on if self.s is None else on & (self.s == s) & (self.t >= 2)

    def connects_at(self, t):
        if self.k is not None:              # s = k + 1 - t >= 2
            return t + 1 <= self.k
        return True if self.s is None else (self.t == t) & (self.s >= 2)

    def max_camera_vertices(self):
        """z_{t-1}, the lane's last camera vertex (0: no camera walk, t = 1); z_k for
        a length."""
        if self.k is not None:
            return mi.UInt32(self.k)
        return self.base.max_camera_vertices() if self.s is None else self.t - 1

    def max_light_vertices(self):
        """y_{s-1}, the lane's last light vertex (0: only y_0, drawn whatever s);
        y_{k-1} for a length."""
        if self.k is not None:
            return self.k - 1
        return self.base.max_light_vertices() if self.s is None else dr.maximum(self.s, 1) - 1
