"""Vertex merging (VCM's photon-mapping half): the pass's hash grid of light vertices,
the merge estimator at camera vertices, and the progressive radius.

Georgiev, Krivanek, Davidovic, Slusallek, "Light transport simulation with vertex
connection and merging" (2012) and its technical report ("Implementing Vertex
Connection and Merging", the tech. rep. of mis.py); SmallVCM's ``hashgrid.hxx`` and
``vertexcm.hxx`` (RangeQuery) are the reference implementation, rewritten here as
Dr.Jit arrays.

Merging at camera vertex z_j with stored light vertex y_i within radius r (a path of
i + j edges; surfaces only, y_0 and z_0 never) estimates (tech. rep. eq. 17 with a
constant kernel 1 / (pi r^2))

    C = beta_E(z_j) f_E(y_{i-1} <- z_j -> z_{j-1}) / |cos_g(z_j, w_y)| beta_L(y_i)
        / (pi r^2 N_L) * w_merge

over the N_L light subpaths of the pass: f_E is z_j's BSDF for the light's incoming
direction w_y (Mitsuba's ``eval`` holds the shading cosine; the geometric cosine of
the flux density divides it), beta_L the light subpath's throughput arriving at y_i.
It is consistent, not unbiased: the kernel blurs over the disc, and the radius
shrinks over passes, r_i = r_1 i^((alpha - 1) / 2) for pass i = 1, 2, ... (Knaus &
Zwicker 2011; SmallVCM's schedule), so the bias vanishes as passes grow.

The grid (SmallVCM's HashGrid, on the pool of stored light vertices, vertices.py):
cells of side 2r hashed into BUCKETS buckets per vertex the pool can hold; per bucket
a count (``dr.scatter_inc``, whose result is also each vertex's slot in its bucket),
an exclusive prefix sum, and the pool's items scattered into bucket order.  A query
reads the counts of the 8 cells that a sphere of radius r around z_j can touch, keeps
those within r of z_j that hold items (a mask), and visits their items in one
symbolic loop, one item per iteration; it keeps only items whose own cell is the one
visited: two of the 8 cells hashed into one bucket would otherwise count its items
twice (SmallVCM does), and a hash collision's foreign items are skipped before their
distance is read.
Radius, cell size, bucket count and normalization are opaque: no kernel is
compiled per pass or per radius.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from . import mis
from .strategies import StrategySet
from .support import scene_bbox
from .surface import finite, spectrum_nonzero
from .vertices import gather
from .optimizer import luminance

# The default first radius, in pixel footprints at the scene's centre.  SmallVCM's
# default, 0.003 x the scene's bounding-sphere radius, is about 1 of them in
# scenes/cornell-box.xml at 512x512 but 2 in benchmarks/scene_files/sds.xml (a floor far
# wider than the view); scaled to small films it made merging there 30x slower (a query
# visits every light vertex of 8 cells of side 2r).
RADIUS_PIXELS = 1.5
# Hash buckets per stored vertex the pool can hold.  A query visits every item of its
# cells' buckets, a hash collision's too (skipped only after its position is read):
# with one bucket per vertex (SmallVCM's), about 6 foreign items per query in the
# diffuse box's pilot, beside its 25 own ones at the default radius.
BUCKETS = 4
# Lanes of an automatic pass with merging (settings.samples_per_pass 0): the radius
# shrinks from pass to pass, so passes stay small (SmallVCM's are 1 spp).
PASS_LANES = 1 << 16


def first_radius(scene: mi.Scene, sensor: mi.Sensor, radius: float) -> float:
    """r_1: ``radius`` if set (> 0), else RADIUS_PIXELS pixel footprints at the
    distance of the scene's bounding-sphere centre from the camera (two rays through
    neighbouring pixels at the film's centre: any camera model)."""
    if radius > 0:
        return float(radius)
    sphere = scene_bbox(scene).bounding_sphere()
    centre = _vec(sphere.center)
    size = sensor.film().crop_size()
    points = []
    for dx in (0.0, 1.0):
        u = mi.Point2f((0.5 * size[0] + dx) / size[0], 0.5)
        ray, _ = sensor.sample_ray(0.0, 0.5, u, mi.Point2f(0.5))
        o, d = _vec(ray.o), _vec(ray.d)
        points.append(o + d * np.linalg.norm(centre - o))
    footprint = float(np.linalg.norm(points[1] - points[0]))
    scene_radius = float(_vec(sphere.radius)[0])
    return max(RADIUS_PIXELS * footprint, 1e-5 * scene_radius, 1e-7)


