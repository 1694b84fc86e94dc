"""``bdpt render``: progressive rendering with checkpoints, a time budget and stops."""
from __future__ import annotations

import contextlib
import signal
import time
from pathlib import Path

from ..settings import PARAMS
from .errors import CLIError, eprint, one_line
from .images import check_writable, contact_sheet, output_path, write_png
from .progress import Progress, exit_status, fmt_rate, fmt_time
from .scene import (check_sensor_index, integrator_defaults, load_scene, make_renderer,
                    scene_params, scene_path, setup_variant)


class Outputs:
    """The files a render writes (EXR, PNG preview, strategy images), each replaced
    atomically; ``write`` returns one line per file that could not be written."""

    def __init__(self, out: Path, strategy_images: bool):
        self.exr, self.png = out, out.with_suffix(".png")
        self.strategy_images = strategy_images
        self.layers_exr = out.with_suffix(".strategies.exr")
        self.sheet_png = out.with_suffix(".strategies.png")
        self.meta = {}
        self._warned = None

    def save(self, renderer, final: bool):
        """Write the image of the passes done.  A checkpoint that cannot be written
        is reported (once per distinct problem) and rendering goes on; the final
        write must succeed."""
        res = renderer.result()
        self.meta.update(spp=res.spp, passes=res.passes, render_time=float(res.time),
                         samples_per_pass=max(p[2] for p in renderer.plan),
                         budget=res.stats["budget"], budget_decision=res.stats["decision"],
                         **{k: res.stats[k] for k in ("cost_counts", "unit_costs") if k in res.stats})
        failed = "; ".join(self.write(res, self.meta))
        if failed and final:
            raise CLIError("%s (the render of %d spp was not saved there)" % (failed, res.spp))
        if failed and failed != self._warned:
            eprint("bdpt: warning: checkpoint at %d spp not saved: %s; rendering goes on"
                   % (res.spp, failed))
        self._warned = failed or None
        return res

    @property
    def paths(self) -> list:
        extra = [self.layers_exr, self.sheet_png] if self.strategy_images else []
        return [self.exr, self.png] + extra

    def write(self, res, meta) -> list:
        from ..exr import write_exr, write_layers
        jobs = [(self.exr, lambda p: write_exr(p, res.image, meta, channels=res.channels)),
                (self.png, lambda p: write_png(p, res.image[..., :len(res.channels) - len(res.aov_names)]))]
        if self.strategy_images:
            layers = {"s%dt%d" % st: img for st, img in sorted(res.strategy_images.items())}
            # Longer paths: one layer per length; "k<DEEP_K+1>+" holds all longer ones.
            from ..strategies import DEEP_K
            layers.update({"k%d%s" % (k, "+" if k > DEEP_K else ""): img
                           for k, img in sorted(res.length_images.items())})
            if res.merge_image is not None:       # every merge (merging, merge.py)
                layers["merge"] = res.merge_image
            jobs.append((self.layers_exr,
                         lambda p: write_layers(p, layers, meta, image=res.image)))
            if res.strategy_images:
                jobs.append((self.sheet_png,
                             lambda p: write_png(p, contact_sheet(res.strategy_images))))
        failed = []
        for path, job in jobs:
            try:
                job(path)
            except Exception as e:  # a full disk, a path turned into a directory, ...
                reason = e.strerror if isinstance(e, OSError) and e.strerror else one_line(e)
                failed.append("cannot write %s: %s" % (path, reason))
        return failed


def _settings(args, scene) -> dict:
    """The scene integrator's settings, overridden by the options given."""
    settings, _ = integrator_defaults(scene)
    given = {p.name: getattr(args, p.name) for p in PARAMS}
    settings.update({k: v for k, v in given.items() if v is not None})
    return settings


