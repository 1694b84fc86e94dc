"""Unit costs: what a unit of the engine's work costs on this machine and variant.

The budget decision (optimizer.Costs) prices each candidate by the work its samples
do, counted in the pilot (rays of each walk, stored light vertices, connections),
times these unit costs.  Counts are a property of the scene and the seed; the units
are measured once per machine and variant by a calibration render
(render.calibrate: the Cornell box at the pilot's occupancy) and kept in a small
JSON file, as Dr.Jit keeps its kernels.  So a decision reads no clock: the same
scene, settings, seed and calibration give the same image whatever the kernel cache,
the machine's load, or how the integrator was made.

The file: ``$BDPT_CALIBRATION`` if set (a fixed file, for exact repeats and tests),
else ``bdpt-units-<variant>-<machine>.json`` under ``$XDG_CACHE_HOME/bdpt-drjit``
(``~/.cache/bdpt-drjit``).  ``bdpt calibrate`` measures again.
"""
from __future__ import annotations

import functools
import hashlib
import json
import os
import platform
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import drjit as dr
import mitsuba as mi

from ._version import __version__

FORMAT = 4         # the file's layout and calibration; a file of another is measured again

# A CPU calibration's units where other jobs kept the cores busy misprice the budgets
# for good (the file keeps them): one CPU-bound process beside it on 2 cores priced
# Mitsuba's path per ray at 0.51x the camera walk's ray against 0.87x idle, a
# connection at 0.42x against 1.77x and a stored vertex at 0 (the walks' many short
# kernels wait for a preempted worker, path's megakernel less; benchmarks/RESULTS.md,
# "Decisions").  It says so where its process had under BUSY_SHARE of the CPU time its
# threads could use: Dr.Jit's workers spin for 20 ms between kernels before they sleep,
# so an idle CPU gives them all of it (0.98-1.0 measured), one busy loop beside them
# 0.60-0.64 and two 0.49-0.50.  (The load average lags a job that just began by a minute
# and counts those just ended, such as the renders before the calibration.)
BUSY_SHARE = 0.8


@dataclass(frozen=True)
class UnitCosts:
    """Seconds of kernel time per unit of work (render.calibrate measures them)."""
    camera_ray: float = 1.0     # a ray of the camera walk with s <= 1 (extension or NEE)
    light_ray: float = 1.0      # a ray of the light walk (extension or t = 1 splat)
    stored_vertex: float = 1.0  # a light vertex stored for connections
    connection: float = 1.0     # a connection's shadow ray, its evaluations and MIS
    path_ray: float = 1.0       # a ray of Mitsuba's path (its megakernel, NEE included)
    grid_vertex: float = 1.0    # merging: a stored vertex put in the pass's hash grid
    merge_step: float = 1.0     # merging: an iteration of a query's loop (an item)

    def describe(self) -> str:
        return " ".join("%s=%.3g" % (f.name, getattr(self, f.name)) for f in fields(self))


@functools.lru_cache(maxsize=None)
def machine(variant: str) -> str:
    """What the units depend on besides the variant: the backend's device and the
    versions of the code that runs (read once per process)."""
    if variant.startswith("cuda"):
        device = "cuda:" + str(dr.detail.cuda_compute_capability()
                               if hasattr(dr.detail, "cuda_compute_capability") else "")
        for info in sorted(Path("/proc/driver/nvidia/gpus").glob("*/information")):
            device += info.read_text().split("\n", 1)[0]
            break
    else:
        device = "cpu:%s:%d" % (_cpu_model(), os.cpu_count() or 1)
    return "%s %s %s %s" % (device, __version__, mi.__version__, dr.__version__)


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def busy_warning(variant: str, cpu_share: float) -> str | None:
    """What to tell a user whose CPU calibration ran beside other jobs (BUSY_SHARE;
    ``cpu_share``: its process's CPU seconds per second of its runs and Dr.Jit thread),
    or None.  (A GPU's kernels do not share its cores with other jobs.)"""
    if not variant.startswith("llvm") or cpu_share >= BUSY_SHARE:
        return None
    return ("bdpt: the unit costs were measured while other jobs kept the CPU busy (the "
            "calibration's %d threads had %.0f%% of its time): they misprice the budgets "
            "'auto' chooses from; run 'bdpt calibrate' again on an idle machine"
            % (dr.thread_count(), 100 * cpu_share))


def path(variant: str | None = None) -> Path:
    """The calibration file the current variant uses."""
    fixed = os.environ.get("BDPT_CALIBRATION")
    if fixed:
        return Path(fixed)
    variant = variant or mi.variant()
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "bdpt-drjit"
    key = hashlib.sha1(machine(variant).encode()).hexdigest()[:10]
    return cache / ("bdpt-units-%s-%s.json" % (variant, key))


def load(variant: str | None = None) -> UnitCosts | None:
    """The stored unit costs of the variant, or None where there are none yet (or a
    file of another layout)."""
    variant = variant or mi.variant()
    try:
        data = json.loads(path(variant).read_text())
        entry = data["variants"][variant] if "variants" in data else data
        if data.get("format") != FORMAT:
            return None
        return UnitCosts(**{f.name: float(entry[f.name]) for f in fields(UnitCosts)})
    except (OSError, ValueError, KeyError, TypeError):
        return None


def save(units: UnitCosts, variant: str | None = None) -> Path:
    """Store ``units`` for the variant (beside other variants' in a fixed file)."""
    variant = variant or mi.variant()
    target = path(variant)
    data = {"format": FORMAT, "machine": machine(variant), "variants": {}}
    try:
        old = json.loads(target.read_text())
        if old.get("format") == FORMAT:
            data["variants"] = old.get("variants", {})
    except (OSError, ValueError):
        pass
    data["variants"][variant] = asdict(units)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_suffix(".tmp%d" % os.getpid())
    tmp.write_text(json.dumps(data, indent=1) + "\n")
    os.replace(tmp, target)
    return target
