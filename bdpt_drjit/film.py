"""Film stage: where contributions become an image.

Two kinds of estimates land on the film, and Mitsuba's ``hdrfilm.develop`` divides
by the weight channel, so they need separate image blocks:

* camera-side strategies (t >= 2): one value per camera sample, put once per pass
  at the sample's film position with weight 1 (normalized per pixel by develop),
  with alpha 1 where the camera ray hit a surface;
* light-tracing strategies (t = 1): splatted wherever the light vertex projects,
  with weight 0 and alpha 0.  A pass of N_C camera samples and N_L light subpaths
  splats its values times N_C / N_L, and the light block is normalized at the end by
  W*H / (camera samples): with N_L = N_C this is Mitsuba's ``ptracer``
  normalization, and passes with different budgets combine as their camera samples
  do.  A pass over every other pixel (the pilot, optimizer.py) keeps the splats
  that land in its own pixels, times 2: each pixel's light image then has the
  rate, and the MIS weights, of the camera samples it is combined with.

Both kinds estimate the same pixel: develop divides a camera sample's filter weight
w_j(p) by the pixel's summed weights, whose mean over the sampled film region S (the
crop window, plus the filter border if the film samples it) is proportional to
c_j = integral over S of w_j(p) dp.  So splats carry the raw weight w_j(p) too, and
the light image is divided by c_j (``_coverage``): a pixel at the film's edge,
whose filter reaches past S, has c_j below its interior value.  (A footprint
normalized to one wherever it is splatted, as Mitsuba's ``ptracer`` does, lost that
share: with a Gaussian filter, light tracing's edge pixels read 15% below
``path``'s.)

These puts run after the walks, in kernels of their own, so that the walks'
kernels never hold the film's size.  Per-strategy images (on request) have a layer
each (strategies.StrategySet.layers); camera-side layers borrow the camera block's
weights when developed, so that the layers add up exactly to the image.

AOVs (aovs.py, on request) have a block of their own, with the film's base channels
(weight 1 per camera sample) and the AOV channels after them; ``develop`` appends
the developed AOV channels to the image's.

``raw`` and ``add_raw`` hand the undeveloped sums between machines (cluster
rendering): a merge of raw sums is the same estimator as one render of all passes.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from .backend import device_array


class FilmAccumulator:
    # frozen.py: the camera samples so far are counted on the host, after each pass,
    # and read by no recorded pass (a new count would record each pass anew).
    FROZEN_IGNORE = ("camera_samples",)

    def __init__(self, film: mi.Film, coalesce: bool, layers: list | None = None,
                 aov_names: list | None = None, border: int = 0):
        """``border``: pixels of filter border around the crop window that the camera
        samples and the light image's splats come from (camera.sampled_border)."""
        self.film = film
        self.aov_names = list(aov_names or [])
        self.aov = None
        self.base_channels = film.prepare([])
        if self.aov_names:
            film.prepare(self.aov_names)
            self.aov = film.create_block()
            film.prepare([])
        self.camera = film.create_block()
        self.camera.set_coalesce(self.camera.coalesce() and coalesce)
        self.light = self._splat_block()
        # Strategy-image layers: (s, t) pairs or ("k", k) groups; a group of a path
        # length has both kinds of strategies, so a block of each kind.
        self.layers = layers or []
        self.layer_camera = {i: film.create_block() for i, (_, t) in enumerate(self.layers)
                             if t != 1}
        self.layer_light = {i: self._splat_block() for i, (s, t) in enumerate(self.layers)
                            if t == 1 or s == "k"}
        self.camera_samples = 0         # the light image's normalization (see above)
        self.crop_pixels = int(dr.prod(film.crop_size()))
        self.coverage = _coverage(film, border)     # 1 / c_j per pixel (see above)

    def _splat_block(self) -> mi.ImageBlock:
        # Raw filter weights, as the camera block's: the light image is divided by each
        # pixel's coverage c_j instead (see above).
        block = self.film.create_block(normalize=False)
        block.set_coalesce(False)
        return block

    # -- writing (after each pass's walks) ---------------------------------------------
    def put_camera(self, rays, radiance, hit, images=None, lanes: int = 0):
        """One value per camera sample; ``images``: the pass's per-layer values."""
        alpha = dr.select(hit, 1.0, 0.0)
        self.camera.put(rays.pos, rays.ray.wavelengths, radiance, alpha, 1.0)
        for index, block in self.layer_camera.items():
            offset = dr.opaque(mi.UInt32, index * lanes)
            value = dr.gather(mi.Spectrum, images, dr.arange(mi.UInt32, lanes) + offset)
            block.put(rays.pos, rays.ray.wavelengths, value, 0.0, 0.0)

    def put_aovs(self, rays, values: list):
        """One value per AOV channel and camera sample (aovs.AOVs.values)."""
        base = [mi.Float(0.0)] * (self.base_channels - 1) + [mi.Float(1.0)]   # weight last
        self.aov.put(rays.pos, base + values)

    def put_splats(self, splats, wavelengths, scale: float, keep: mi.Bool, layer_of=None):
        """The light image's splats of a pass where ``keep``, times ``scale`` = N_C /
        N_L of the pass (over the share of the film kept).  Light subpath l has the
        wavelengths of camera lane l mod N_C."""
        active = keep
        pos = splats.pos + mi.Vector2f(self.light.offset())
        home = splats.lane % dr.opaque(mi.UInt32, dr.width(wavelengths))
        wl = dr.gather(type(wavelengths), wavelengths, home, active)
        value = splats.value * dr.opaque(mi.Float, scale)
        self.light.put(pos, wl, value, 0.0, 0.0, active)
        for index, block in self.layer_light.items():
            mine = active & (layer_of(splats.s) == dr.opaque(mi.Int32, index))
            block.put(pos, wl, value, 0.0, 0.0, mine)

    def put_light(self, pos, value, active=True):
        """Values at film positions (crop-window pixels) on the light block, with no
        normalization but ``develop_light``'s (Metropolis light transport, mlt.py)."""
        pos = pos + mi.Vector2f(self.light.offset())
        self.light.put(pos, mi.Color0f(), value, 0.0, 0.0, active)

    def develop_light(self, scale) -> mi.TensorXf:
        """The light block alone, times ``scale``."""
        return self._develop_splats(self.light) * dr.opaque(mi.Float, scale)

    # -- raw sums (cluster rendering) ------------------------------------------------------
    def _raw_blocks(self) -> dict:
        """The blocks by their key in ``raw()``."""
        out = {"camera": self.camera, "light": self.light}
        if self.aov is not None:
            out["aov"] = self.aov
        for kind, blocks in (("camera", self.layer_camera), ("light", self.layer_light)):
            for index, block in blocks.items():
                out["layer:%d:%s" % (index, kind)] = block
        return out

    def raw(self) -> dict:
        """The undeveloped sums: camera and light blocks (and layers), and the camera
        samples that normalize the light image."""
        out = {key: np.array(block.tensor()) for key, block in self._raw_blocks().items()}
        out["camera_samples"] = self.camera_samples
        return out

    def add_raw(self, raw: dict) -> None:
        """Add undeveloped sums (``raw()`` of a film of the same size and layers, or a
        sum of several, in any float type) to this film's: ``develop()`` then
        develops them as if their samples had been put here."""
        blocks = self._raw_blocks()
        if set(raw) - {"camera_samples"} != set(blocks):
            raise ValueError("bdpt: raw film sums with blocks %s do not fit this film's %s"
                             % (sorted(set(raw) - {"camera_samples"}), sorted(blocks)))
        for key, block in blocks.items():
            data = np.asarray(raw[key], dtype=np.float32)
            if data.shape != tuple(block.tensor().shape):
                raise ValueError("bdpt: raw film block %r has shape %s, this film's is %s"
                                 % (key, data.shape, tuple(block.tensor().shape)))
            block.put_block(mi.ImageBlock(device_array(mi.TensorXf, data), block.offset(),
                                          self.film.rfilter(), block.has_border()))
        self.camera_samples += int(raw["camera_samples"])

    def blocks(self) -> list:
        return ([self.camera, self.light] + ([] if self.aov is None else [self.aov])
                + list(self.layer_camera.values()) + list(self.layer_light.values()))

    def clear(self) -> None:
        for block in self.blocks():
            block.clear()
        self.camera_samples = 0

    # -- developing ----------------------------------------------------------------
    def _develop(self, block: mi.ImageBlock) -> mi.TensorXf:
        self.film.prepare([])
        self.film.put_block(block)
        img = self.film.develop()
        dr.eval(img)
        return img

    def _develop_splats(self, block: mi.ImageBlock) -> mi.TensorXf:
        """A block of splats developed, each pixel divided by its coverage c_j."""
        img = self._develop(block)
        return img if self.coverage is None else img * self.coverage

    def _light_scale(self, camera_samples: int | None = None) -> mi.Float:
        return dr.opaque(mi.Float, self.crop_pixels / max(camera_samples or self.camera_samples, 1))

    def develop(self, camera_samples: int | None = None) -> mi.TensorXf:
        """The image: the camera block developed, plus the light block scaled; the
        light block has alpha 0, so alpha is the camera block's.  AOV channels last.
        ``camera_samples``: normalize the light image by that many instead of those
        put so far (a round of passes not yet complete)."""
        img = (self._develop(self.camera)
               + self._develop_splats(self.light) * self._light_scale(camera_samples))
        if self.aov is None:
            return img
        self.film.prepare(self.aov_names)
        self.film.put_block(self.aov)
        aov = self.film.develop()
        self.film.prepare([])
        return dr.concat([img, aov[..., -len(self.aov_names):]], axis=-1)

    def develop_layers(self) -> dict:
        """Each layer's image; they add up to ``develop()``."""
        out = {}
        cam = self.camera.tensor()
        ch = cam.shape[2]
        weight_mask = dr.tile(mi.Float([0.0] * (ch - 1) + [1.0]), cam.shape[0] * cam.shape[1])
        for index, layer in enumerate(self.layers):
            img = 0
            if index in self.layer_camera:
                # Borrow the camera block's weight channel (the last one).
                block = self.layer_camera[index]
                data = dr.select(weight_mask > 0, cam.array, block.tensor().array)
                merged = mi.ImageBlock(mi.TensorXf(data, cam.shape), block.offset(),
                                       self.film.rfilter(), self.film.sample_border())
                img = self._develop(merged)
            if index in self.layer_light:
                img = img + self._develop_splats(self.layer_light[index]) * self._light_scale()
            out[layer] = img
        return out


