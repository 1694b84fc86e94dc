"""OpenEXR input and output for renders: float32 images with metadata.

    write_exr("out.exr", image, {"spp": 64, "seed": 1})     # (H, W, C) array
    image, meta = read_exr("out.exr")                       # meta["spp"] == 64
    write_layers("out.strategies.exr", {"s1t2": img12, "s0t3": img03}, meta)
    layers, meta = read_layers("out.strategies.exr")

Every file is written atomically: to a temporary file in the same directory, then
renamed over the target with ``os.replace``, so an interrupted write (Ctrl-C, a
full disk, a crash) never leaves a truncated file behind.

Channel names: 1 channel is ``Y``, 3 are ``R, G, B``, 4 are ``R, G, B, A``, any
other count ``C00, C01, ...``.  A layer ``name`` prefixes them: ``name.R``.
Metadata becomes header attributes: ints as int attributes (32 bit; larger ones
as strings), floats as float attributes (32 bit), bools as 0/1, anything else as
a string.  ``read_exr`` returns only these custom attributes, not the standard
ones (``channels``, ``dataWindow``, ...).
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

import numpy as np
import OpenEXR

__all__ = ["write_exr", "read_exr", "write_layers", "read_layers", "write_channels",
           "read_channels", "assemble_channels", "atomic_path", "channel_names"]

# Attributes every EXR file has (or may have) that are not user metadata.
STANDARD_ATTRIBUTES = frozenset({
    "channels", "compression", "dataWindow", "displayWindow", "lineOrder",
    "pixelAspectRatio", "screenWindowCenter", "screenWindowWidth", "type", "name",
    "tiles", "version", "chunkCount", "view", "maxSamplesPerPixel"})

_INT32 = (-2 ** 31, 2 ** 31 - 1)


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path beside ``path``; on success rename it over ``path``.

    On an exception (or KeyboardInterrupt) the temporary file is removed and the
    target is left as it was.
    """
    path = Path(path)
    directory = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=".%s." % path.name, suffix=".tmp", dir=directory)
    os.close(fd)
    try:
        yield tmp
        # mkstemp makes the file private (0600); give it the usual permissions.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def channel_names(count: int) -> list[str]:
    """Default channel names for an image with ``count`` channels."""
    if count == 1:
        return ["Y"]
    if count == 3:
        return ["R", "G", "B"]
    if count == 4:
        return ["R", "G", "B", "A"]
    return ["C%02d" % i for i in range(count)]


def _as_image(image) -> np.ndarray:
    a = np.asarray(image, dtype=np.float32)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[0] == 0 or a.shape[1] == 0 or a.shape[2] == 0:
        raise ValueError("write_exr: image must be an (H, W) or (H, W, C) array, got shape %s"
                         % (a.shape,))
    return np.ascontiguousarray(a)


def _header_value(key, value):
    if key in STANDARD_ATTRIBUTES:
        raise ValueError("write_exr: metadata key %r is a standard EXR attribute" % key)
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, int):
        return value if _INT32[0] <= value <= _INT32[1] else str(value)
    if isinstance(value, float):
        return value
    return str(value)


def _write(path, channels: dict, metadata) -> None:
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for key, value in (metadata or {}).items():
        header[str(key)] = _header_value(str(key), value)
    with atomic_path(path) as tmp:
        OpenEXR.File(header, channels).write(tmp)


def _image_channels(image, prefix: str = "", names=None) -> dict:
    a = _as_image(image)
    names = list(names) if names is not None else channel_names(a.shape[2])
    if len(names) != a.shape[2]:
        raise ValueError("write_exr: %d channel names for %d channels" % (len(names), a.shape[2]))
    return {prefix + n: np.ascontiguousarray(a[:, :, i]) for i, n in enumerate(names)}


def write_exr(path, image, metadata: dict | None = None, channels=None) -> None:
    """Write an (H, W) or (H, W, C) image as a float32 OpenEXR file, atomically.

    ``metadata`` becomes header attributes (see the module docstring);
    ``channels`` overrides the default channel names.
    """
    _write(path, _image_channels(image, names=channels), metadata)


def write_channels(path, channels: dict, metadata: dict | None = None) -> None:
    """Write {name: (H, W) array} channels as they are (float32), atomically."""
    chans = {str(n): np.ascontiguousarray(np.asarray(a, dtype=np.float32)) for n, a in channels.items()}
    if not chans or len({a.shape for a in chans.values()}) != 1 or next(iter(chans.values())).ndim != 2:
        raise ValueError("write_channels: need one or more (H, W) channels of the same size")
    _write(path, chans, metadata)


def write_layers(path, layers: dict, metadata: dict | None = None, image=None) -> None:
    """Write a multi-layer EXR: layer ``name`` gets channels ``name.R`` etc.

    ``image``, if given, is stored as the unprefixed default layer (what viewers
    show first).  All layers must have the same size.
    """
    channels = {}
    if image is not None:
        channels.update(_image_channels(image))
    for name, img in layers.items():
        if not name or "." in str(name):
            raise ValueError("write_layers: bad layer name %r" % (name,))
        channels.update(_image_channels(img, prefix="%s." % name))
    if not channels:
        raise ValueError("write_layers: no layers to write")
    shapes = {c.shape for c in channels.values()}
    if len(shapes) > 1:
        raise ValueError("write_layers: layers differ in size: %s" % sorted(shapes))
    _write(path, channels, metadata)


def read_channels(path) -> tuple[dict, dict]:
    """All channels of a (single-part) EXR file as {name: (H, W) float32 array},
    and its custom metadata."""
    path = str(path)
    f = OpenEXR.File(path, separate_channels=True)
    header = f.header()
    meta = {k: v for k, v in header.items() if k not in STANDARD_ATTRIBUTES}
    channels = {name: np.asarray(ch.pixels, dtype=np.float32)
                for name, ch in f.channels().items()}
    return channels, meta


def assemble_channels(channels: dict) -> np.ndarray:
    """Stack channels in their natural order: RGB(A), Y, else sorted by name."""
    names = set(channels)
    for order in (["R", "G", "B", "A"], ["R", "G", "B"], ["Y", "A"], ["Y"]):
        if names == set(order):
            return np.stack([channels[n] for n in order], axis=-1)
    return np.stack([channels[n] for n in sorted(names)], axis=-1)


def _split_layers(channels: dict) -> dict:
    layers: dict[str, dict] = {}
    for name, pixels in channels.items():
        layer, _, short = name.rpartition(".")
        layers.setdefault(layer, {})[short] = pixels
    return layers


def read_exr(path) -> tuple[np.ndarray, dict]:
    """Read an EXR file as ((H, W, C) float32 array, metadata dict).

    In a multi-layer file this is the default (unprefixed) layer, or the first
    layer if there is none.
    """
    channels, meta = read_channels(path)
    layers = _split_layers(channels)
    key = "" if "" in layers else sorted(layers)[0]
    return assemble_channels(layers[key]), meta


def read_layers(path) -> tuple[dict, dict]:
    """Read a multi-layer EXR as ({layer: (H, W, C) array}, metadata); the
    unprefixed channels are the layer ``""``."""
    channels, meta = read_channels(path)
    return {name: assemble_channels(chs) for name, chs in _split_layers(channels).items()}, meta
