"""Image output: atomic EXR and PNG files, the sRGB preview, the strategy contact sheet."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from .errors import CLIError, one_line


def output_path(arg, scene: Path) -> Path:
    """The EXR to write: ``arg`` (``.exr`` added if it has no suffix), else
    <scene name>.exr in the current directory."""
    out = Path(arg) if arg else Path.cwd() / (scene.stem + ".exr")
    if out.suffix == "":
        out = out.with_name(out.name + ".exr")
    if out.suffix.lower() != ".exr":
        raise CLIError("output %s must be an OpenEXR file ending in .exr (a PNG preview "
                       "is written beside it)" % out)
    return out


def check_writable(paths) -> None:
    """Fail now, before rendering, if any output cannot be written."""
    checked = set()
    for path in map(Path, paths):
        if path.is_dir():
            raise CLIError("cannot write %s: it is a directory" % path)
        parent = path.parent
        if parent in checked:
            continue
        if not parent.exists():
            raise CLIError("cannot write %s: directory %s does not exist" % (path, parent))
        if not parent.is_dir():
            raise CLIError("cannot write %s: %s is not a directory" % (path, parent))
        try:
            fd, tmp = tempfile.mkstemp(prefix=".bdpt-write-test.", dir=parent)
            os.close(fd)
            os.unlink(tmp)
        except OSError as e:
            raise CLIError("cannot write %s: %s" % (path, e.strerror or e)) from None
        checked.add(parent)


def read_image(name) -> tuple[dict, dict]:
    """An EXR's channels and header, or a CLIError saying why not."""
    from ..exr import read_channels
    if not Path(name).is_file():
        raise CLIError("image not found: %s" % name)
    try:
        return read_channels(name)
    except Exception as e:
        raise CLIError("cannot read %s as OpenEXR: %s" % (name, one_line(e))) from None


def srgb8(image) -> np.ndarray:
    """Linear HDR (H, W, C) -> 8-bit sRGB (H, W, 3), by Mitsuba's own conversion
    (clipped to [0, 1]); images of 2 or more than 4 channels show their first 3 or 1."""
    import mitsuba as mi
    a = np.asarray(image, dtype=np.float32)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.shape[2] not in (1, 3):
        a = a[:, :, :3] if a.shape[2] > 3 else a[:, :, :1]
    return np.array(mi.util.convert_to_bitmap(np.ascontiguousarray(a)))


def write_png(path, image) -> None:
    """Write a linear (H, W, C) image as an sRGB PNG, atomically."""
    import mitsuba as mi
    from ..exr import atomic_path
    rgb8 = image if image.dtype == np.uint8 else srgb8(image)
    with atomic_path(path) as tmp:
        mi.Bitmap(np.ascontiguousarray(rgb8)).write(tmp, mi.Bitmap.FileFormat.PNG)


def contact_sheet(strategies: dict, gap: int = 2) -> np.ndarray:
    """Tone-mapped strategy images on a grid: row k = s + t - 1, column s."""
    if not strategies:
        raise ValueError("no strategy images")
    h, w = next(iter(strategies.values())).shape[:2]
    kmax = max(s + t - 1 for s, t in strategies)
    smax = max(s for s, _ in strategies)
    rows, cols = kmax, smax + 1
    sheet = np.full((gap + rows * (h + gap), gap + cols * (w + gap), 3), 48, np.uint8)
    for (s, t), img in strategies.items():
        k = s + t - 1
        if k < 1:
            continue
        y, x = gap + (k - 1) * (h + gap), gap + s * (w + gap)
        sheet[y:y + h, x:x + w] = srgb8(img)
    return sheet