def _coverage(film: mi.Film, border: int) -> mi.TensorXf | None:
    """1 / c_j for each pixel j of the crop window, (H, W, 1): c_j, the integral of
    the pixel's filter weight w_j(p) = w(x - p_x) w(y - p_y) (x, y its centre) over the
    sampled region, the crop plus ``border`` pixels on every side.  Separable:
    c_j = c_x c_y, each the filter's cumulative integral between the region's two
    ends.  None for a box filter (c_j = 1)."""
    rfilter = film.rfilter()
    if rfilter.is_box_filter():
        return None
    radius = rfilter.radius()
    u = np.linspace(-radius, radius, 8193)
    w = np.array(rfilter.eval(device_array(mi.Float, u.astype(np.float32))), dtype=np.float64)
    cumulative = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(u))])

    def axis(n: int) -> np.ndarray:
        # Pixel i (centre i + 0.5) over positions p in [-border, n + border]: the
        # filter's argument i + 0.5 - p runs from i + 0.5 - n - border to i + 0.5 + border.
        centre = np.arange(n) + 0.5
        upper = np.interp(centre + border, u, cumulative)
        lower = np.interp(centre - n - border, u, cumulative)
        return upper - lower

    width, height = (int(v) for v in film.crop_size())
    inverse = 1.0 / np.outer(axis(height), axis(width))
    return device_array(mi.TensorXf, inverse.astype(np.float32)[..., None])