def _renderer(args, scene, settings, workers: int = 1):
    """The renderer; with --time, --checkpoint or --cluster, many small passes (never
    more per pass than the memory budget allows), so that all are honoured closely
    and every worker has passes to render (cluster.small_pass_spp)."""
    from ..cluster import small_pass_spp
    settings = dict(settings)
    chose_pass_size = "samples_per_pass" in settings
    settings.setdefault("samples_per_pass", 0)
    make = lambda: make_renderer(scene, args.sensor, args.spp, args.seed,  # noqa: E731
                                 args.strategy_images, settings)
    renderer = make()
    many = args.time is not None or args.checkpoint is not None or args.cluster is not None
    per_pass = small_pass_spp(renderer, args.variant, workers) if many else None
    if per_pass is not None and not chose_pass_size:
        settings["samples_per_pass"] = per_pass
        renderer = make()
    return renderer


def _cluster(args, path, stop):
    """The Ray cluster of --cluster, not yet started, or None: a bad address, or no
    Ray installed, fails before the scene is loaded."""
    if args.cluster is None:
        return None
    from ..cluster import Cluster, ClusterError, parse_address
    try:
        address = parse_address(args.cluster)
    except ValueError as e:
        raise CLIError("--cluster: %s" % one_line(e), 2) from None
    try:
        return Cluster(address, path, args.variant, log=lambda m: eprint("bdpt: " + m),
                       poll=stop.check)
    except ClusterError as e:
        raise CLIError(str(e)) from None


@contextlib.contextmanager
def _cluster_errors():
    from ..cluster import ClusterError
    try:
        yield
    except ClusterError as e:
        raise CLIError(one_line(e)) from None


def _metadata(args, path: Path, params: dict, renderer, cluster=None) -> dict:
    """The EXR header: what the image is (spp, passes and time are updated as it grows)."""
    from .. import __version__
    meta = {"spp": 0, "seed": args.seed, "bdpt_version": __version__,
            "scene": str(path.resolve()),
            "scene_params": ",".join("%s=%s" % kv for kv in sorted(params.items())),
            "sensor": args.sensor, "passes": 0, "render_time": 0.0,
            "variant": args.variant, "spp_requested": renderer.spp}
    for p in PARAMS:
        value = getattr(renderer.settings, p.name)
        if p.name == "technique":
            value = "all" if value is None else "%d,%d" % value
        meta[p.name] = int(value) if p.kind is bool else value
    meta["samples_per_pass"] = max(p[2] for p in renderer.plan)
    meta["memory_budget"] = renderer.memory_budget     # "auto" as resolved on this machine
    if cluster is not None:
        meta.update(cluster=args.cluster, workers=cluster.size)
    return meta


def _announce(path: Path, renderer, args, cluster=None) -> None:
    depth, technique = renderer.settings.max_depth, renderer.settings.technique
    w, h = (int(x) for x in renderer.sensor.film().crop_size())
    passes = len(renderer.plan)
    eprint("bdpt: rendering %s (%dx%d, %d spp in %d pass%s, max_depth %s%s%s, seed %d, %s)%s"
           % (path.name, w, h, renderer.spp, passes, "" if passes == 1 else "es",
              "unbounded" if depth < 0 else depth,
              "" if technique is None else ", technique %d,%d" % technique,
              ", sensor %d" % args.sensor if args.sensor else "", args.seed, args.variant,
              "" if cluster is None else " on %d workers (%s)" % (cluster.size, args.cluster)))


def _stop_text(run) -> str:
    """What the first Ctrl-C does, said when it arrives."""
    whole = len({p[1] for p in run.plan}) == 1 and run.plan[0][1] == run.pixels
    if hasattr(run, "wind_down"):       # a cluster: several passes are in flight
        return "stopping after the passes in flight" + ("" if whole else
                                                         " and the rest of their round")
    return ("stopping after the current pass" if whole
            else "stopping once every pixel has its samples of this round")