def _vec(v) -> np.ndarray:
    """A scalar or width-1 Dr.Jit value as a flat float64 NumPy array."""
    return np.ravel(np.array(v, dtype=np.float64))


def pass_radius(r1: float, alpha: float, index: int) -> float:
    """r_i = r_1 i^((alpha - 1) / 2) for the pass of 0-based ``index`` (i = index + 1)."""
    return r1 * float(index + 1) ** ((alpha - 1.0) / 2.0)


def _cell(p, inv_cell) -> mi.Vector3i:
    return mi.Vector3i(dr.floor(p * inv_cell))


def _bucket(cell: mi.Vector3i, buckets) -> mi.UInt32:
    """SmallVCM's spatial hash of a cell (Teschner et al. 2003's primes)."""
    c = mi.Vector3u(cell)
    return ((c.x * 73856093) ^ (c.y * 19349663) ^ (c.z * 83492791)) % buckets


@dataclass
class Photon:
    """What a merge reads of a stored light vertex y_i, copied in bucket order when
    the grid is built: a query then reads neighbouring records (one cell's), and 12
    values instead of the 22 of the vertex record it would otherwise gather."""
    w: mi.Vector3f          # toward y_{i-1} (world)
    beta: mi.Spectrum       # the light subpath's throughput arriving at y_i
    d_vcm: mi.Float         # MIS chains (mis.py)
    d_vc: mi.Float
    s: mi.UInt32            # i + 1
    d_end: mi.Float = None  # moment passes: the chain's far end, its merge part (mis.py)
    d_vm: mi.Float = None


@dataclass
class HashGrid:
    """The pass's light vertices in cells of side 2r (see the module docstring)."""
    order: mi.UInt32        # pool items, bucket after bucket
    start: mi.UInt32        # per bucket: its first position in ``order``
    count: mi.UInt32        # per bucket: its items
    inv_cell: mi.Float      # 1 / (2 r)
    radius2: mi.Float       # r^2
    buckets: mi.UInt32      # the bucket count
    norm: mi.Float          # 1 / (pi r^2 N_L)
    points: mi.Point3f = None   # positions in bucket order
    photons: Photon = None      # merge records in bucket order (render passes)

    @staticmethod
    def build(store, radius: float, light_subpaths: int, photons: bool = True,
              shares: bool = False) -> "HashGrid":
        """The grid of ``store``'s vertices (vertices.LightVertexStore's pool) at radius r;
        ``photons``: also copy their merge records (``Photon``) in bucket order, with
        ``shares`` (a moment pass) the chains' ends and merge parts too."""
        items = store.vertices.items
        capacity = store.vertices.capacity
        index = dr.arange(mi.UInt32, capacity)
        size = dr.gather(mi.UInt32, store.vertices.count, dr.zeros(mi.UInt32, capacity))
        # Every stored vertex that can merge: in the pool, on a surface.
        ok = (index < dr.minimum(size, capacity)) & ~items.record.in_medium
        buckets = dr.opaque(mi.UInt32, BUCKETS * capacity)
        inv_cell = dr.opaque(mi.Float, 0.5 / radius)
        bucket = _bucket(_cell(items.record.p, inv_cell), buckets)
        count = dr.zeros(mi.UInt32, BUCKETS * capacity)
        slot = dr.scatter_inc(count, bucket, ok)
        dr.eval(slot, count)            # the counter's results, in the kernel that counts
        start = dr.prefix_sum(count)    # exclusive
        order = dr.zeros(mi.UInt32, capacity)
        dr.scatter(order, index, dr.gather(mi.UInt32, start, bucket, ok) + slot, ok)
        dr.eval(order)
        grid = HashGrid(order=order, start=start, count=count, inv_cell=inv_cell,
                        radius2=dr.opaque(mi.Float, radius * radius), buckets=buckets,
                        norm=dr.opaque(mi.Float, 1.0 / (math.pi * radius * radius
                                                        * max(light_subpaths, 1))),
                        points=dr.gather(mi.Point3f, items.record.p, order))
        if photons:
            rec = gather(items.record, order)
            grid.photons = Photon(w=rec.sh_frame.to_world(rec.wi),
                                  beta=dr.gather(type(items.beta), items.beta, order),
                                  d_vcm=dr.gather(mi.Float, items.d_vcm, order),
                                  d_vc=dr.gather(mi.Float, items.d_vc, order),
                                  s=dr.gather(mi.UInt32, items.s, order))
            if shares:
                grid.photons.d_end = dr.gather(mi.Float, items.d_end, order)
                grid.photons.d_vm = dr.gather(mi.Float, items.d_vm, order)
        dr.eval(grid.start, grid.points, grid.photons)
        return grid

    def neighbour(self, cell: mi.Vector3i, away: mi.Vector3i, k) -> mi.Vector3i:
        """The k-th of the 8 cells a sphere of radius r around a point of ``cell`` can
        touch: bit 2, 1, 0 of k step x, y, z toward the nearer neighbour (``away``)."""
        k = mi.UInt32(k)
        return cell + mi.Vector3i(dr.select((k & 4) != 0, away.x, 0),
                                  dr.select((k & 2) != 0, away.y, 0),
                                  dr.select((k & 1) != 0, away.z, 0))


