"""What the backend a render runs on sets: the memory a pass may use by default, and
the lanes of a pass of Mitsuba's ``path``.

A pass's fixed cost (tracing its kernels from Python, host syncs) is a few ms on the
CPU but 25-40 ms on a GPU host, where its kernels take 4-35 ns per lane: there passes
must be large.  The default memory budget is therefore 2 GiB on the CPU and a quarter
of the GPU's memory (2-12 GiB) under CUDA, and a pass of path tracing (the pilot's
choice where light paths do not pay) takes up to 2^24 lanes there.  Sizes follow the
device, not timings, so a seed still fixes the image on a given machine.
"""
from __future__ import annotations

import ctypes
import functools

import drjit as dr
import mitsuba as mi
import numpy as np

CPU_MEMORY_BUDGET = 2 * 1024 ** 3
# Under CUDA: a quarter of the GPU's memory, between these.  Past ~8M lanes a pass's
# fixed cost is under a tenth of its time: 12 GiB at Veach's BDPT's planned 1.6 KB per
# lane (render._lanes_for; measured on an H100 at 8 GiB when passes were planned at 1.1).
GPU_MEMORY_BUDGET = (CPU_MEMORY_BUDGET, 12 * 1024 ** 3)
# Lanes of a pass of Mitsuba's path after the pilot chose path tracing, at most: on the
# CPU about what a BDPT pass takes; on a GPU 16 spp of a 1024x1024 film.
PATH_PASS_LANES = {"llvm": 1 << 21, "cuda": 1 << 24}
# Bytes per lane of such a pass (Mitsuba's path: camera ray and sampler state;
# measured 28-64 bytes per lane on the CPU and an H100).
PATH_LANE_BYTES = 64


def is_cuda() -> bool:
    return mi.variant().startswith("cuda")


def default_memory_budget() -> int:
    """The memory budget ``memory_budget=0`` (auto) means on this backend."""
    if not is_cuda():
        return CPU_MEMORY_BUDGET
    low, high = GPU_MEMORY_BUDGET
    return min(high, max(low, gpu_memory() // 4))


@functools.lru_cache(maxsize=None)
def gpu_memory() -> int:
    """Total memory of CUDA device 0 in bytes (0 where the driver does not say);
    Dr.Jit does not report it, so the CUDA driver is asked directly."""
    try:
        cuda = ctypes.CDLL("libcuda.so.1")
    except OSError:
        return 0
    total = ctypes.c_size_t(0)
    if cuda.cuInit(0) != 0 or cuda.cuDeviceTotalMem_v2(ctypes.byref(total), 0) != 0:
        return 0
    return int(total.value)


def path_pass_lanes(memory_budget: int) -> int:
    """Lanes of a pass of Mitsuba's path under ``memory_budget``."""
    cap = PATH_PASS_LANES["cuda" if is_cuda() else "llvm"]
    return max(1024, min(cap, memory_budget // PATH_LANE_BYTES))


# Dr.Jit's CPU backend reads a NumPy array in place, and a kernel that loads it is
# compiled for the address's alignment ("align 64" or "align 1"): arrays in NumPy's
# memory, aligned at random, made the kernels that read them differ from render to
# render, compiled anew for a new seed (tests/test_mlt.py).
ALIGN = 64


def device_array(cls, values: np.ndarray):
    """``cls(values)`` read from a copy of ``values`` aligned to ALIGN bytes, as
    Dr.Jit's own buffers are, so that the kernels reading it do not depend on where
    NumPy put ``values``."""
    values = np.ascontiguousarray(values)
    raw = np.empty(values.nbytes + ALIGN, dtype=np.uint8)
    start = -raw.ctypes.data % ALIGN
    aligned = raw[start:start + values.nbytes].view(values.dtype).reshape(values.shape)
    aligned[...] = values
    return cls(aligned)


def read_values(*values) -> list:
    """Width-1 device values (sums, counts) read to the host in one copy: a read is a
    sync on a GPU, and a decision reads several."""
    f64 = dr.float64_array_t(mi.Float)
    out = dr.zeros(f64, len(values))
    for i, value in enumerate(values):
        dr.scatter(out, f64(value), i)
    return out.numpy().tolist()
