"""Frozen walks: a walk's kernel recorded once (``dr.freeze``) and replayed by later
passes whose Python side is the same, without tracing it again.

Tracing a walk in Python (Mitsuba's virtual calls over the scene's BSDFs and shapes,
the MIS chains) and assembling its kernel cost 5-10 ms a pass whatever its size: on a
64x64 film that is most of the pilot pass's time (its kernels run 3 ms).  A pass of
Mitsuba's path (render._recorded_path_pass) is recorded whole the same way.

What a walk reads lives in plain Python objects (the pass context's emitters, MIS
weights, media, camera) that ``dr.freeze`` cannot traverse.  So the recorded function
takes no arguments of its own: ``_inputs`` walks the objects a call hands it and
splits them into

* the key: every Python value the tracing may branch on or bake into the kernel
  (ints, floats, strings, flags, the types and widths of arrays, the identity of each
  Mitsuba object and of the scene; a sampler's or an image block's type and sizes) --
  a call whose key differs records anew;
* the state: every Dr.Jit array and Mitsuba object they hold, which ``dr.freeze``
  takes as the recording's inputs (``state_fn``) and replaces by the new call's.

A class may name attributes the walks never read in ``FROZEN_IGNORE`` (a value read
back from the device: a read inside a recording fails), so that they key nothing.

A replay runs the kernels recorded from the same Python code on the new arrays, so it
gives the image the traced walk gives (tests/test_frozen.py).  Host reads are not
allowed inside a recording: the walks have none (pool sizes are read after them).
"""
from __future__ import annotations

import dataclasses
import enum
import gc
import hashlib
import os
import types

import drjit as dr
import mitsuba as mi
import numpy as np

# Recordings kept, of all walks together (LRU): a render's kinds of pass (the pilot,
# the budget's passes, its moment passes, a pass with outgrown pools) take two each
# (the Cornell box at 128x128: 7); past the limit each render would record again.
LIMIT = 16

_SCALARS = (int, float, str, bool, bytes, type(None), enum.Enum, complex)


def _inputs(obj, key: list, state: list, seen: dict) -> None:
    """Append ``obj``'s Python values to ``key`` and its arrays and Mitsuba objects to
    ``state``, depth first, in a fixed order."""
    kind, info = _KINDS.get(type(obj)) or _classify(type(obj))
    if kind is _SCALAR:
        key.append(obj)
    elif kind is _JIT_ARRAY:
        key.append(("array", info, dr.width(obj)))
        state.append(obj)
    elif kind is _STRUCT:                   # Mitsuba's records (rays, interactions)
        key.append(info[0])
        for name in info[1]:
            key.append(name)
            _inputs(getattr(obj, name), key, state, seen)
    elif kind is _MITSUBA:                  # the scene, its sensor, samplers, plugins
        # A pass's samplers are clones, new each pass, and a render's image blocks are
        # its own: what the tracing sees of them is their type and sizes; every other
        # object, the scene's own, by identity.
        key.append(("mitsuba", info[0], info[1](obj) if info[1] else id(obj)))
        if id(obj) not in seen:
            seen[id(obj)] = len(seen)
            state.append(obj)
    elif kind is _TYPE:
        key.append(("type", obj.__module__, obj.__qualname__))
    elif kind is _HOST_ARRAY:               # a host value: baked into the kernels
        key.append(("scalar array", info, repr(obj)))
    elif id(obj) in seen:                   # shared or cyclic: its position, once
        key.append(("seen", seen[id(obj)]))
    else:
        seen[id(obj)] = len(seen)
        _container(kind, info, obj, key, state, seen)


def _container(kind, info, obj, key: list, state: list, seen: dict) -> None:
    """``_inputs`` of an object met for the first time that holds others."""
    if kind is _SEQUENCE:
        key.append((info, len(obj)))
        for item in obj:
            _inputs(item, key, state, seen)
    elif kind is _FIELDS:                   # a dataclass: its fields, FROZEN_IGNORE's out
        key.append(info[0])
        for name in info[1]:
            key.append(name)
            _inputs(getattr(obj, name), key, state, seen)
    elif kind is _ATTRS and hasattr(obj, "__dict__"):
        key.append(info[0])
        for name in sorted(vars(obj)):
            if name not in info[1]:
                key.append(name)
                _inputs(getattr(obj, name), key, state, seen)
    elif kind is _DICT:
        key.append(("dict", tuple(repr(k) for k in obj)))
        for item in obj.values():
            _inputs(item, key, state, seen)
    elif kind is _SET:
        key.append(("set", tuple(sorted(repr(v) for v in obj))))
    elif kind is _NUMPY:
        key.append(("numpy", obj.dtype.str, obj.shape, obj.tobytes()))
    elif kind is _FUNCTION:
        _function(obj, key, state, seen)
    else:                                   # unknown: this very object only
        key.append(("other", type(obj).__qualname__, id(obj)))


