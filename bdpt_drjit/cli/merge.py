"""``bdpt merge``: average renders made with different seeds, weighted by their spp."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..settings import PARAMS
from .errors import CLIError, eprint
from .images import check_writable, output_path, read_image, write_png

# Header entries that should agree between the merged images (a warning otherwise).
_SAME = ("scene", "scene_params", "sensor", "variant") + tuple(
    p.name for p in PARAMS if p.name not in ("samples_per_pass", "memory_budget"))


def _seeds(value) -> list:
    """The seeds an image was rendered with (an int, or a list written by merge)."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return [int(value)]
    out = []
    for part in re.split(r"[,\s]+", str(value).strip("[]() ")):
        if part:
            out.append(int(part) if re.fullmatch(r"-?\d+", part) else part)
    return out


def _read(name: str) -> tuple:
    """(name, channels, header, spp, seeds) of an input, or a CLIError saying why not."""
    channels, meta = read_image(name)
    spp = meta.get("spp")
    if not isinstance(spp, int) or isinstance(spp, bool) or spp <= 0:
        raise CLIError("%s has no spp in its header (not written by 'bdpt render'?); "
                       "cannot weight it" % name)
    if "seed" not in meta:
        raise CLIError("%s has no seed in its header; cannot check that the renders "
                       "are independent" % name)
    return name, channels, meta, spp, _seeds(meta["seed"])


def _check_compatible(images, quiet: bool) -> None:
    name0, ch0 = images[0][:2]
    shape0 = next(iter(ch0.values())).shape
    for name, ch, *_ in images[1:]:
        shape = next(iter(ch.values())).shape
        if shape != shape0:
            raise CLIError("cannot merge images of different sizes: %s is %dx%d, %s is %dx%d"
                           % (name0, shape0[1], shape0[0], name, shape[1], shape[0]))
        if set(ch) != set(ch0):
            raise CLIError("cannot merge: %s has channels %s, %s has %s"
                           % (name0, ",".join(sorted(ch0)), name, ",".join(sorted(ch))))
    seen = {}
    for name, *_, seeds in images:
        for s in seeds:
            if s in seen:
                raise CLIError("cannot merge %s and %s: both were rendered with seed %s, so "
                               "their noise is identical (render again with another --seed)"
                               % (seen[s], name, s))
            seen[s] = name
    for key in _SAME:
        values = {str(m.get(key)) for _, _, m, _, _ in images if key in m}
        if len(values) > 1 and not quiet:
            eprint("bdpt: warning: the images differ in %s (%s); merging anyway"
                   % (key, ", ".join(sorted(values))))


def _average(images) -> tuple[dict, dict]:
    """The spp-weighted average of every channel, and its header."""
    total = sum(spp for *_, spp, _ in images)
    merged = {}
    for c, first in images[0][1].items():
        acc = np.zeros(first.shape, np.float64)
        for _, ch, _, spp, _ in images:
            acc += spp * ch[c].astype(np.float64)
        merged[c] = (acc / total).astype(np.float32)
    meta = dict(images[0][2])
    meta.update(spp=total, seed=",".join(str(s) for *_, seeds in images for s in seeds),
                passes=sum(int(m.get("passes", 0)) for _, _, m, _, _ in images),
                render_time=float(sum(float(m.get("render_time", 0.0)) for _, _, m, _, _ in images)),
                merged_from=len(images))
    meta.pop("spp_requested", None)
    return merged, meta


def run(args, stop) -> int:
    from ..exr import assemble_channels, write_channels
    if len(args.inputs) < 2:
        raise CLIError("merge needs at least two images")
    out = output_path(args.output, Path("merged"))
    png = out.with_suffix(".png")
    check_writable([out, png])
    images = [_read(name) for name in args.inputs]
    _check_compatible(images, args.quiet)
    merged, meta = _average(images)
    stop.check()
    write_channels(out, merged, meta)
    wrote = [str(out)]
    top = {c: v for c, v in merged.items() if "." not in c}
    if top:
        write_png(png, assemble_channels(top))
        wrote.append(str(png))
    if not args.quiet:
        print("bdpt: merged %d images (%s spp = %d spp, seeds %s) -> %s"
              % (len(images), " + ".join(str(spp) for *_, spp, _ in images), meta["spp"],
                 meta["seed"], ", ".join(wrote)), flush=True)
    return 0
