"""Rendering on a Ray cluster: passes as work units, raw film sums merged exactly.

    bdpt render scene.xml --spp 1024 --cluster local:2        # 2 worker processes here
    bdpt render scene.xml --spp 1024 --cluster auto           # the cluster of `ray start`
    bdpt_drjit.render("scene.xml", spp=1024, cluster="ray://head:10001")

* Workers are Ray actors (``_Worker``): ``local:N`` starts a Ray cluster of N on this
  machine; on a running cluster there is one per GPU (``cuda_*`` variants) or one per
  node (``llvm_*``, which uses all of a node's cores).  Each loads the scene once, from
  the scene file with its parameters, and keeps one Renderer (its kernels stay warm).
* The scene's folder is shipped to the workers as the Ray job's runtime-env working
  directory (uploaded once, at most 512 MiB, .gitignore not applied); every file the
  scene uses must be inside it.  A worker that cannot load the scene stops the render
  with one error naming the worker and Mitsuba's reason.
* A work unit is a pass of the driver's plan (``Renderer.render_pass(index)``); its
  samples depend only on (seed, index).  The worker returns the pass's raw film sums
  (``FilmAccumulator.raw()``) and clears its film.  The driver adds them in float64
  in pass order (a pass that finishes early waits for those before it), so the image
  is the same estimator as one machine rendering every pass, whichever worker ran
  what, and develops once per image written (``Renderer.load_raw``, ``result``).
* A worker lost mid-pass (its process killed, its node gone) loses only that pass: it
  goes back to the front of the queue and runs again, from the same seed, on another
  worker or on the same one restarted by Ray.
* ``wind_down`` (a signal, a time budget) dispatches no more passes and finishes those
  in flight (and the rest of their round of pixel ranges), so that the passes kept are
  always a prefix 0..k-1 of the plan that gives every pixel its camera samples.
"""
from __future__ import annotations

import collections
import contextlib
import functools
import hashlib
import logging
import os
import re
import signal
import socket
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

INSTALL = "pip install 'bdpt-drjit[cluster]' (or: pip install 'ray[client]')"
RESTARTS = 3             # times Ray restarts a worker whose process died
PASS_RUNS = 3            # runs of one pass lost to dying workers before giving up
START_TIMEOUT = 300.0    # seconds for the workers to load the scene
MAX_FOLDER_BYTES = 512 * 1024 ** 2       # Ray's limit on a shipped working directory
_POLL = 0.25             # seconds between looks at a stop request while waiting
# Many small passes (a cluster, a time budget, checkpoints): at most spp/16 samples per
# pixel (spp / (4 x workers) on larger clusters) and about this many lanes per pass,
# fewer on the CPU, where a lane costs more.
SMALL_PASS_LANES = {"llvm": 1 << 16, "cuda": 1 << 20}

_log = logging.getLogger(__name__)


class ClusterError(RuntimeError):
    """A cluster render cannot start or go on; the message says why, on one line."""


# -- addresses, Ray, pass sizes --------------------------------------------------------
@dataclass(frozen=True)
class Address:
    kind: str            # "local" (start one here), "auto" or "remote" (connect)
    text: str
    workers: int = 0     # local: the number of worker processes


def parse_address(text) -> Address:
    """``local:N``, ``auto``, ``ray://HOST:PORT`` (Ray client) or ``HOST:PORT`` (the
    head's GCS, from a node of the cluster)."""
    text = str(text).strip()
    m = re.fullmatch(r"local:(\d+)", text)
    if m and int(m.group(1)) >= 1:
        return Address("local", text, int(m.group(1)))
    if text == "auto":
        return Address("auto", text)
    if re.fullmatch(r"(ray://)?[\w.-]+:\d+", text) and not text.startswith("local"):
        return Address("remote", text)
    raise ValueError("bdpt: the cluster address must be local:N (a Ray cluster of N worker "
                     "processes on this machine), auto (the Ray cluster this machine is part "
                     "of) or a Ray address such as ray://HOST:10001, got %r" % text)


def check_reachable(address: Address, timeout: float = 5.0) -> None:
    """Fail at once if nothing listens at a HOST:PORT address: Ray itself retries for
    minutes."""
    host, port = re.fullmatch(r"(?:ray://)?([\w.-]+):(\d+)", address.text).groups()
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as e:
        raise ClusterError("nothing answers at %s (%s): is a Ray head running there ('ray "
                           "start --head')?" % (address.text, e.strerror or e)) from None