# What ``_inputs`` does with an object, by its type, decided once per type (the walks'
# context is about 440 objects per pass; deciding per object took 0.4 ms a walk).
(_SCALAR, _TYPE, _HOST_ARRAY, _JIT_ARRAY, _STRUCT, _MITSUBA, _SEQUENCE, _SET, _DICT, _NUMPY,
 _FUNCTION, _FIELDS, _ATTRS) = (object() for _ in range(13))
_KINDS: dict = {}


def _classify(t: type) -> tuple:
    """(kind, what ``_inputs`` needs of the type) for objects of type ``t``."""
    if issubclass(t, _SCALARS):
        kind = _SCALAR, None
    elif issubclass(t, type):
        kind = _TYPE, None
    elif dr.is_array_v(t):
        kind = (_JIT_ARRAY if dr.is_jit_v(t) else _HOST_ARRAY), t.__name__
    elif getattr(t, "DRJIT_STRUCT", None) is not None:
        kind = _STRUCT, (("struct", t.__qualname__), tuple(t.DRJIT_STRUCT))
    elif issubclass(t, mi.Object):
        kind = _MITSUBA, (t.__name__, _sampler_key if issubclass(t, mi.Sampler) else
                          _block_key if issubclass(t, mi.ImageBlock) else None)
    elif issubclass(t, (list, tuple)):
        kind = _SEQUENCE, t.__name__
    elif issubclass(t, (set, frozenset)):
        kind = _SET, None
    elif issubclass(t, dict):
        kind = _DICT, None
    elif issubclass(t, np.ndarray):
        kind = _NUMPY, None
    elif issubclass(t, (types.FunctionType, types.MethodType, types.BuiltinFunctionType)):
        kind = _FUNCTION, None
    else:
        header = ("object", t.__module__, t.__qualname__)
        ignore = getattr(t, "FROZEN_IGNORE", ())
        if dataclasses.is_dataclass(t):
            kind = _FIELDS, (header, tuple(f.name for f in dataclasses.fields(t)
                                           if f.name not in ignore))
        else:
            kind = _ATTRS, (header, ignore)
    _KINDS[t] = kind
    return kind


def _function(fn, key: list, state: list, seen: dict) -> None:
    """A callable: its code, and what its closure and bound object hold."""
    if isinstance(fn, types.MethodType):
        key.append(("method", fn.__func__.__qualname__))
        _inputs(fn.__self__, key, state, seen)
        fn = fn.__func__
    code = getattr(fn, "__code__", None)
    key.append(("function", getattr(fn, "__module__", None), getattr(fn, "__qualname__", None),
                None if code is None else id(code)))
    for cell in getattr(fn, "__closure__", None) or ():
        _inputs(cell.cell_contents, key, state, seen)
    if getattr(fn, "__defaults__", None):
        _inputs(fn.__defaults__, key, state, seen)


def _sampler_key(sampler) -> tuple:
    """What a sampler's calls bake into kernels and its traversal does not give."""
    return (sampler.class_name(), sampler.sample_count(), sampler.wavefront_size())


def _block_key(block) -> tuple:
    """What an image block's put bakes into kernels: its sizes and flags, and its
    filter (the film's, by identity)."""
    return (tuple(block.size()), tuple(block.offset()), block.channel_count(),
            block.border_size(), block.coalesce(), block.normalize(), block.warn_invalid(),
            block.warn_negative(), id(block.rfilter()))


class _Calls:
    """The calls being run (function, state, arguments), and the Mitsuba objects whose
    identity keys the recordings.  ``dr.freeze`` also traverses the globals its
    function reads: held in a plain object, which it hashes by identity, they stay out
    of the recording's key."""

    def __init__(self):
        self.stack = []
        self.alive = {}         # id -> object: kept alive while recordings name it
        self.failed = set()     # digests whose recording failed: traced from then on
        self.textured = {}      # id of a scene -> whether it holds texture data


class RecordingFailed(RuntimeError):
    """``dr.freeze`` could not record a walk (a nested virtual call, such as an emitter
    whose radiance is a texture, in Dr.Jit 1.5).  The walk ran, but its inputs (the
    samplers) have moved on: the caller runs its pass again, and this key is traced
    from then on."""


_calls = _Calls()


def _state(key):
    return _calls.stack[-1][1]


def _recorder(backend: dr.JitBackend):
    """The frozen function of a backend, through which every recorded call goes."""
    @dr.freeze(state_fn=_state, limit=LIMIT, warn_after=10 ** 6, auto_opaque=False,
               backend=backend)
    def frozen(key):
        fn, _, args = _calls.stack[-1]
        return fn(*args)
    return frozen


_frozen = _recorder(dr.JitBackend.LLVM)