def _render_loop(run, args, stop, save) -> tuple:
    """Run passes until done, stopped (signal, time budget); checkpoint on the way.
    ``run`` is the Renderer, or a cluster.ClusterRun, which on a stop finishes the
    passes it has in flight.  Returns why it stopped early (or None) and the time it
    took."""
    progress = Progress(run, budget=args.time, enabled=not args.quiet)
    stop.announce = None if args.quiet else _stop_text(run)
    t0 = last_checkpoint = time.perf_counter()
    reason = None
    while not run.done:
        run.run_pass()
        now = time.perf_counter()
        progress.update(now - t0)
        if run.done:
            break
        if reason is not None or not run.at_round_end:
            continue          # stops and checkpoints wait for every pixel's samples
        if stop.signal is not None:
            reason = "interrupted"
        elif args.time is not None and now - t0 >= args.time:
            reason = "time"
        if reason:
            if not getattr(run, "wind_down", lambda: False)():
                break
            continue
        if args.checkpoint is not None and now - last_checkpoint >= args.checkpoint:
            save(run, final=False)
            last_checkpoint = time.perf_counter()
    progress.finish()
    return reason, time.perf_counter() - t0


def _report(res, renderer, outputs, reason, wall, stop, args) -> None:
    import numpy as np
    if reason is not None and res.passes == len(renderer.plan):
        reason = None                   # a cluster finished every pass while stopping
    if not np.all(np.isfinite(res.image)):
        eprint("bdpt: warning: the image has %d non-finite values"
               % int(np.size(res.image) - np.isfinite(res.image).sum()))
    if reason == "interrupted":
        eprint("bdpt: interrupted (%s) after %d of %d spp (%d of %d passes); wrote the "
               "image of the passes done" % (signal.Signals(stop.signal).name, res.spp,
                                             renderer.spp, res.passes, len(renderer.plan)))
    elif stop.signal is not None:
        eprint("bdpt: %s arrived during the last pass; the image is complete"
               % signal.Signals(stop.signal).name)
    elif reason == "time":
        eprint("bdpt: time budget of %s used up after %d of %d spp"
               % (fmt_time(args.time), res.spp, renderer.spp))
    if not args.quiet:
        eprint("bdpt: budget %s (%s)" % (res.stats["budget"], res.stats["decision"]))
    w, h = (int(x) for x in renderer.sensor.film().crop_size())
    rate = res.spp * renderer.pixels / wall if wall > 0 else 0.0
    workers, rerun = res.stats.get("workers"), res.stats.get("passes_rerun", 0)
    where = "" if workers is None else " on %d workers%s" % (
        workers, "" if not rerun else " (%d pass%s run again)" % (rerun, "" if rerun == 1 else "es"))
    print("bdpt: %dx%d, %d spp (%d pass%s) in %s, %ssamples/s%s -> %s"
          % (w, h, res.spp, res.passes, "" if res.passes == 1 else "es", fmt_time(wall),
             fmt_rate(rate), where, ", ".join(map(str, outputs.paths))), flush=True)


def run(args, stop) -> int:
    """Render; exit status 0, or 128 + the signal's number if SIGINT or SIGTERM
    stopped it (after writing the image of the passes done)."""
    path = scene_path(args.scene)
    outputs = Outputs(output_path(args.output, path), args.strategy_images)
    check_writable(outputs.paths)
    cluster = _cluster(args, path, stop)
    mi = setup_variant(args.variant)
    params = scene_params(args)
    scene = load_scene(mi, path, params)
    check_sensor_index(scene, args.sensor)
    settings = _settings(args, scene)
    workers = (cluster.size or 1) if cluster is not None else 1
    renderer = _renderer(args, scene, settings, workers)
    stop.check()
    with contextlib.ExitStack() as stack:
        run = renderer
        if cluster is not None:
            stack.enter_context(_cluster_errors())
            stack.enter_context(cluster)                 # start or join the Ray cluster
            if cluster.size != workers:
                renderer = _renderer(args, scene, settings, cluster.size)
        outputs.meta = _metadata(args, path, params, renderer, cluster)
        if not args.quiet:
            _announce(path, renderer, args, cluster)
        if cluster is not None:
            run = cluster.start(renderer, params, args.sensor)
            if not args.quiet:
                eprint("bdpt: %d workers ready after %s" % (cluster.size, fmt_time(cluster.startup)))
        reason, wall = _render_loop(run, args, stop, outputs.save)
        res = outputs.save(run, final=True)
    _report(res, renderer, outputs, reason, wall, stop, args)
    return 0 if stop.signal is None else exit_status(stop.signal)