def import_ray():
    try:
        import ray
    except ImportError as e:
        raise ClusterError("rendering on a cluster needs Ray, which is not installed (%s): %s"
                           % (e, INSTALL)) from None
    return ray


def small_pass_spp(renderer, variant: str, workers: int = 1) -> int | None:
    """Samples per pixel per pass for many small passes (see SMALL_PASS_LANES), never
    more than the memory budget allows; None where the plan stays as it is (it has such
    passes already, or it splits the film into pixel ranges)."""
    if renderer.plan[-1][1] != renderer.pixels:
        return None
    auto = max(p[2] for p in renderer.plan)
    lanes = SMALL_PASS_LANES["cuda" if variant.startswith("cuda") else "llvm"]
    per_pass = max(1, min(renderer.spp // max(16, 4 * workers), auto, lanes // renderer.pixels))
    return None if per_pass == auto else per_pass


@functools.lru_cache(maxsize=None)
def code_fingerprint() -> str:
    """A hash of the renderer's sources (bdpt_drjit and the plugin): every worker must
    run the driver's code, or the passes would not be the same estimator."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for package in ("bdpt_drjit", "integrators"):
        for path in sorted((root / package).rglob("*.py")):
            h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes())
    return h.hexdigest()[:16]


def _versions() -> dict:
    import sys

    import drjit
    import mitsuba

    from ._version import __version__
    return {"bdpt_drjit": __version__, "mitsuba": mitsuba.__version__,
            "drjit": drjit.__version__, "python": "%d.%d" % sys.version_info[:2]}


def _short(e) -> str:
    """One line from a Ray error: its innermost Python exception where there is one."""
    from .cli.errors import one_line
    cause = getattr(e, "cause", None)
    if isinstance(cause, BaseException) and cause is not e:
        return _short(cause)
    lines = [line.strip() for line in str(e).strip().splitlines() if line.strip()]
    raised = [line for line in lines if re.match(r"^[\w.]+(Error|Exception|Interrupt):", line)]
    text = one_line(raised[-1] if raised else (lines[0] if lines else type(e).__name__))
    return text if len(text) <= 400 else text[:400] + "..."


# -- the worker ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Job:
    """What a worker renders: the scene file (its name inside the shipped folder) and
    everything the driver's Renderer was made with."""
    scene: str
    params: dict
    sensor: int
    spp: int
    seed: int
    strategy_images: bool
    settings: dict
    variant: str
    threads: int | None = None        # Dr.Jit's threads (local:N shares one machine)
    folder: str = ""                  # the scene's folder on the driver (for messages)
    unit_costs: object = None         # the driver's units.UnitCosts: the pilot's worker
                                      # decides as a local render on the driver would


def _load(job: Job):
    import mitsuba as mi

    from .render import Renderer
    if mi.variant() != job.variant:
        mi.set_variant(job.variant)
    if job.threads:
        import drjit as dr
        dr.set_thread_count(job.threads)
    path = Path.cwd() / job.scene
    if not path.is_file():
        raise FileNotFoundError("the scene file %s is not in the folder shipped to it (%s)"
                                % (job.scene, Path.cwd()))
    from .support import load_file
    scene = load_file(path, **job.params)
    renderer = Renderer(scene, sensor=job.sensor, spp=job.spp, seed=job.seed,
                        strategy_images=job.strategy_images, unit_costs=job.unit_costs,
                        reuse_pilot=False, **job.settings)
    renderer.redecide = False     # every worker renders the driver's plan, fixed before
    return renderer               # the pilot


class _Worker:
    """A Ray actor (``ray.remote`` is applied by Cluster, so that this module imports
    without Ray): loads the scene once, then renders passes, returning raw film sums.
    A failure to load is returned, not raised, so the driver can say it in one line."""

    def __init__(self, job: Job):
        self.host, self.pid = socket.gethostname(), os.getpid()
        self.renderer = self.error = None
        start = time.perf_counter()
        try:
            self.renderer = _load(job)
        except Exception as e:
            # Name files as the driver knows them, not by the copy's path.
            self.error = _short(e).replace(str(Path.cwd()), job.folder or str(Path.cwd()))
        self.load_time = time.perf_counter() - start

    def info(self) -> dict:
        r = self.renderer
        return {"host": self.host, "pid": self.pid, "error": self.error,
                "load_time": self.load_time, "plan": None if r is None else list(r.plan),
                "code": code_fingerprint(), "versions": _versions(),
                "package": str(Path(__file__).parent)}

    def render(self, index: int, budget=None) -> dict:
        """Pass ``index`` with the driver's ``budget`` (None: the renderer's own)."""
        if budget is not None:
            self.renderer.budget = budget
        return self._passes([index])

    def pilot(self) -> dict:
        """The pilot pass of an "auto" budget, which chooses the budget from what it
        rendered (optimizer.py); the choice goes back with it."""
        from .optimizer import Pilot
        out = self._passes(range(Pilot.PASSES))
        if "raw" in out:
            out["decision"] = self.renderer.pilot.decision
            out["costs"] = self.renderer.pilot.costs
        return out

    def _passes(self, indices) -> dict:
        if self.error is not None:
            return {"error": self.error, "pid": self.pid}
        r = self.renderer
        start, rays = time.perf_counter(), r.rays
        for index in indices:
            r.render_pass(index)
        raw = r.film.raw()
        r.film.clear()
        return {"raw": raw, "time": time.perf_counter() - start, "rays": r.rays - rays,
                "pid": self.pid, "passes": len(indices)}


# -- the driver -------------------------------------------------------------------------
@dataclass(eq=False)
class _Slot:
    """The driver's view of one worker."""
    number: int
    handle: object
    host: str = "?"
    pid: int = 0
    busy: object = None          # the ObjectRef of its pass (or probe) in flight
    deaths: int = 0
    restarting: bool = False     # lost; probed (``info``) until it answers
    retry_at: float = 0.0
    dead: bool = False

    @property
    def name(self) -> str:
        return "worker %d (%s, pid %d)" % (self.number, self.host, self.pid)


@contextlib.contextmanager
def _for_ray_init(env: dict):
    """Environment variables ray.init reads, and this process's SIGINT/SIGTERM
    handlers kept: ray.init installs a SIGTERM handler that exits at once, and the
    command line stops between passes instead."""
    old_env = {k: os.environ.get(k) for k in env}
    handlers = {}
    if threading.current_thread() is threading.main_thread():
        handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    os.environ.update(env)
    try:
        yield
    finally:
        for k, v in old_env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        for s, h in handlers.items():
            if h is not None:
                signal.signal(s, h)


def _quiet_worker_deaths():
    """Ray's driver prints a worker's death on stdout, in many lines ("(raylet) A worker
    died or was killed ..."); the run says it in one line on stderr instead, so Ray's
    text goes to this module's debug log.  Patches Ray's private printer (if it has
    it); returns what undoes that."""
    try:
        from ray._private import worker as ray_worker
        original = ray_worker.print_to_stdstream
    except (ImportError, AttributeError):
        return lambda: None

    def printer(data, *args, **kwargs):
        if data.get("pid") == "raylet":
            _log.debug("ray: %s", " ".join(map(str, data.get("lines", []))))
        else:
            original(data, *args, **kwargs)

    ray_worker.print_to_stdstream = printer

    def restore():
        ray_worker.print_to_stdstream = original
    return restore


def _check_folder(folder: Path) -> None:
    total = 0
    for dirpath, _, filenames in os.walk(folder):
        for name in filenames:
            with contextlib.suppress(OSError):
                total += os.path.getsize(os.path.join(dirpath, name))
            if total > MAX_FOLDER_BYTES:
                raise ClusterError(
                    "the scene's folder %s holds more than %d MiB, and the workers get a "
                    "copy of all of it (Ray ships at most %d MiB): put the scene and its "
                    "files in a folder of their own" % (folder, MAX_FOLDER_BYTES >> 20,
                                                         MAX_FOLDER_BYTES >> 20))


class Cluster:
    """A Ray cluster and bdpt's workers on it (a context manager: leaving it ends the
    workers, and the Ray cluster if it started one).

    ``connect`` starts or joins the cluster, shipping the scene's folder;
    ``size`` is the number of workers it will run; ``start`` loads the scene on them
    and returns the ``ClusterRun`` that renders a Renderer's plan.  ``poll`` is called
    while waiting (the command line's stop check); ``log`` gets one-line notices."""

    def __init__(self, address, scene_path, variant: str, log=None, poll=None,
                 start_timeout: float = START_TIMEOUT):
        self.address = address if isinstance(address, Address) else parse_address(address)
        self.scene_path = Path(scene_path).resolve()
        self.variant = variant
        self.log = log or _log.warning
        self.poll = poll or (lambda: None)
        self.start_timeout = start_timeout
        self.ray = import_ray()
        self.owns = False
        self._restore_printing = lambda: None
        self.slots: list[_Slot] = []
        self.size = self.address.workers
        self.startup = 0.0

    def __enter__(self) -> "Cluster":
        try:
            self.connect()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> bool:
        self.close()
        return False

    # -- connecting ----------------------------------------------------------------
    def connect(self) -> None:
        ray, a = self.ray, self.address
        if ray.is_initialized():
            raise ClusterError("Ray is already initialized in this process; bdpt connects "
                               "itself, to ship the scene's folder with the job: call "
                               "ray.shutdown() first")
        folder = self.scene_path.parent
        _check_folder(folder)
        runtime_env = {"working_dir": str(folder)}
        kwargs = {"log_to_driver": False, "logging_level": logging.ERROR}
        env = {"RAY_RUNTIME_ENV_IGNORE_GITIGNORE": "1"}     # ship every asset
        if a.kind == "local":
            # Workers import this checkout of bdpt_drjit, as the driver does.
            root = str(Path(__file__).resolve().parents[1])
            runtime_env["env_vars"] = {"PYTHONPATH": os.pathsep.join(
                [root] + [p for p in [os.environ.get("PYTHONPATH")] if p])}
            kwargs.update(num_cpus=a.workers, include_dashboard=False,
                          _node_ip_address="127.0.0.1")
            # Every Ray process of it on 127.0.0.1 (otherwise they also listen on, and
            # report, this machine's network address).
            env.update(RAY_USAGE_STATS_ENABLED="0", RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER="0")
        else:
            if a.kind == "remote":
                check_reachable(a)
            kwargs["address"] = a.text
        start = time.perf_counter()
        try:
            with _for_ray_init(env):
                ray.init(runtime_env=runtime_env, **kwargs)
        except Exception as e:
            with contextlib.suppress(Exception):
                ray.shutdown()                  # whatever ray.init had started
            what = ("start a local Ray cluster" if a.kind == "local" else
                    "connect to the Ray cluster at %s" % a.text)
            hint = ("" if a.kind == "local" else " (start one with 'ray start --head', or "
                    "render with --cluster local:N)")
            raise ClusterError("cannot %s: %s%s" % (what, _short(e), hint)) from None
        self.owns = True
        self._restore_printing = _quiet_worker_deaths()
        self.startup = time.perf_counter() - start
        if a.kind != "local":
            self.size = len(self._placements())
            if self.size == 0:
                raise ClusterError("the Ray cluster at %s has no %s for a worker"
                                   % (a.text, "GPU" if self.variant.startswith("cuda")
                                      else "node with a CPU"))

    def _placements(self) -> list:
        """Ray options of each worker on a running cluster: one per GPU, or one per node
        with a CPU (Dr.Jit's LLVM backend uses every core of its node)."""
        ray = self.ray
        if self.variant.startswith("cuda"):
            gpus = int(ray.cluster_resources().get("GPU", 0))
            return [{"num_gpus": 1, "num_cpus": 1}] * gpus
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy
        return [{"num_cpus": 1, "scheduling_strategy": NodeAffinitySchedulingStrategy(
                    node["NodeID"], soft=False)}
                for node in ray.nodes()
                if node.get("Alive") and node.get("Resources", {}).get("CPU", 0) >= 1]

    # -- workers -------------------------------------------------------------------
    def start(self, renderer, params: dict, sensor: int = 0) -> "ClusterRun":
        """Start the workers, each loading the scene into a Renderer like ``renderer``
        (same plan), and wait until all are ready."""
        ray, a = self.ray, self.address
        threads = max(1, (os.cpu_count() or 1) // a.workers) if a.kind == "local" else None
        job = Job(scene=self.scene_path.name, params=dict(params), sensor=int(sensor),
                  spp=renderer.spp, seed=renderer.seed,
                  strategy_images=bool(renderer.strategy_images),
                  # The budget resolved here: "auto" follows each machine's memory.
                  settings=dict(renderer.settings.as_dict(),
                                memory_budget=renderer.memory_budget),
                  variant=self.variant, threads=threads,
                  folder=str(self.scene_path.parent),
                  unit_costs=renderer.pilot.costs.units if renderer.pilot else None)
        placements = ([{"num_cpus": 1}] * a.workers if a.kind == "local"
                      else self._placements()[:self.size])
        actor = ray.remote(_Worker)
        start = time.perf_counter()
        for number, options in enumerate(placements):
            handle = actor.options(max_restarts=RESTARTS, max_task_retries=0,
                                   **options).remote(job)
            self.slots.append(_Slot(number, handle))
        self._wait_ready(renderer)
        self.startup += time.perf_counter() - start
        return ClusterRun(self, renderer)

    def _wait_ready(self, renderer) -> None:
        ray = self.ray
        pending = {slot.handle.info.remote(): slot for slot in self.slots}
        deadline = time.perf_counter() + self.start_timeout
        mine = {"code": code_fingerprint(), "versions": _versions()}
        while pending:
            self.poll()
            if time.perf_counter() > deadline:
                raise ClusterError(
                    "%d of %d workers were not ready after %d s (the cluster has %s; each "
                    "worker needs %s)" % (len(pending), len(self.slots), self.start_timeout,
                                          ray.cluster_resources(),
                                          "a GPU" if self.variant.startswith("cuda")
                                          else "a CPU"))
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=_POLL)
            for ref in ready:
                slot = pending.pop(ref)
                try:
                    info = ray.get(ref)
                except ray.exceptions.RuntimeEnvSetupError as e:
                    raise ClusterError("worker %d could not get the scene's folder %s: %s"
                                       % (slot.number, self.scene_path.parent, _short(e))) from None
                except ray.exceptions.RayError as e:
                    raise ClusterError("worker %d failed to start (is bdpt-drjit installed on "
                                       "every node?): %s" % (slot.number, _short(e))) from None
                slot.host, slot.pid = info["host"], info["pid"]
                self._check_worker(slot, info, mine, renderer)

    def _check_worker(self, slot, info, mine, renderer) -> None:
        if info["error"]:
            raise ClusterError(
                "%s could not load the scene: %s (workers load %s from a copy of its folder "
                "%s, shipped by Ray: every file the scene uses must be inside that folder)"
                % (slot.name, info["error"], self.scene_path.name, self.scene_path.parent))
        if info["versions"] != mine["versions"] or info["code"] != mine["code"]:
            raise ClusterError(
                "%s runs other code than this driver: %s (bdpt_drjit in %s, sources %s) "
                "against %s (sources %s); install the same bdpt-drjit, Mitsuba and Dr.Jit "
                "on every node" % (slot.name, info["versions"], info["package"], info["code"],
                                   mine["versions"], mine["code"]))
        if [tuple(p) for p in info["plan"]] != [tuple(p) for p in renderer.plan]:
            raise ClusterError("%s planned other passes than the driver (%d against %d)"
                               % (slot.name, len(info["plan"]), len(renderer.plan)))

    def close(self) -> None:
        ray = self.ray
        for slot in self.slots:
            with contextlib.suppress(Exception):
                ray.kill(slot.handle, no_restart=True)
        self.slots = []
        if self.owns:
            self.owns = False
            self._restore_printing()
            with contextlib.suppress(Exception):
                ray.shutdown()


@dataclass
class _Sums:
    """The raw film sums of passes 0..passes-1, added in float64 in pass order."""
    raw: dict | None = None
    passes: int = 0
    time: float = 0.0
    rays: int = 0

    def add(self, out: dict) -> None:
        raw = out["raw"]
        if self.raw is None:
            self.raw = {k: (int(v) if k == "camera_samples" else np.array(v, np.float64))
                        for k, v in raw.items()}
        else:
            for k, v in raw.items():
                if k == "camera_samples":
                    self.raw[k] += int(v)
                else:
                    np.add(self.raw[k], v, out=self.raw[k])
        self.passes += out.get("passes", 1)
        self.time += out["time"]
        self.rays += out["rays"]


class ClusterRun:
    """The passes of a Renderer's plan, rendered by a Cluster's workers.  It is driven
    as a Renderer is (``run_pass`` until ``done``, ``at_round_end``, ``result``);
    ``passes_done`` and ``spp_done`` count the prefix of passes merged."""

    def __init__(self, cluster: Cluster, renderer):
        self.cluster, self.renderer = cluster, renderer
        self.plan, self.pixels, self.spp = renderer.plan, renderer.pixels, renderer.spp
        self._spp_at = [0.0]                  # spp after the first k passes
        for index in range(len(self.plan)):
            self._spp_at.append(self._spp_at[-1] + renderer.pass_spp(index))
        self.limit = len(self.plan)           # passes to merge (lowered by wind_down)
        self.queue = collections.deque(range(len(self.plan)))
        # An "auto" budget: the pilot pass goes to one worker (index 0); the other
        # passes wait for the budget it chooses.
        self.pilot = renderer.pilot is not None
        if self.pilot:
            from .optimizer import Pilot
            self.queue = collections.deque([0] + list(range(Pilot.PASSES, len(self.plan))))
        self.budget = None if self.pilot else renderer.budget
        self.in_flight = {}                   # ObjectRef -> (slot, index, time sent)
        self.finished = {}                    # index -> a worker's result, past the prefix
        self.sums = _Sums()
        self.runs_lost = collections.Counter()
        self.overheads = []                   # per pass: round trip - the worker's time
        self.merge_time = 0.0                 # the driver's float64 additions
        # Passes past the prefix held at most: bounds the driver's memory.
        self.window = max(8, 3 * len(cluster.slots))

    # -- the Renderer's protocol ----------------------------------------------------
    @property
    def passes_done(self) -> int:
        return self.sums.passes

    @property
    def spp_done(self) -> float:
        return self._spp_at[self.sums.passes]

    @property
    def done(self) -> bool:
        return self.sums.passes >= self.limit

    @property
    def at_round_end(self) -> bool:
        return self.renderer.is_round_end(self.sums.passes, self.spp_done)

    @property
    def workers_alive(self) -> int:
        return sum(not s.dead and not s.restarting for s in self.cluster.slots)

    @property
    def passes_rerun(self) -> int:
        return sum(self.runs_lost.values())

    def run_pass(self) -> None:
        """Keep every worker busy; return once the prefix of passes merged has grown
        (or a worker was lost)."""
        ray = self.cluster.ray
        merged, lost = self.sums.passes, self.passes_rerun
        while not self.done:
            self._dispatch()
            if not self.in_flight and any(s.restarting and not s.dead
                                          for s in self.cluster.slots):
                time.sleep(_POLL)
                continue
            if not self.in_flight:
                raise ClusterError("all %d workers were lost; %d of %d passes were done"
                                   % (len(self.cluster.slots), self.sums.passes, len(self.plan)))
            ready, _ = ray.wait(list(self.in_flight), num_returns=1, timeout=_POLL)
            if ready:
                more, _ = ray.wait(list(self.in_flight), num_returns=len(self.in_flight),
                                   timeout=0)
                for ref in set(ready) | set(more):
                    self._collect(ref)
                self._merge()
                if self.sums.passes > merged or self.passes_rerun > lost:
                    return

    def wind_down(self) -> bool:
        """Send no more passes: finish those sent (and the rest of their round of pixel
        ranges); True while there are passes left to wait for."""
        sent = [i for _, i, _ in self.in_flight.values()] + list(self.finished)
        end = max(sent) + 1 if sent else self.sums.passes
        while not self.renderer.is_round_end(end, self._spp_at[end]):
            end += 1
        self.limit = min(self.limit, end)
        return not self.done

    def result(self):
        """The image of the passes merged (the same as a Renderer's after them)."""
        s = self.sums
        self.renderer.load_raw(s.raw, s.passes, s.time, s.rays)
        res = self.renderer.result()
        res.stats.update(workers=len(self.cluster.slots), passes_rerun=self.passes_rerun,
                         startup=self.cluster.startup,
                         overhead_per_pass=float(np.mean(self.overheads)) if self.overheads else 0.0)
        return res

    # -- passes ---------------------------------------------------------------------------
    def _dispatch(self) -> None:
        """A pass to every idle worker; a worker being restarted gets a probe (``info``)
        instead, and passes again once it answers."""
        now = time.perf_counter()
        for slot in self.cluster.slots:
            if slot.dead or slot.busy is not None:
                continue
            if slot.restarting:
                if now >= slot.retry_at:
                    self._send(slot, None, slot.handle.info.remote())
                continue
            if not self.queue:
                continue
            index = self.queue[0]
            if (index >= self.limit or index >= self.sums.passes + self.window
                    or (index > 0 and self.budget is None)):
                continue
            self.queue.popleft()
            if index == 0 and self.pilot:
                self._send(slot, index, slot.handle.pilot.remote())
            else:
                self._send(slot, index, slot.handle.render.remote(index, self.budget))

    def _send(self, slot, index, ref) -> None:
        slot.busy = ref
        self.in_flight[ref] = (slot, index, time.perf_counter())

    def _collect(self, ref) -> None:
        ray = self.cluster.ray
        slot, index, sent = self.in_flight.pop(ref)
        slot.busy = None
        try:
            out = ray.get(ref)
        except ray.exceptions.RayTaskError as e:
            raise ClusterError("pass %d failed on %s: %s" % (index, slot.name, _short(e))) from None
        except ray.exceptions.RayError as e:     # the worker died: its process, its node
            if index is None:
                self._probe_failed(slot, e)
            else:
                self._lost(slot, index, e)
            return
        if out.get("error"):
            raise ClusterError("%s could not load the scene after a restart: %s"
                               % (slot.name, out["error"]))
        slot.pid, slot.restarting = out["pid"], False
        if index is not None:
            self.overheads.append(time.perf_counter() - sent - out["time"])
            self.finished[index] = out
        if out.get("decision") is not None:
            self._decided(out["decision"], out["costs"])

    def _decided(self, decision, costs) -> None:
        """The pilot's choice of budget and what it priced: the driver's renderer
        reports them."""
        self.budget = self.renderer.budget = decision.budget
        self.renderer.pilot.decision = decision
        self.renderer.pilot.costs = costs

    def _lost(self, slot, index: int, error) -> None:
        self.runs_lost[index] += 1
        slot.deaths += 1
        slot.restarting, slot.retry_at = True, time.perf_counter()
        if self.runs_lost[index] >= PASS_RUNS:
            raise ClusterError("pass %d was lost %d times: the workers running it died (last: "
                               "%s: %s)" % (index, PASS_RUNS, slot.name, _short(error)))
        self.queue.appendleft(index)
        self.cluster.log("%s was lost during pass %d (%s); the pass runs again on the next "
                         "free worker" % (slot.name, index, type(error).__name__))

    def _probe_failed(self, slot, error) -> None:
        """A worker being restarted did not answer: Ray is still restarting it, or gave
        up (its restarts used up, its node gone)."""
        if isinstance(error, self.cluster.ray.exceptions.ActorDiedError) or slot.deaths > RESTARTS:
            slot.dead = True
            self.cluster.log("%s is gone (%s); %d workers left"
                             % (slot.name, _short(error), self.workers_alive))
        else:
            slot.retry_at = time.perf_counter() + _POLL

    def _merge(self) -> None:
        start = time.perf_counter()
        while self.sums.passes in self.finished and self.sums.passes < self.limit:
            self.sums.add(self.finished.pop(self.sums.passes))
        self.merge_time += time.perf_counter() - start


def render_on_cluster(scene, cluster, spp: int | None = None, seed: int = 0, sensor: int = 0,
                      strategy_images: bool = False, scene_params: dict | None = None,
                      **settings):
    """``bdpt_drjit.render(..., cluster=ADDRESS)``: ``scene`` must be an XML file path
    (the workers load it themselves, from a copy of its folder); without
    ``samples_per_pass`` the plan has many small passes (``small_pass_spp``)."""
    if not isinstance(scene, (str, os.PathLike)):
        raise TypeError("bdpt: rendering on a cluster needs the scene's file path (workers "
                        "load it themselves, from a copy of its folder), not a loaded "
                        "mi.Scene: pass the path, and its parameters as scene_params")
    import mitsuba as mi

    from .render import Renderer
    address = parse_address(cluster)
    import_ray()
    params = dict(scene_params or {})
    from .support import load_file
    loaded = load_file(scene, **params)

    def make(workers):
        r = Renderer(loaded, sensor=sensor, spp=spp, seed=seed,
                     strategy_images=strategy_images, reuse_pilot=False, **settings)
        per_pass = None if "samples_per_pass" in settings else small_pass_spp(r, mi.variant(), workers)
        if per_pass is None:
            return r
        return Renderer(loaded, sensor=sensor, spp=spp, seed=seed,
                        strategy_images=strategy_images, reuse_pilot=False,
                        **dict(settings, samples_per_pass=per_pass))

    make(address.workers or 1)          # a bad setting fails before Ray starts
    with Cluster(address, scene, mi.variant()) as c:
        run = c.start(make(c.size), params, sensor)
        while not run.done:
            run.run_pass()
        return run.result()