def _near(grid: HashGrid, pos, cell, p, active):
    """Is the vertex at ``pos`` (bucket order) of the visited ``cell`` (not a hash
    collision's) and within r of p?"""
    y = dr.gather(mi.Point3f, grid.points, pos, active)
    own = dr.all(_cell(y, grid.inv_cell) == cell)
    return active & own & (dr.squared_norm(y - p) <= grid.radius2)


def _merge_one(ctx, pos, active, state, v):
    """The weighted merge contribution of the light vertex at ``pos`` (bucket order) at
    camera vertex ``v`` (z_j), before beta_E and the normalization; in a moment pass
    also (luminance of the contribution, its u_pt, u_lt, u_vm times it)."""
    y = gather(ctx.grid.photons, pos, active)
    w_y, beta_l, s = y.w, y.beta, y.s
    active &= ctx.strategies.merges(s - 1, state.depth)
    cos_g, ok = v.cosine(w_y)
    active &= ok & (cos_g > 0)
    w = ctx.weights
    # pdf_w: z_j toward y_{i-1}, the light side's reverse; rev_w: toward z_{j-1}, the
    # camera side's reverse.
    if w.merges_evaluated:
        f, pdf_w, rev_w = v.eval_and_reverse(w_y, active)
    else:
        f, pdf_w = v.eval(w_y, active)
    value = f * beta_l / cos_g
    active &= spectrum_nonzero(value)
    if w.merges_evaluated:
        light_d_vc = cam_d_vc = None
        if ctx.moments is not None:          # (a shadow pass's chains lack merging's part)
            light_d_vc = w.moment_d_vc(y.d_vc, y.d_vm)
            cam_d_vc = w.moment_d_vc(state.d_vc, state.d_vm)
        value *= w.merge(y, state.d_vcm, state.d_vc if cam_d_vc is None else cam_d_vc,
                         state.depth, pdf_w, rev_w, light_d_vc)
    value = dr.select(active, finite(value), 0.0)
    if ctx.moments is None:
        return value
    light = mis.Chains(y.d_vcm, light_d_vc, y.d_end, y.d_vm)
    u = mis.groups_merge(light, s == 2, pdf_w, state.d_vcm, cam_d_vc, state.d_end, state.d_vm,
                         state.depth == 1, rev_w, w.eta, w.rate(s - 1), w.rate(state.depth))
    lum = luminance(value * state.beta)
    return value, lum, u[0] * lum, u[1] * lum, u[2] * lum, dr.square(lum)


def _sum(a, b):
    """a + b, element by element for tuples (a sum of several values)."""
    if isinstance(a, tuple):
        return tuple(_sum(x, y) for x, y in zip(a, b))
    return type(a)(a + b)


