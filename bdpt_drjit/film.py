"""Film stage: where contributions become an image.

Two kinds of estimates land on the film, and Mitsuba's ``hdrfilm.develop`` divides
by the weight channel, so they need separate image blocks:

* camera-side strategies (t >= 2): one value per camera sample, put once per pass
  at the sample's film position with weight 1 (normalized per pixel by develop);
* light-tracing strategies (t = 1): splatted wherever the light vertex projects,
  with weight 0 and alpha 0, and normalized at the end by W*H / (number of light
  paths) -- the same normalization as Mitsuba's ``ptracer``.

Per-strategy images (on request) use the same two kinds of blocks; camera-side
strategy blocks borrow the camera block's weights when developed, so that the
strategy images add up exactly to the image.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi


class FilmAccumulator:
    def __init__(self, film: mi.Film, coalesce: bool, strategy_images: bool):
        self.film = film
        film.prepare([])
        self.camera = film.create_block()
        self.camera.set_coalesce(self.camera.coalesce() and coalesce)
        self.light = self._splat_block()
        self.strategy_images = strategy_images
        self.strategies: dict[tuple[int, int], mi.ImageBlock] = {}
        self.light_paths = 0            # total number of light subpaths traced
        self.crop_pixels = int(dr.prod(film.crop_size()))

    def _splat_block(self) -> mi.ImageBlock:
        # normalize=True: a filter footprint sums to one wherever it is splatted.
        block = self.film.create_block(normalize=True)
        block.set_coalesce(False)
        return block

    def strategy_block(self, s: int, t: int) -> mi.ImageBlock | None:
        if not self.strategy_images:
            return None
        if (s, t) not in self.strategies:
            self.strategies[(s, t)] = (self._splat_block() if t == 1
                                       else self.film.create_block())
        return self.strategies[(s, t)]

    # -- writing -----------------------------------------------------------------
    def put_camera(self, pos, wavelengths, value, alpha):
        self.camera.put(pos, wavelengths, value, alpha, 1.0)

    @staticmethod
    def put_strategy(block, pos, wavelengths, value, active):
        """Camera-side strategy image: value only, weights come from the camera block."""
        if block is not None:
            block.put(pos, wavelengths, value, 0.0, 0.0, active)

    def splat(self, s: int, uv, wavelengths, value, active):
        """Light-tracing contribution at film position uv (crop-relative, from
        ``sensor.sample_direction``) into the light block and its strategy block."""
        pos = uv + mi.Vector2f(self.light.offset())
        self.light.put(pos, wavelengths, value, 0.0, 0.0, active)
        block = self.strategy_block(s, 1)
        if block is not None:
            block.put(pos, wavelengths, value, 0.0, 0.0, active)

    # -- developing ----------------------------------------------------------------
    def _develop(self, block: mi.ImageBlock) -> mi.TensorXf:
        self.film.prepare([])
        self.film.put_block(block)
        img = self.film.develop()
        dr.eval(img)
        return img

    def _light_scale(self) -> float:
        return self.crop_pixels / max(self.light_paths, 1)

    def develop(self) -> mi.TensorXf:
        return self._develop(self.camera) + self._develop(self.light) * self._light_scale()

    def develop_strategies(self) -> dict[tuple[int, int], mi.TensorXf]:
        out = {}
        cam = self.camera.tensor()
        ch = cam.shape[2]
        for (s, t), block in sorted(self.strategies.items()):
            if t == 1:
                out[(s, t)] = self._develop(block) * self._light_scale()
                continue
            # Borrow the camera block's weight channel (the last one).
            tensor = mi.TensorXf(block.tensor())
            weight_mask = dr.tile(mi.Float([0.0] * (ch - 1) + [1.0]), cam.shape[0] * cam.shape[1])
            data = dr.select(weight_mask > 0, cam.array, tensor.array)
            merged = mi.ImageBlock(mi.TensorXf(data, cam.shape), block.offset(),
                                   self.film.rfilter(), self.film.sample_border())
            out[(s, t)] = self._develop(merged)
        return out
