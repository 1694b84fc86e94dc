"""Stored light vertices and light-image splats of a pass: append-only pools.

Only light vertices are stored (camera vertices are connected while their
interaction is live in the camera walk).  Subpaths end at different depths, so
instead of a slot per lane and depth, each vertex that some strategy (s, t >= 2)
will connect is appended to one pool (``dr.scatter_inc``: on the CPU a SIMD packet
takes consecutive entries), and each lane's vertices form a list y_1 -> y_2 -> ...
(``first`` per lane, ``next`` per record) that the camera walk follows.  Memory and
work then follow the vertices that exist, whatever the depth (max_depth -1 included),
and no kernel depends on how deep a subpath went.

Pools have a capacity fixed before the light walk.  Appends past it are counted but
not written; the renderer then runs the light walk again with a larger pool
(``overflowed``), before anything reached the film, so an overflow costs time, never
a sample.
"""
from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from .surface import VertexRecord

NONE = 0xFFFFFFFF                    # "no vertex" in first/next


@dataclass
class LightVertex:
    """Light vertex y_{s-1} (s >= 2) as connections need it."""
    record: VertexRecord             # the vertex (a surface point or a medium point)
    beta: mi.Spectrum                # throughput from y_0 to here (Russian roulette included)
    d_vcm: mi.Float                  # MIS chain state (mis.py)
    d_vc: mi.Float
    d_end: mi.Float                  # moment passes: the chain's far end (mis.py)
    d_vm: mi.Float                   # moment passes with merging: d_vc's merge part
    s: mi.UInt32                     # the light vertex count of its strategies: s = i + 1
    next: mi.UInt32                  # the lane's next stored vertex, or NONE


@dataclass
class PackedVertices:
    """The pool's light vertices: their floats (and s, prim_index and in_medium as
    bits) in chunks of 4 floats read by Dr.Jit's packet gathers, the first HEAD of each
    vertex side by side in one array and the rest in another; the pointers and the
    list's links an array each.  A connection reads a vertex from 7 cache lines (3 for
    its floats) instead of one per field (40): the connection loop gathers a vertex of
    its lane's light subpath at every iteration.  (Dr.Jit rounds an allocation up to a
    power of two: two arrays of a power of two floats per vertex take what one array
    per field does, where one array of 36 took up to 1.8x.)"""
    head: mi.Float                   # HEAD floats per vertex (_pack)
    tail: mi.Float                   # 4 x _tail_chunks() floats per vertex
    shape: mi.ShapePtr
    instance: mi.ShapePtr
    medium: mi.MediumPtr
    next: mi.UInt32                  # the lane's next stored vertex, or NONE


HEAD = 32                            # floats of a vertex in the first array (a power of two)


def _floats() -> int:
    """Floats per vertex: the record's 26, the throughput's channels, 4 MIS values and
    3 bit fields (36 in RGB)."""
    return 33 + dr.size_v(mi.Spectrum)