ENABLED = True
# Backends whose calls are recorded: LLVM and CUDA (BDPT_FREEZE_CUDA=0 traces every
# CUDA call: the A/B of benchmarks/gpu_check.sh's step "frozen"), where the scene
# holds no texture (_reads_cuda_textures).  On an H100 the suite passed with CUDA's
# recordings but for an environment map's scenes, and a small render took half the
# time.
BACKENDS = ("llvm",) if os.environ.get("BDPT_FREEZE_CUDA") == "0" else ("llvm", "cuda")
_RECORDERS = {"llvm": _frozen}


def _recorder_of(backend: str):
    if backend not in _RECORDERS:
        _RECORDERS[backend] = _recorder(dr.JitBackend.CUDA)
    return _RECORDERS[backend]


def call(fn, *args):
    """``fn(*args)``, recorded on the first call of its key and replayed after (the
    variants of ``BACKENDS``; others trace every call).  ``fn`` must read nothing
    from the device and change no Python state that a later step reads: only its
    return value and the arrays it scatters to survive a replay.

    Every input is made opaque (``auto_opaque=False``): a literal that changed from
    one call to the next would otherwise record the kernels again with it opaque, so
    that which kernels a pass runs would depend on the passes before it.

    Python's cyclic collector is off during the call: run at an allocation inside a
    recording, it freed arrays and objects of earlier renders there, and Dr.Jit 1.5
    aborted the process (tests/test_optimizer.py run after test_vcm.py and
    test_mis.py, in a light walk's recording)."""
    backend = mi.variant().split("_", 1)[0]
    if not ENABLED or backend not in BACKENDS:
        return fn(*args)
    recorder = _recorder_of(backend)
    key, state, seen = [mi.variant()], [], {}
    _inputs((fn, args), key, state, seen)
    digest = _digest(key)
    if digest in _calls.failed:
        return fn(*args)
    _keep_alive(state)
    if _reads_cuda_textures(backend, state):
        return fn(*args)
    _calls.stack.append((fn, state, args))
    collecting = gc.isenabled()
    gc.disable()
    try:
        recorded = recorder.n_recordings
        return recorder(digest)
    except RuntimeError as error:
        if recorder.n_recordings == recorded:   # not a recording's failure
            raise
        _calls.failed.add(digest)
        raise RecordingFailed(str(error)) from error
    finally:
        _calls.stack.pop()
        if collecting:
            gc.enable()


def _nothing(*objects):
    return None


def settle(*objects) -> None:
    """Make the literal arrays inside Mitsuba ``objects`` (a scene's one-value
    parameters, a film's zeroed storage) evaluated, as a recording does with its
    inputs (it copies them and assigns the copies back): a walk traced after a
    recording then compiles against the same variables as before it, not a kernel of
    its own (mlt.py: a second seed compiled 4 kernels).  A no-op function, recorded
    once per kind of object and replayed after (one that cannot be recorded settles
    nothing, and is harmless)."""
    try:
        call(_nothing, *objects)
    except RecordingFailed:
        pass


def _digest(key: list) -> str:
    """The key as one string.  ``dr.freeze`` 1.5 told a tuple of Python values from
    another by a hash that swapped values passed: a walk of technique (3, 2) replayed
    the recording of (2, 3), and rendered black (tests/test_frozen.py)."""
    return hashlib.blake2b(repr(key).encode(), digest_size=16).hexdigest()


def _keep_alive(state: list) -> None:
    """Keys name Mitsuba objects by id; an id is reused once its object is freed.  The
    recordings therefore hold the objects they name alive, and are dropped when a call
    names another scene (a render of another scene starts)."""
    objects = {id(o): o for o in state if isinstance(o, mi.Object)
               and not isinstance(o, mi.Sampler)}
    if any(isinstance(o, mi.Scene) and i not in _calls.alive for i, o in objects.items()):
        for recorder in _RECORDERS.values():
            recorder.clear()
        _calls.alive, _calls.failed, _calls.textured = {}, set(), {}
    _calls.alive.update(objects)


def _reads_cuda_textures(backend: str, state: list) -> bool:
    """Whether a CUDA call's scene holds texture data (a tensor parameter: a bitmap,
    an environment map, a grid volume), which CUDA kernels read through texture
    objects.  Dr.Jit 1.5 aborted the process recording a walk under an environment
    map (seen on an H100; the frozen function does not traverse the texture object,
    only its tensor), so such a scene's walks are traced."""
    if backend != "cuda":
        return False
    for scene in (obj for obj in state if isinstance(obj, mi.Scene)):
        if id(scene) not in _calls.textured:
            params = mi.traverse(scene)
            _calls.textured[id(scene)] = any(isinstance(params[k], mi.TensorXf)
                                             for k in params.keys())
        if _calls.textured[id(scene)]:
            return True
    return False
