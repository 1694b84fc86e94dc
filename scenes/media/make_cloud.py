"""Writes cloud.vol, the density grid of cloud.xml: a few overlapping Gaussian puffs
in the unit cube, 24^3 values in [0, 1] (Mitsuba's .vol format, mi.VolumeGrid.write).
Run from anywhere: python scenes/media/make_cloud.py"""
from pathlib import Path

import numpy as np
import mitsuba as mi

mi.set_variant("scalar_rgb")
N = 24
PUFFS = [((0.5, 0.45, 0.5), 0.22), ((0.3, 0.55, 0.45), 0.15), ((0.7, 0.5, 0.55), 0.16),
         ((0.5, 0.65, 0.4), 0.13), ((0.45, 0.35, 0.65), 0.12)]

c = (np.arange(N) + 0.5) / N
z, y, x = np.meshgrid(c, c, c, indexing="ij")        # the grid is stored z, y, x
density = np.zeros((N, N, N))
for (cx, cy, cz), r in PUFFS:
    density += np.exp(-((x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2) / (2 * r * r))
density = np.clip(density / density.max(), 0.0, 1.0)
density[density < 0.05] = 0.0                          # empty space around the puffs
grid = mi.VolumeGrid(density[..., None].astype(np.float32))
grid.write(str(Path(__file__).with_name("cloud.vol")))