def visit(grid: HashGrid, store, p, active, value, zero, count: bool = False):
    """The sum over stored light vertices within r of ``p`` of ``value(pos, near)``
    (``pos``: the vertex's place in bucket order, ``grid.order[pos]`` its pool item)
    (0 where not ``near``): one symbolic loop over the items of the buckets of the
    cells a sphere of radius r around p touches (``_cells``), one item per iteration,
    cell after cell of their mask (``dr.tzcnt``): an empty cell costs no iteration.
    ``count``: also return the items each query visited (the merge's counted work)."""
    scaled = p * grid.inv_cell
    cell = mi.Vector3i(dr.floor(scaled))
    away = mi.Vector3i(dr.select(scaled - dr.floor(scaled) < 0.5, -1, 1))
    n = dr.width(p)

    def load(k, mask, pos, end, visiting, on):
        """Where ``on``: the first cell left in ``mask`` (k = 8 if none), its items."""
        k = dr.select(on, dr.select(mask == 0, 8, mi.Int32(dr.tzcnt(mask))), k)
        on &= k < 8
        nxt = grid.neighbour(cell, away, dr.minimum(dr.maximum(k, 0), 7))
        bucket = _bucket(nxt, grid.buckets)
        first = dr.gather(mi.UInt32, grid.start, bucket, on)
        end = dr.select(on, first + dr.gather(mi.UInt32, grid.count, bucket, on), end)
        mask = dr.select(on, mask & ~(mi.UInt32(1) << mi.UInt32(dr.maximum(k, 0))), mask)
        return k, mask, dr.select(on, first, pos), end, dr.select(on, nxt, visiting)

    def body(k, mask, pos, end, visiting, total, items):
        total = _sum(total, value(pos, _near(grid, pos, visiting, p, k < 8)))
        pos = pos + 1
        return load(k, mask, pos, end, visiting, pos >= end) + (total, items + 1)

    zeros = dr.zeros(mi.UInt32, n)
    state = load(mi.Int32(8), _cells(grid, cell, away, p, active), zeros, zeros,
                 mi.Vector3i(cell), dr.full(mi.Bool, True, n))
    *_, total, items = dr.while_loop(
        state + (zero, zeros), lambda k, *rest: k < 8, body,
        labels=("k", "mask", "pos", "end", "visiting", "total", "items"), label="merges")
    return (total, items) if count else total


def _cells(grid: HashGrid, cell, away, p, active) -> mi.UInt32:
    """The cells a query at ``p`` (in ``cell``) visits, as a mask (bit k: the k-th of
    the 8, HashGrid.neighbour): those within r of p whose bucket holds items.  Each
    cell its sphere might touch and found empty was an iteration of the query's loop,
    with the whole merge evaluated under its mask (8 per query; 3.1 queries and 94
    items per camera sample in the diffuse box's pilot)."""
    mask = dr.zeros(mi.UInt32, dr.width(p))
    size = dr.rcp(grid.inv_cell)
    for k in range(8):
        nxt = grid.neighbour(cell, away, k)
        lo = mi.Vector3f(nxt) * size                    # the cell's box [lo, lo + size]
        gap = dr.maximum(dr.maximum(lo - p, p - (lo + size)), 0.0)
        near = active & (dr.squared_norm(gap) <= grid.radius2 * 1.001)   # (rounding)
        items = dr.gather(mi.UInt32, grid.count, _bucket(nxt, grid.buckets), near)
        mask |= dr.select(near & (items > 0), mi.UInt32(1 << k), 0)
    return mask


def merge_at(ctx, store, state, v, active) -> mi.Spectrum:
    """Every merge at camera vertex z_j (j = state.depth): the weighted sum over the
    light vertices within r, times beta_E / (pi r^2 N_L).  Counts the query and the
    items it visited (``state.merges``, ``state.merge_items``); a moment pass records
    the sum as one sample, its groups the contributions' luminance-weighted means, and
    the sum of their squares apart (optimizer.MomentSamples.add: the photons' pairs
    are what more photons do not average away)."""
    grid = ctx.grid
    n = dr.width(v.p)
    zero = dr.zeros(mi.Spectrum, n)
    if ctx.moments is not None:
        zero = (zero,) + tuple(dr.zeros(mi.Float, n) for _ in range(5))
    total, items = visit(grid, store, v.p, active,
                         lambda pos, near: _merge_one(ctx, pos, near, state, v), zero, True)
    state.merges += dr.select(active, 1, 0)
    state.merge_items += items
    if ctx.moments is None:
        return dr.select(active, finite(state.beta * total * grid.norm), 0.0)
    value = dr.select(active, finite(state.beta * total[0] * grid.norm), 0.0)
    lum = total[1]
    u = [dr.select(lum > 0, x / lum, 0.0) for x in total[2:5]]
    state.slot = ctx.moments.add(state.slot, ctx.lane, ctx.pixel, value, *u, active,
                                 total[5] * dr.square(grid.norm))
    return value


def can_merge(strategies: StrategySet, v, depth, connectible):
    """Camera vertex z_j merges: it scatters smoothly, lies on a surface, and some
    light vertex y_i (i >= 1) could make a path within max_depth."""
    return connectible & v.surface & strategies.merges(1, depth)
