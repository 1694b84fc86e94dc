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
cells of side 2r hashed into at least BUCKETS buckets per vertex the pool can hold (a
power of two); per bucket a count (``dr.scatter_inc``, whose result is also each
vertex's slot in its bucket), an exclusive prefix sum, and one kernel that scatters
the pool's vertices into bucket order as records of 4 floats (position; direction and
d_vcm; throughput and d_vc) in flat arrays: a query reads a vertex from one cache line.
A query reads the counts of the 8 cells that a sphere of radius r around z_j can
touch and keeps, as a list of item ranges, those within r of z_j that hold items
(the hash puts the 8 cells in distinct buckets: SmallVCM's can put two in one and
count its items twice; a hash collision's foreign items lie farther than r).
Its items are then visited in rounds of two symbolic loops: the first steps over
them (a position read and a distance each) and keeps up to FOUND within r in a local
array, the second evaluates the merge for those alone.  (One loop evaluating the
whole merge under a mask for every item ran it for the 5 items outside r of every 6:
a SIMD packet or a GPU warp runs a masked body as long as any of its lanes needs it.)
With ``DEFERRED`` on, a render pass runs its queries after the camera walk, in a
kernel of their own (``query_pool``): the walk stores each merging camera vertex
(``defer``) and ``run_queries`` merges them, one lane per query, so a packet's lanes
all query.  A moment pass merges in the walk (``merge_at``).
Radius, cell size, bucket count and normalization are opaque: no kernel is
compiled per pass or per radius.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from . import mis
from .connect import at_lane
from .strategies import StrategySet
from .support import scene_bbox
from .surface import VertexRecord, finite, spectrum_nonzero
from .optimizer import luminance
from .vertices import Pool, gather

# The default first radius, in pixel footprints at the scene's centre.  SmallVCM's
# default, 0.003 x the scene's bounding-sphere radius, is about 1 of them in
# scenes/cornell-box.xml at 512x512 but 2 in benchmarks/scene_files/sds.xml (a floor far
# wider than the view); scaled to small films it made merging there 30x slower (a query
# visits every light vertex of 8 cells of side 2r).
RADIUS_PIXELS = 1.5
# Hash buckets per stored vertex the pool can hold (at least; rounded up to a power of
# two).  A query visits every item of its cells' buckets, a hash collision's too
# (skipped only after its position is read): with one bucket per vertex (SmallVCM's),
# about 6 foreign items per query in the diffuse box's pilot, beside its 25 own ones
# at the default radius.
BUCKETS = 4
# Lanes of an automatic pass with merging (settings.samples_per_pass 0): the radius
# shrinks from pass to pass, so passes stay small (SmallVCM's are 1 spp).
PASS_LANES = 1 << 16
# Vertices within r that a query's scan collects before it merges them (merge.visit):
# the diffuse box's queries find 9 within r on average, a 16-lane packet's largest
# count 16 (Cornell box, 256x256, Veach's budget); more wait for another round.
FOUND = 16
# A render pass defers its merge queries (``query_pool``) where their pool, at most one
# query per lane and camera depth, fits this share of the memory budget.
DEFERRED_SHARE = 4
# Whether render passes defer their queries: off (BDPT_DEFERRED_MERGES=1 turns it on,
# the A/B of benchmarks/gpu_check.sh's step "deferred").  On the CPU, A/B in one process
# (2026-11-27): 0.96x the time of merging in the walk on the Cornell box at Veach's
# budget, but 1.13x at light_paths=0.25 connections=0 and 1.26x on the SDS scene at the
# budget vcm picks there, where the queries are few and their 152-byte records cost
# more than full packets save.  A GPU warp idles for every lane that does not query:
# there it may pay.
DEFERRED = os.environ.get("BDPT_DEFERRED_MERGES") == "1"


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


def _padded(spectrum) -> list:
    """A spectrum's channels padded to 3 (a record's first 3 floats)."""
    channels = [spectrum[i] for i in range(dr.size_v(spectrum))]
    return (channels + [mi.Float(0.0)] * 3)[:3]


def _unpadded(v: mi.Vector4f) -> mi.Spectrum:
    n = dr.size_v(mi.Spectrum)
    return mi.Spectrum(*[v[i] for i in range(n)]) if n > 1 else mi.Spectrum(v.x)


def _bucket(cell: mi.Vector3i, buckets) -> mi.UInt32:
    """A cell's bucket: the low 6 bits are the cell's coordinates modulo 4, the others
    SmallVCM's spatial hash (Teschner et al. 2003's primes) of its block of 4x4x4 cells.
    The 8 cells of a query lie in distinct buckets (they differ by 1 along some axis),
    next to each other in memory where they share a block; ``buckets``: a power of two,
    at least 64.  (SmallVCM's hash of the cell itself: 13% more items per query in the
    Cornell box, foreign ones, and a test that two of the 8 cells share no bucket.)"""
    c = mi.Vector3u(cell)
    b = c >> 2
    low = (c.x & 3) | ((c.y & 3) << 2) | ((c.z & 3) << 4)
    return ((((b.x * 73856093) ^ (b.y * 19349663) ^ (b.z * 83492791)) << 6) | low) & (buckets - 1)


@dataclass
class Photon:
    """What a merge reads of a stored light vertex y_i (``HashGrid.photon``: the
    grid's records in bucket order, 12 values of the 22 of the vertex's record; one
    record of 4 floats more in a moment pass)."""
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
    points: mi.Float = None     # per vertex in bucket order: (position, s as bits)
    photons: mi.Float = None    # per vertex: (w, d_vcm), (beta, d_vc) (render passes)
    shares: mi.Float = None     # per vertex: (d_end, d_vm) (moment passes)

    @staticmethod
    def build(store, radius: float, light_subpaths: int, photons: bool = True,
              shares: bool = False) -> "HashGrid":
        """The grid of ``store``'s vertices (vertices.LightVertexStore's pool) at radius r;
        ``photons``: also copy their merge records (``Photon``) in bucket order, with
        ``shares`` (a moment pass) the chains' ends and merge parts too."""
        capacity = store.vertices.capacity
        index = dr.arange(mi.UInt32, capacity)
        size = dr.gather(mi.UInt32, store.vertices.count, dr.zeros(mi.UInt32, capacity))
        stored = index < dr.minimum(size, capacity)
        items = store.vertices.gather(index, stored)    # in pool order
        # Every stored vertex that can merge: in the pool, on a surface.
        ok = stored & ~items.record.in_medium
        n_buckets = max(1 << max(BUCKETS * capacity - 1, 1).bit_length(), 64)
        buckets = dr.opaque(mi.UInt32, n_buckets)
        inv_cell = dr.opaque(mi.Float, 0.5 / radius)
        bucket = _bucket(_cell(items.record.p, inv_cell), buckets)
        count = dr.zeros(mi.UInt32, n_buckets)
        slot = dr.scatter_inc(count, bucket, ok)
        dr.eval(slot, count)            # the counter's results, in the kernel that counts
        start = dr.prefix_sum(count)    # exclusive
        # One kernel puts every vertex in its place: it reads the pool in order and
        # scatters (gathering the records in bucket order read each at random: 21
        # values, frame included; 2.7x the time of this kernel on the CPU).
        dest = dr.gather(mi.UInt32, start, bucket, ok) + slot
        order = dr.zeros(mi.UInt32, capacity)
        dr.scatter(order, index, dest, ok)
        # Records of 4 floats each in one flat array (Dr.Jit's packet gather and scatter):
        # a query reads a vertex's record from one cache line, not from one per field.
        points = dr.zeros(mi.Float, 4 * capacity)
        stage = mi.Float(dr.reinterpret_array(mi.Float, items.s)) if photons else mi.Float(0.0)
        dr.scatter(points, mi.Vector4f(*items.record.p, stage), dest, ok)
        grid = HashGrid(order=order, start=start, count=count, inv_cell=inv_cell,
                        radius2=dr.opaque(mi.Float, radius * radius), buckets=buckets,
                        norm=dr.opaque(mi.Float, 1.0 / (math.pi * radius * radius
                                                        * max(light_subpaths, 1))),
                        points=points)
        if photons:
            w = items.record.sh_frame.to_world(items.record.wi)
            beta = _padded(items.beta)
            grid.photons = dr.zeros(mi.Float, 8 * capacity)
            dr.scatter(grid.photons, mi.Vector4f(*w, items.d_vcm), 2 * dest, ok)
            dr.scatter(grid.photons, mi.Vector4f(*beta, items.d_vc), 2 * dest + 1, ok)
            if shares:
                grid.shares = dr.zeros(mi.Float, 2 * capacity)
                dr.scatter(grid.shares, mi.Vector2f(items.d_end, items.d_vm), dest, ok)
        dr.eval(grid.start, grid.order, grid.points, grid.photons, grid.shares)
        return grid

    def photon(self, pos, active) -> Photon:
        """The merge record of the vertex at ``pos`` (bucket order)."""
        a = dr.gather(mi.Vector4f, self.photons, 2 * pos, active)
        b = dr.gather(mi.Vector4f, self.photons, 2 * pos + 1, active)
        stage = dr.gather(mi.Vector4f, self.points, pos, active).w
        y = Photon(w=mi.Vector3f(a.x, a.y, a.z), beta=_unpadded(b), d_vcm=a.w, d_vc=b.w,
                   s=dr.reinterpret_array(mi.UInt32, stage))
        if self.shares is not None:
            e = dr.gather(mi.Vector2f, self.shares, pos, active)
            y.d_end, y.d_vm = e.x, e.y
        return y

    def neighbour(self, cell: mi.Vector3i, away: mi.Vector3i, k) -> mi.Vector3i:
        """The k-th of the 8 cells a sphere of radius r around a point of ``cell`` can
        touch: bit 2, 1, 0 of k step x, y, z toward the nearer neighbour (``away``)."""
        k = mi.UInt32(k)
        return cell + mi.Vector3i(dr.select((k & 4) != 0, away.x, 0),
                                  dr.select((k & 2) != 0, away.y, 0),
                                  dr.select((k & 1) != 0, away.z, 0))


def _near(grid: HashGrid, pos, p, active):
    """Is the vertex at ``pos`` (bucket order) within r of p?"""
    q = dr.gather(mi.Vector4f, grid.points, pos, active)
    return active & (dr.squared_norm(mi.Point3f(q.x, q.y, q.z) - p) <= grid.radius2)


def _merge_one(ctx, pos, active, state, v):
    """The weighted merge contribution of the light vertex at ``pos`` (bucket order) at
    camera vertex ``v`` (z_j), before beta_E and the normalization; in a moment pass
    also (luminance of the contribution, its u_pt, u_lt, u_vm times it)."""
    y = ctx.grid.photon(pos, active)
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
    """The sum over stored light vertices within r of ``p`` of ``value(pos, active)``
    (``pos``: the vertex's place in bucket order, ``grid.order[pos]`` its pool item;
    called for vertices within r only, where ``active``): the items of the cells
    ``_cells`` lists, in rounds (see the module docstring): a scan loop collects up
    to FOUND items within r into a local array, a merge loop sums ``value`` over them.
    The items within r are summed in the order of a single loop over the cells' items.
    ``count``: also return the items each query visited (the merge's counted work:
    every item of its ranges, within r or not)."""
    n = dr.width(p)
    ranges, cells = _cells(grid, p, active)

    def step(j, pos, end, items, found, buf, ranges):
        """The item at ``pos``: into ``buf`` if within r; then the next item, the next
        cell's first if this one's are done (j: the cell, of ``cells``)."""
        near = _near(grid, pos, p, j < cells)
        buf.write(pos, found, near)
        pos = pos + 1
        j = dr.select(pos >= end, j + 1, j)
        on = (pos >= end) & (j < cells)
        pos = dr.select(on, ranges.read(2 * j, on), pos)
        end = dr.select(on, ranges.read(2 * j + 1, on), end)
        return j, pos, end, items + 1, found + dr.select(near, 1, 0), buf, ranges

    def merges(i, total, found, buf):
        return i + 1, _sum(total, value(buf.read(i, i < found), i < found)), found, buf

    def body(j, pos, end, items, total, ranges):
        buf = dr.alloc_local(mi.UInt32, FOUND)
        j, pos, end, items, found, buf, ranges = dr.while_loop(
            (j, pos, end, items, dr.zeros(mi.UInt32, n), buf, ranges),
            lambda j, pos, end, items, found, buf, ranges: (j < cells) & (found < FOUND),
            step, labels=("j", "pos", "end", "items", "found", "buf", "ranges"),
            label="merge candidates")
        _, total, _, _ = dr.while_loop(
            (dr.zeros(mi.UInt32, n), total, found, buf), lambda i, total, found, buf: i < found,
            merges, labels=("i", "total", "found", "buf"), label="merges")
        return j, pos, end, items, total, ranges

    zeros = dr.zeros(mi.UInt32, n)
    on = cells > 0
    state = (zeros, ranges.read(zeros, on), ranges.read(zeros + 1, on), zeros, zero, ranges)
    _, _, _, items, total, _ = dr.while_loop(
        state, lambda j, *rest: j < cells, body,
        labels=("j", "pos", "end", "items", "total", "ranges"), label="merge rounds")
    return (total, items) if count else total


def _cells(grid: HashGrid, p, active):
    """The item ranges a query at ``p`` visits: of the 8 cells a sphere of radius r
    around p can touch (HashGrid.neighbour), those within r of p whose bucket holds
    items (their buckets are distinct, ``_bucket``: no item is counted twice, and a
    collision's foreign items, of cells farther away, fail the distance test).
    Returns a local array of (first, end) positions, cell after cell, and their count:
    the query's loop reads its next range from it, not from the grid."""
    scaled = p * grid.inv_cell
    cell = mi.Vector3i(dr.floor(scaled))
    away = mi.Vector3i(dr.select(scaled - dr.floor(scaled) < 0.5, -1, 1))
    n = dr.width(p)
    ranges = dr.alloc_local(mi.UInt32, 16)
    cells = dr.zeros(mi.UInt32, n)
    size = dr.rcp(grid.inv_cell)
    for k in range(8):
        nxt = grid.neighbour(cell, away, k)
        lo = mi.Vector3f(nxt) * size                    # the cell's box [lo, lo + size]
        gap = dr.maximum(dr.maximum(lo - p, p - (lo + size)), 0.0)
        near = active & (dr.squared_norm(gap) <= grid.radius2 * 1.001)   # (rounding)
        bucket = _bucket(nxt, grid.buckets)             # (the 8 buckets are distinct)
        items = dr.gather(mi.UInt32, grid.count, bucket, near)
        listed = near & (items > 0)
        start = dr.gather(mi.UInt32, grid.start, bucket, listed)
        ranges.write(start, 2 * cells, listed)
        ranges.write(start + items, 2 * cells + 1, listed)
        cells += dr.select(listed, 1, 0)
    return ranges, cells


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


@dataclass
class MergeQuery:
    """A camera vertex z_j whose merges run after the camera walk (``run_queries``):
    what ``_merge_one`` reads of the walk's state there."""
    record: VertexRecord    # z_j
    beta: mi.Spectrum       # beta_E(z_j)
    d_vcm: mi.Float         # the camera chains at z_j (mis.py)
    d_vc: mi.Float
    depth: mi.UInt32        # j
    lane: mi.UInt32         # the camera lane


def query_pool(strategies: StrategySet, lanes: int, moments: bool,
               memory_budget: int) -> Pool | None:
    """The pool of a render pass's deferred merge queries (``defer``, ``run_queries``;
    allocated by the walk that fills it), or None where the camera walk merges at
    each vertex itself (``merge_at``): a moment pass (its moment samples take slots in
    the walk's order, and a shadow pass's merges are for them alone), no bound on
    the depth, or a pool past 1 / DEFERRED_SHARE of ``memory_budget``.  A lane
    queries at most once per camera vertex z_j, j <= max_depth - 1 (a merge needs
    y_1), so the pool never overflows.

    Why defer: in the walk's kernel a SIMD packet (a warp) runs each depth's query
    loops as long as any of its lanes queries, the lanes that stopped or sit on a
    delta surface idle (the Cornell box, 256x256, Veach's budget: 3.1 queries per lane
    over depths 1-5, and 2.9x the packet iterations that the queries' items / 16 would
    take; run over the queries alone, 1.9x)."""
    if not DEFERRED or moments or strategies.max_depth < 0:
        return None
    depths = strategies.max_depth - 1
    if strategies.max_camera_vertices() is not None:
        depths = min(depths, strategies.max_camera_vertices())
    size = lanes * max(depths, 1)
    record = 4 * (31 + dr.size_v(mi.Spectrum) + 4)      # VertexRecord's 31 values
    if size * record * DEFERRED_SHARE > memory_budget:
        return None
    return Pool(MergeQuery, size, allocate=False)


def defer(ctx, state, v, active) -> None:
    """Camera vertex z_j's merges, put off until the walk ends (``run_queries``)."""
    ctx.queries.append(MergeQuery(record=VertexRecord.of(v), beta=mi.Spectrum(state.beta),
                                  d_vcm=mi.Float(state.d_vcm), d_vc=mi.Float(state.d_vc),
                                  depth=mi.UInt32(state.depth), lane=mi.UInt32(ctx.lane)),
                       active)
    state.merges += dr.select(active, 1, 0)


def run_queries(ctx, store, cam) -> None:
    """The merges a camera walk deferred (``defer``), one lane per query, each as
    ``merge_at`` evaluates it: its value goes to its camera lane's radiance (and the
    merge layer), its visited items to the lane's count.  The walk's other strategies
    are in ``cam.radiance`` already: the sum differs from the walk's own by float
    rounding.  The pool's size stays on the device (a recorded walk reads nothing
    back, frozen.py): the lanes past it do nothing."""
    pool, grid = ctx.queries, ctx.grid
    n = pool.capacity
    index = dr.arange(mi.UInt32, n)
    active = index < dr.gather(mi.UInt32, pool.count, dr.zeros(mi.UInt32, n))
    q = gather(pool.items, index, active)
    v = q.record.vertex(at_lane(ctx.time, q.lane, active),
                        at_lane(ctx.wavelengths, q.lane, active), ctx.media.present)
    total, items = visit(grid, store, v.p, active,
                         lambda pos, near: _merge_one(ctx, pos, near, q, v),
                         dr.zeros(mi.Spectrum, n), True)
    value = dr.select(active, finite(q.beta * total * grid.norm), 0.0)
    dr.scatter_reduce(dr.ReduceOp.Add, cam.radiance, value, q.lane, active)
    dr.scatter_reduce(dr.ReduceOp.Add, cam.merge_items, items, q.lane, active)
    if ctx.images is not None:
        ctx.images.add_layer(q.lane, ctx.images.merge_layer, value, active)


def can_merge(strategies: StrategySet, v, depth, connectible):
    """Camera vertex z_j merges: it scatters smoothly, lies on a surface, and some
    light vertex y_i (i >= 1) could make a path within max_depth."""
    return connectible & v.surface & strategies.merges(1, depth)
