"""Compaction of sparse work in a pass (pbrt-v4's wavefront queues, in two forms).

Deep vertices are sparse (Russian roulette), yet a masked lane still runs the
arithmetic of every connection.  Two remedies, neither of which changes a sample
(tests/test_options.py::test_compaction_changes_no_sample):

* the camera and light wavefronts are compacted to their live lanes (walk.py),
  drawing the samplers' numbers through ``Draws``;
* light vertices alive in few lanes become a list of (home lane, vertex) items
  (``SparseLights``), connected to the dense camera depths in one kernel each.
"""
from __future__ import annotations

from dataclasses import replace

import drjit as dr
import mitsuba as mi

from . import connect
from .records import Vertex, concat_vertices, gather_vertex

# Compact the camera wavefront to its live lanes once fewer than this fraction of
# its lanes are alive.  Deep vertices are sparse (Russian roulette), yet a masked
# lane still runs the arithmetic of every connection: with max_depth = -1 the
# Cornell box spent half its time on camera depths where ~1% of lanes lived.
COMPACT_BELOW = 0.25
MIN_LANES = 4096


class Draws:
    """The camera sampler's numbers for the lanes of the wavefront.  Once the
    wavefront is compacted, the numbers of a depth are drawn for all lanes in one
    kernel (``prefetch``) and gathered at the live ones, so a surviving lane sees the
    numbers it would see uncompacted (a lane's sequence advances whenever it is
    alive, in both cases)."""

    def __init__(self, sampler):
        self.sampler, self.lane, self.queue = sampler, None, []

    def prefetch(self, dims: list[int]) -> None:
        self.queue = [self.sampler.next_1d() if d == 1 else self.sampler.next_2d() for d in dims]
        self.sampler.schedule_state()
        dr.eval(self.queue)

    def next_1d(self, active=True):
        if self.lane is None:
            return self.sampler.next_1d(active)
        return dr.gather(mi.Float, self.queue.pop(0), self.lane)

    def next_2d(self, active=True):
        if self.lane is None:
            return self.sampler.next_2d(active)
        return dr.gather(mi.Point2f, self.queue.pop(0), self.lane)


_NO_ITEM = 0xFFFFFFFF


class SparseLights:
    """Light vertices alive in few lanes (fewer than ``COMPACT_BELOW``).  The light
    walk hands each such vertex over as soon as it is stored (``add``): its live
    lanes become (home lane, y_i) items and its full-width record is dropped, so
    memory stays bounded with max_depth = -1, where subpaths reach ~40 vertices.
    Dense camera depths connect to all items in one kernel (``connect_sparse``)
    instead of running masked full-width pairs; a compacted camera wavefront finds
    its lanes' items through ``map`` (home lane -> item, 4 bytes per lane and sparse
    vertex), in a symbolic loop over the sparse vertices (``connect_compacted``)."""

    def __init__(self, ctx, width: int):
        self.width = width
        self.on = (COMPACT_BELOW > 0 and width >= MIN_LANES
                   and not ctx.film.strategy_images)    # (those need a block per (s, t))
        self.indices: set[int] = set()   # i of the sparse light vertices
        self.lane = self.s = self.light = self.radiance = self.rays = None
        self.map = self.map_s = None     # K maps home lane -> item, and s = i + 1 of each
        self.map_end = None              # per home lane: 1 + the last k with an item
        self.groups: list[tuple[int, int]] = []          # (offset, count) per vertex
        self._parts, self._lanes, self._s, self._count = [], [], [], 0
        self._maps, self._map_s = [], []

    def add(self, i: int, vertex: Vertex, lane: mi.UInt32 | None = None) -> bool:
        """Take y_i (an evaluated record) if it is sparse; says whether it did.  A
        record of a compacted light wavefront (``lane``: its home lanes) is always
        taken."""
        if not self.on:
            return False
        n = dr.count(vertex.connectible)[0]
        if lane is None and n >= COMPACT_BELOW * self.width:
            return False
        self.indices.add(i)
        if n > 0:
            idx = dr.compress(vertex.connectible)
            part = gather_vertex(vertex, idx)
            home = idx if lane is None else dr.gather(mi.UInt32, lane, idx)
            item = dr.arange(mi.UInt32, n) + self._count
            m = dr.full(mi.UInt32, _NO_ITEM, self.width)
            dr.scatter(m, item, home)
            if self.map_end is None:
                self.map_end = dr.zeros(mi.UInt32, self.width)
            dr.scatter(self.map_end, dr.opaque(mi.UInt32, len(self._maps) + 1), home)
            dr.eval(part, home, m, self.map_end)
            self._maps.append(m)
            self._map_s.append(i + 1)
            self._parts.append(part)
            self._lanes.append(home)
            self._s.append(dr.full(mi.UInt32, i + 1, n))
            self.groups.append((self._count, n))
            self._count += n
        return True

    def finish(self) -> None:
        """One list of all items, after the light walk."""
        if self._parts:
            self.light = concat_vertices(self._parts)
            self.lane, self.s = dr.concat(self._lanes), dr.concat(self._s)
            self.radiance = dr.zeros(mi.Spectrum, self._count)
            self.rays = dr.zeros(mi.UInt32, self._count)
            self.map = dr.concat(self._maps) if len(self._maps) > 1 else self._maps[0]
            self.map_s = mi.UInt32(self._map_s)
            dr.eval(self.light, self.lane, self.s, self.radiance, self.rays, self.map, self.map_s)
        self._parts, self._lanes, self._s, self._maps = [], [], [], []

    def enabled(self, ctx, t: int) -> mi.Bool:
        """Per s = 0 .. max: is the strategy (s, t) enabled?  A table to gather from,
        so that kernels do not change with the set of sparse vertices."""
        top = max(self.indices, default=0) + 1          # the largest s = i + 1
        return mi.Bool([ctx.enabled(s, t) for s in range(top + 1)])


