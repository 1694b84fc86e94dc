"""``bdpt mlt``: render with multiplexed MLT (``--integrator mlt``, bdpt_drjit/mmlt.py)
or PSSMLT over BDPT samples (``pssmlt``, bdpt_drjit/mlt.py), with progress per
iteration, a time budget and stops.

An iteration mutates every chain once; the command stops after the iteration that
crosses ``--time`` or after a Ctrl-C (SIGINT) or SIGTERM, and writes the image of
the iterations done: its normalization holds after any whole iteration (mlt.py), so
an early stop gives a correct, noisier image.  The
bootstrap cannot be stopped part way: a signal during it ends the command with
nothing written."""
from __future__ import annotations

import time

from .errors import CLIError, eprint, one_line
from .images import check_writable, output_path, write_png
from .progress import exit_status, fmt_time
from .scene import check_sensor_index, integrator_defaults, load_scene, scene_params, scene_path, setup_variant

_BDPT_KEYS = ("max_depth", "rr_depth", "mis", "light_image", "hide_emitters")
_MLT_KEYS = ("mutations_per_pixel", "large_step_probability", "bootstrap_samples", "chains",
             "large_step_mis", "multiplex", "direct_samples", "two_stage")


def _params(args, scene) -> dict:
    """The scene integrator's max_depth and rr_depth (or a pssmlt integrator's
    settings), overridden by the options given; mutations per pixel default to the
    scene's sample count (mlt.py)."""
    defaults, _ = integrator_defaults(scene)
    out = {k: v for k, v in defaults.items() if k in _BDPT_KEYS + _MLT_KEYS}
    for key in _BDPT_KEYS + _MLT_KEYS:
        value = getattr(args, key, None)
        if value is not None:
            out[key] = value
    return out


def _save(renderer, out, meta) -> object:
    from ..exr import write_exr
    res = renderer.result()
    meta.update(spp=res.spp, passes=res.passes, render_time=float(res.time),
                b=float(res.stats["b"]), chains=res.stats["chains"],
                direct_samples_per_iteration=res.stats["direct_samples_per_iteration"],
                acceptance=float(res.stats["acceptance"]),
                mutations_per_pixel=float(res.stats["mutations_per_pixel"]))
    try:
        write_exr(out, res.image, meta, channels=res.channels)
        write_png(out.with_suffix(".png"), res.image[..., :len(res.channels)])
    except OSError as e:
        raise CLIError("cannot write %s: %s" % (out, e.strerror or one_line(e))) from None
    return res


def run(args, stop) -> int:
    path = scene_path(args.scene)
    out = output_path(args.output, path)
    check_writable([out, out.with_suffix(".png")])
    mi = setup_variant(args.variant)
    params = scene_params(args)
    scene = load_scene(mi, path, params)
    check_sensor_index(scene, args.sensor)
    settings = _params(args, scene)
    from .. import mlt, mmlt
    from ..support import UnsupportedPluginError
    stop.check()
    t0 = time.perf_counter()
    try:
        cls = mmlt.MMLTRenderer if args.integrator == "mlt" else mlt.MLTRenderer
        renderer = cls(scene, sensor=args.sensor, seed=args.seed, **settings)
    except UnsupportedPluginError as e:
        raise CLIError("the scene uses an unsupported plugin: %s" % one_line(e)) from None
    except (ValueError, RuntimeError) as e:
        raise CLIError(one_line(e)) from None
    stop.check()
    if not args.quiet:
        eprint("bdpt: %s %s: %d chains x %d iterations, bootstrap of %d samples in %s, "
               "b = %.6g, chains on %d distinct start states"
               % (renderer.name, path.name, renderer.chains, renderer.iterations, renderer.bootstrap_samples,
                  fmt_time(renderer.bootstrap_time), renderer.b, renderer.start_states))
        if renderer.direct_lanes:
            eprint("bdpt: paths of 1 and 2 edges (%.0f%% of b) by %d direct samples per "
                   "iteration" % (100.0 * renderer.b_direct / renderer.b, renderer.direct_lanes))
    reason, last = None, 0.0
    while not renderer.done:
        renderer.run_iteration()
        now = time.perf_counter() - t0
        if not args.quiet and (now - last >= 1.0 or renderer.done):
            last = now
            eprint("bdpt: %d/%d iterations, %.1f mutations per pixel, acceptance %.2f, %s"
                   % (renderer.iterations_done, renderer.iterations,
                      renderer.chains * renderer.iterations_done / renderer.pixels,
                      renderer.last_acceptance(), fmt_time(now)))
        if renderer.done:
            break
        if stop.signal is not None:
            reason = "interrupted"
        elif args.time is not None and now >= args.time:
            reason = "time"
        if reason:
            break
    from .. import __version__
    meta = {"integrator": renderer.name, "seed": args.seed, "bdpt_version": __version__,
            "scene": str(path.resolve()), "variant": args.variant, "sensor": args.sensor,
            "scene_params": ",".join("%s=%s" % kv for kv in sorted(params.items())),
            **{k: v for k, v in settings.items() if k != "mutations_per_pixel"}}
    res = _save(renderer, out, meta)
    if reason is not None:
        eprint("bdpt: %s after %d of %d iterations; wrote their image"
               % ("interrupted" if reason == "interrupted" else "time budget used up",
                  res.passes, renderer.iterations))
    print("bdpt: %s %s, %.1f mutations per pixel in %s -> %s"
          % (renderer.name, "x".join(str(int(x)) for x in renderer.sensor.film().crop_size()),
             res.stats["mutations_per_pixel"], fmt_time(time.perf_counter() - t0), out),
          flush=True)
    return 0 if stop.signal is None else exit_status(stop.signal)