def _tail_chunks() -> int:
    """4-float chunks of a vertex past HEAD, a power of two (1 in RGB, 2 spectral)."""
    return 1 << max(-(-(_floats() - HEAD) // 4) - 1, 0).bit_length()


def _bits(value) -> mi.Float:
    return dr.reinterpret_array(mi.Float, mi.UInt32(value))


def _pack(v: LightVertex) -> list:
    """A vertex's floats and bit fields, in the order ``_unpack`` reads them."""
    r = v.record
    beta = [v.beta[i] for i in range(dr.size_v(mi.Spectrum))]
    values = [*r.p, *r.n, *r.uv, *r.sh_frame.s, *r.sh_frame.t, *r.sh_frame.n, *r.dp_du,
              *r.dp_dv, *r.wi, *beta, v.d_vcm, v.d_vc, v.d_end, v.d_vm, _bits(v.s),
              _bits(r.prim_index), _bits(dr.select(r.in_medium, 1, 0))]
    return values + [mi.Float(0.0)] * (HEAD + 4 * _tail_chunks() - len(values))


def _unpack(values: list, shape, instance, medium, next_) -> LightVertex:
    n = dr.size_v(mi.Spectrum)
    take = iter(values)
    vec = lambda cls, k: cls(*[next(take) for _ in range(k)])      # noqa: E731
    p, nrm, uv = vec(mi.Point3f, 3), vec(mi.Normal3f, 3), vec(mi.Point2f, 2)
    frame = mi.Frame3f(vec(mi.Vector3f, 3), vec(mi.Vector3f, 3), vec(mi.Normal3f, 3))
    dp_du, dp_dv, wi = vec(mi.Vector3f, 3), vec(mi.Vector3f, 3), vec(mi.Vector3f, 3)
    beta = vec(mi.Spectrum, n) if n > 1 else mi.Spectrum(next(take))
    d_vcm, d_vc, d_end, d_vm = (next(take) for _ in range(4))
    s, prim, in_medium = (dr.reinterpret_array(mi.UInt32, next(take)) for _ in range(3))
    record = VertexRecord(p=p, n=nrm, uv=uv, sh_frame=frame, dp_du=dp_du, dp_dv=dp_dv,
                          wi=wi, shape=shape, instance=instance, prim_index=prim,
                          medium=medium, in_medium=in_medium != 0)
    return LightVertex(record=record, beta=beta, d_vcm=d_vcm, d_vc=d_vc, d_end=d_end,
                       d_vm=d_vm, s=s, next=next_)


# A stored light vertex's bytes (PackedVertices, RGB): 36 floats, 3 pointers and a link.
RECORD_BYTES = 4 * (HEAD + 4 + 4)


@dataclass
class Splat:
    """One light-image (t = 1) contribution, put on the film after the light walk."""
    pos: mi.Point2f                  # film position (pixels, crop offset included)
    value: mi.Spectrum
    s: mi.UInt32                     # its strategy (s, 1)
    lane: mi.UInt32                  # the light subpath's lane (its wavelengths)
    u_pt: mi.Float                   # moment passes: balance-weight groups (optimizer.py)
    u_lt: mi.Float
    u_vm: mi.Float                   # (merging's share)


SPLAT_BYTES = 4 * (2 + 3 + 1 + 1 + 3)


def empty(kind, n: int, zeroed: bool = False):
    """``dr.empty(kind, n)`` for a record dataclass, its field types resolved for the
    current variant (Dr.Jit caches a dataclass's types at first use, so after
    ``mi.set_variant`` it would build the previous variant's arrays).  ``zeroed``:
    filled with zeros, by a memset (see ``LightVertexStore``)."""
    hints = typing.get_type_hints(kind)
    make = dr.zeros if zeroed else dr.empty
    return kind(**{f.name: empty(hints[f.name], n, zeroed) if dataclasses.is_dataclass(
        hints[f.name]) else make(hints[f.name], n) for f in dataclasses.fields(kind)})


def gather(source, index, active=True):
    """``dr.gather`` of a record dataclass, field by field (see ``empty``); a field
    left None stays None."""
    if source is None:
        return None
    if dataclasses.is_dataclass(source):
        return type(source)(**{f.name: gather(getattr(source, f.name), index, active)
                               for f in dataclasses.fields(source)})
    return dr.gather(type(source), source, index, active)


class Pool:
    """An append-only buffer of records of one type, with a counter."""

    # frozen.py: the count read after a walk is no input of the walks (a read
    # inside a recording fails), so it does not key their recordings.
    FROZEN_IGNORE = ("_size",)

    def __init__(self, kind, capacity: int, zeroed: bool = False, allocate: bool = True):
        """``allocate``: False leaves the buffers to ``allocate`` (LightVertexStore)."""
        self.kind, self.capacity, self.zeroed = kind, int(capacity), zeroed
        self.items = self.count = self._capacity = None
        self._size = None               # the count, once read (a read is a sync)
        if allocate:
            self.allocate()

    def allocate(self) -> None:
        self.items = empty(self.kind, self.capacity, self.zeroed)
        self.count = dr.zeros(mi.UInt32, 1)
        self._capacity = dr.opaque(mi.UInt32, self.capacity)

    def append(self, value, active) -> mi.UInt32:
        """Append ``value`` where ``active``; returns each lane's index, NONE where
        nothing was written."""
        self._size = None
        idx = dr.scatter_inc(self.count, mi.UInt32(0), active)
        if not dr.flag(dr.JitFlag.SymbolicScope):
            # An evaluated (wavefront) loop: the counter's result must be evaluated in
            # the kernel that increments it before another kernel may read it.
            dr.eval(idx)
        ok = active & (idx < self._capacity)
        self._scatter(value, idx, ok)
        return dr.select(ok, idx, NONE)

    def _scatter(self, value, idx, ok) -> None:
        dr.scatter(self.items, value, idx, ok)

    def size(self) -> int:
        """Appends requested (may exceed the capacity: see ``overflowed``), read from
        the device once after the appends."""
        if self._size is None:
            self._size = int(self.count[0])
        return self._size

    def overflowed(self) -> bool:
        return self.size() > self.capacity

    def adopt_count(self, count) -> None:
        """The counter a recorded walk that filled this pool returned (frozen.py)."""
        self.count, self._size = count, None


class VertexPool(Pool):
    """The pool of light vertices, packed (PackedVertices)."""

    def __init__(self, capacity: int, zeroed: bool = False, allocate: bool = True):
        super().__init__(PackedVertices, capacity, zeroed, allocate)

    def allocate(self) -> None:
        make = dr.zeros if self.zeroed else dr.empty
        n = self.capacity
        self.items = PackedVertices(
            head=make(mi.Float, HEAD * n), tail=make(mi.Float, 4 * _tail_chunks() * n),
            shape=make(mi.ShapePtr, n), instance=make(mi.ShapePtr, n),
            medium=make(mi.MediumPtr, n), next=make(mi.UInt32, n))
        self.count = dr.zeros(mi.UInt32, 1)
        self._capacity = dr.opaque(mi.UInt32, self.capacity)

    def _chunked(self):
        """(array, chunks per vertex, first value) of the head and the tail."""
        return (self.items.head, HEAD // 4, 0), (self.items.tail, _tail_chunks(), HEAD)

    def _scatter(self, vertex: LightVertex, idx, ok) -> None:
        values, r = _pack(vertex), vertex.record
        for array, chunks, first in self._chunked():
            for c in range(chunks):
                at = first + 4 * c
                dr.scatter(array, mi.Vector4f(*values[at:at + 4]), idx * chunks + c, ok)
        for name, value in (("shape", r.shape), ("instance", r.instance),
                            ("medium", r.medium), ("next", vertex.next)):
            dr.scatter(getattr(self.items, name), value, idx, ok)

    def gather(self, item, active=True) -> LightVertex:
        values = []
        for array, chunks, _ in self._chunked():
            for c in range(chunks):
                chunk = dr.gather(mi.Vector4f, array, item * chunks + c, active)
                values += [chunk.x, chunk.y, chunk.z, chunk.w]
        return _unpack(values, *(dr.gather(type(a), a, item, active) for a in (
            self.items.shape, self.items.instance, self.items.medium, self.items.next)))

    def s(self, item, active=True) -> mi.UInt32:
        """The vertex's s alone (the first bit field, after 30 floats and the
        throughput: _pack)."""
        at = 30 + dr.size_v(mi.Spectrum)
        if at < HEAD:
            array, index = self.items.head, item * HEAD + at
        else:
            array, index = self.items.tail, item * (4 * _tail_chunks()) + at - HEAD
        value = dr.gather(mi.Float, array, index, active)
        return dr.reinterpret_array(mi.UInt32, value)


class LightVertexStore:
    """The pools of one pass: stored light vertices with each lane's list, and the
    light image's splats.  ``zeroed`` (the pilot's passes, whose walks are timed): a
    memset, which the pilot's timer does not count, touches the pools' memory first.
    A small buffer's fresh pages cost their first writer a fault each: the pilot's
    light walks, writing new pools of a few MB, timed up to 35% dearer per light
    subpath in a process's first render, and its first pass dearer than its second
    (which reuses the first's pools), while the passes after it, whose pools are
    hundreds of MB, run as fast on fresh memory as on reused (Cornell box lit via its
    ceiling, 128x128, light_paths=0.25: 466 against 473 ms)."""

    def __init__(self, lanes: int, vertex_capacity: int, splat_capacity: int,
                 zeroed: bool = False, allocate: bool = True):
        """``allocate``: False leaves the buffers to ``allocate``, which a frozen walk
        calls inside its recording (render.py): buffers made before it are inputs of
        the recording, which its scatters copy first (copy on write)."""
        self.lanes = lanes
        self.vertices = VertexPool(max(vertex_capacity, 1), zeroed, allocate)
        self.splats = Pool(Splat, max(splat_capacity, 1), zeroed, allocate)
        self.first = None
        self.order = None                # vertex caches: the pool in a fixed order
        if allocate:
            self.allocate()

    def allocate(self) -> None:
        for pool in (self.vertices, self.splats):
            if pool.items is None:
                pool.allocate()
        self.first = dr.full(mi.UInt32, NONE, self.lanes)
        dr.make_opaque(self.vertices.items, self.splats.items, self.first)

    def buffers(self) -> tuple:
        """The arrays a walk writes, for ``adopt`` (a frozen walk's outputs)."""
        return tuple((p.items, p.count, p._capacity) for p in (self.vertices, self.splats)) + (
            self.first,)

    def adopt(self, buffers: tuple) -> None:
        (self.vertices.items, self.vertices.count, self.vertices._capacity), \
            (self.splats.items, self.splats.count, self.splats._capacity), self.first = buffers
        self.vertices._size = self.splats._size = None

    def add_vertex(self, vertex: LightVertex, lane, prev, active) -> mi.UInt32:
        """Append y_i of ``lane`` after its stored vertex ``prev`` (NONE: the first)."""
        vertex.next = dr.full(mi.UInt32, NONE, dr.width(lane))
        item = self.vertices.append(vertex, active)
        stored = item != NONE
        dr.scatter(self.first, item, lane, stored & (prev == NONE))
        dr.scatter(self.vertices.items.next, item, prev, stored & (prev != NONE))
        return dr.select(stored, item, prev)

    def vertex(self, item, active) -> LightVertex:
        return self.vertices.gather(item, active)

    def overflowed(self) -> bool:
        return self.vertices.overflowed() or self.splats.overflowed()

    def _walk_lists(self, visit) -> mi.UInt32:
        """Follow every light subpath's list, calling ``visit(item, k, path)`` for its
        k-th stored vertex; returns the vertices per light subpath."""
        path = dr.arange(mi.UInt32, dr.width(self.first))

        def body(item, k):
            visit(item, k, path)
            return dr.gather(mi.UInt32, self.vertices.items.next, item), k + 1

        _, count = dr.while_loop((mi.UInt32(self.first), dr.zeros(mi.UInt32, dr.width(path))),
                                 lambda item, k: item != NONE, body, label="light lists")
        return count

    def ordered(self) -> mi.UInt32:
        """The pool's items in a deterministic order: by light subpath, then along its
        list.  Appends land in the pool in whatever order threads reach the counter,
        so a vertex cache drawing "item i" from the pool itself would differ from run
        to run; drawing position i of this order does not."""
        count = self._walk_lists(lambda item, k, path: None)
        start = dr.prefix_sum(count)                 # exclusive
        # NONE where no vertex was stored: a pick there reads no record.
        order = dr.full(mi.UInt32, NONE, max(self.vertices.size(), 1))
        dr.make_opaque(start, order)
        self._walk_lists(lambda item, k, path: dr.scatter(
            order, item, dr.gather(mi.UInt32, start, path) + k))
        dr.eval(order)
        return order