def connect_sparse(ctx, sparse: SparseLights, cam_record: Vertex, t: int) -> None:
    """s, t >= 2 between camera vertex z_{t-1} (``cam_record``, full width) and the
    sparse light vertices' items."""
    enabled = dr.gather(mi.Bool, sparse.enabled(ctx, t), sparse.s)
    light = replace(sparse.light, connectible=sparse.light.connectible & enabled)
    cam = gather_vertex(cam_record, sparse.lane)
    rays, ctx.rays = ctx.rays, sparse.rays
    sparse.radiance += connect.connect_vertices(ctx, light, cam, cam.si.bsdf())
    sparse.rays, ctx.rays = ctx.rays, rays
    dr.eval(sparse.radiance, sparse.rays)


def connect_compacted(ctx, sparse: SparseLights, cam: Vertex, bsdf, lane: mi.UInt32, t: int):
    """s, t >= 2 between the camera vertices z_{t-1} of a compacted wavefront (home
    lanes ``lane``) and their lanes' sparse light vertices.  A symbolic loop over the
    K sparse vertices: one connection in the kernel, however deep the light subpaths
    went (with max_depth = -1, K varies from render to render, and an unrolled loop
    gave kernels of ~8000 operations whose code generation alone took ~0.5 s per
    render).  Returns the radiance per lane."""
    if sparse.map is None:
        return dr.zeros(mi.Spectrum, dr.width(lane))
    enabled = sparse.enabled(ctx, t)
    # Most light subpaths end a few vertices after compaction: each lane loops only
    # over the sparse vertices up to its last item.
    count = dr.gather(mi.UInt32, sparse.map_end, lane, cam.connectible)
    width = dr.opaque(mi.UInt32, sparse.width)

    def body(k, radiance, rays):
        item = dr.gather(mi.UInt32, sparse.map, k * width + lane)
        s = dr.gather(mi.UInt32, sparse.map_s, k)
        ok = (item != _NO_ITEM) & dr.gather(mi.Bool, enabled, s)
        outer, ctx.rays = ctx.rays, rays
        radiance += connect.connect_vertices(ctx, gather_vertex(sparse.light, item, ok), cam, bsdf)
        rays, ctx.rays = ctx.rays, outer
        return k + 1, radiance, rays

    _, radiance, ctx.rays = dr.while_loop(
        (mi.UInt32(0), dr.zeros(mi.Spectrum, dr.width(lane)), mi.UInt32(ctx.rays)),
        lambda k, radiance, rays: k < count, body,
        labels=("k", "radiance", "rays"), label="connect_compacted")
    return radiance


def send_sparse_home(sparse: SparseLights, radiance, rays) -> None:
    """Add the items' radiance to their home lanes, one light vertex at a time: a
    lane appears once per vertex, so no two additions race (the image stays
    deterministic)."""
    for offset, n in sparse.groups:
        item = dr.arange(mi.UInt32, n) + offset
        dr.scatter_reduce(dr.ReduceOp.Add, radiance, dr.gather(mi.Spectrum, sparse.radiance, item),
                          dr.gather(mi.UInt32, sparse.lane, item))
        dr.eval(radiance)
    dr.scatter_reduce(dr.ReduceOp.Add, rays, sparse.rays, sparse.lane)
