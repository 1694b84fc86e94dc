"""``bdpt render``: progressive rendering with checkpoints, a time budget and stops."""
from __future__ import annotations

import signal
import time
from pathlib import Path

from ..settings import PARAMS
from .errors import CLIError, eprint, one_line
from .images import check_writable, contact_sheet, output_path, write_png
from .progress import Progress, exit_status, fmt_rate, fmt_time
from .scene import (check_sensor_index, integrator_defaults, load_scene, make_renderer,
                    scene_params, scene_path, setup_variant)

# With --time or --checkpoint and no --samples-per-pass, passes are kept small
# (at most spp/16 samples per pixel and about this many lanes, fewer on the CPU
# where a lane costs more) so there are many.
_TIMED_PASS_LANES = {"llvm": 1 << 16, "cuda": 1 << 20}


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
                         budget=res.stats["budget"], budget_decision=res.stats["decision"])
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
        jobs = [(self.exr, lambda p: write_exr(p, res.image, meta)),
                (self.png, lambda p: write_png(p, res.image))]
        if self.strategy_images:
            layers = {"s%dt%d" % st: img for st, img in sorted(res.strategy_images.items())}
            # Longer paths: one layer per length; "k<DEEP_K+1>+" holds all longer ones.
            from ..strategies import DEEP_K
            layers.update({"k%d%s" % (k, "+" if k > DEEP_K else ""): img
                           for k, img in sorted(res.length_images.items())})
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


def _renderer(args, scene, settings):
    """The renderer; with --time or --checkpoint, many small passes (never more per
    pass than the memory budget allows), so that both are honoured closely."""
    chose_pass_size = "samples_per_pass" in settings
    settings.setdefault("samples_per_pass", 0)
    make = lambda: make_renderer(scene, args.sensor, args.spp, args.seed,  # noqa: E731
                                 args.strategy_images, settings)
    renderer = make()
    timed = args.time is not None or args.checkpoint is not None
    if timed and not chose_pass_size and renderer.plan[-1][1] == renderer.pixels:
        auto = max(p[2] for p in renderer.plan)
        per_pass = max(1, min(renderer.spp // 16, auto,
                              _TIMED_PASS_LANES[args.variant.split("_")[0]] // renderer.pixels))
        if per_pass != auto:
            settings["samples_per_pass"] = per_pass
            renderer = make()
    return renderer


def _metadata(args, path: Path, params: dict, renderer) -> dict:
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
    return meta


def _announce(path: Path, renderer, args) -> None:
    depth, technique = renderer.settings.max_depth, renderer.settings.technique
    w, h = (int(x) for x in renderer.sensor.film().crop_size())
    passes = len(renderer.plan)
    eprint("bdpt: rendering %s (%dx%d, %d spp in %d pass%s, max_depth %s%s%s, seed %d, %s)"
           % (path.name, w, h, renderer.spp, passes, "" if passes == 1 else "es",
              "unbounded" if depth < 0 else depth,
              "" if technique is None else ", technique %d,%d" % technique,
              ", sensor %d" % args.sensor if args.sensor else "", args.seed, args.variant))


def _render_loop(renderer, args, stop, save) -> tuple:
    """Run passes until done, stopped (signal, time budget); checkpoint on the way.
    Returns why it stopped early (or None) and the time it took."""
    progress = Progress(renderer, budget=args.time, enabled=not args.quiet)
    stop.announce = None if args.quiet else (
        "stopping after the current pass" if renderer.at_round_end and len(
            {p[1] for p in renderer.plan}) == 1 and renderer.plan[0][1] == renderer.pixels
        else "stopping once every pixel has its samples of this round")
    t0 = last_checkpoint = time.perf_counter()
    reason = None
    while not renderer.done:
        renderer.run_pass()
        now = time.perf_counter()
        progress.update(now - t0)
        if renderer.done:
            break
        if not renderer.at_round_end:
            continue          # stops and checkpoints wait for every pixel's samples
        if stop.signal is not None:
            reason = "interrupted"
        elif args.time is not None and now - t0 >= args.time:
            reason = "time"
        if reason:
            break
        if args.checkpoint is not None and now - last_checkpoint >= args.checkpoint:
            save(renderer, final=False)
            last_checkpoint = time.perf_counter()
    progress.finish()
    return reason, time.perf_counter() - t0


def _report(res, renderer, outputs, reason, wall, stop, args) -> None:
    import numpy as np
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
    print("bdpt: %dx%d, %d spp (%d pass%s) in %s, %ssamples/s -> %s"
          % (w, h, res.spp, res.passes, "" if res.passes == 1 else "es", fmt_time(wall),
             fmt_rate(rate), ", ".join(map(str, outputs.paths))), flush=True)


def run(args, stop) -> int:
    """Render; exit status 0, or 128 + the signal's number if SIGINT or SIGTERM
    stopped it (after writing the image of the passes done)."""
    path = scene_path(args.scene)
    outputs = Outputs(output_path(args.output, path), args.strategy_images)
    check_writable(outputs.paths)
    mi = setup_variant(args.variant)
    params = scene_params(args)
    scene = load_scene(mi, path, params)
    check_sensor_index(scene, args.sensor)
    renderer = _renderer(args, scene, _settings(args, scene))
    stop.check()
    outputs.meta = _metadata(args, path, params, renderer)
    if not args.quiet:
        _announce(path, renderer, args)
    reason, wall = _render_loop(renderer, args, stop, outputs.save)
    res = outputs.save(renderer, final=True)
    _report(res, renderer, outputs, reason, wall, stop, args)
    return 0 if stop.signal is None else exit_status(stop.signal)
