"""Where MLT spends its samples on an easy scene: per-pixel error maps of ``mlt`` and
the default ``bdpt`` at equal time on the diffuse Cornell box (README, Metropolis light
transport; issue 31 asked for the picture).

    python -m benchmarks.mlt_picture [--seconds 5] [--runs 4] [--out docs/mlt-diffuse-box.png]

Each round renders ``mlt`` and the default ``bdpt`` for ``--seconds`` each, interleaved
(benchmarks.mlt_door's timed renders and cached reference: 16384 spp of BDPT at 64x64).
Per pixel, the relative RMS error over the runs, sqrt(mean (I - R)^2 / (R^2 + eps)).
The picture, luminance only, each panel 64x64 shown 4x: the reference, one ``mlt`` run,
one ``bdpt`` run (white: the 99th percentile of the pixels off the lamp), then both
error maps on one scale (black: none, white: the larger map's 99th percentile or more).
Printed: each method's relMSE over the film, over its darkest and brightest quarters
of pixels (by the reference), and of 8x8 block means."""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import mitsuba as mi
from bdpt_drjit import mlt, mmlt, support

from .mlt_door import reference, timed_bdpt, timed_mlt

SCENE = "scenes/cornell-box.xml"
RES, REF_SPP, PLAN_MPP = 64, 16384, 256        # as mlt_door's box figure
ZOOM = 4


def _panel(image: np.ndarray, white: float, gamma: float = 1.0) -> np.ndarray:
    """A panel scaled so that ``white`` is 1, raised to 1 / ``gamma`` (the renders' 2.2;
    the error maps stay linear), enlarged ZOOM times."""
    return np.kron(np.clip(image / white, 0.0, 1.0) ** (1.0 / gamma), np.ones((ZOOM, ZOOM)))


def _quarters(err2: np.ndarray, ref: np.ndarray) -> tuple:
    """relMSE over the film, its darkest and its brightest quarter of pixels."""
    order = np.argsort(ref.ravel())
    q = order.size // 4
    flat = err2.ravel()
    return float(flat.mean()), float(flat[order[:q]].mean()), float(flat[order[-q:]].mean())


def _blocks(images: list, ref: np.ndarray, size: int = 8) -> float:
    """relMSE of ``size`` x ``size`` block means, averaged over the runs: an error
    correlated over the image (a chain's neighbourhood) stays there, pixel noise
    averages out."""
    def means(a):
        h, w = a.shape
        return a.reshape(h // size, size, w // size, size).mean(axis=(1, 3))
    r = means(ref)
    eps = (0.01 * r.mean()) ** 2
    return float(np.mean([np.mean((means(i) - r) ** 2 / (r ** 2 + eps)) for i in images]))


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--runs", type=int, default=4)
    ap.add_argument("--out", default="docs/mlt-diffuse-box.png")
    args = ap.parse_args(argv)
    scene = support.load_file(SCENE, resx=RES, resy=RES)
    ref, eps, _ = reference(scene, SCENE, RES, REF_SPP, 0.45)
    chains, _ = mlt.automatic_plan(PLAN_MPP * RES * RES, 0, 0)
    methods = {"mlt": lambda s: timed_mlt(scene, args.seconds, s, True, chains, 0,
                                          mmlt.MMLTRenderer),
               "bdpt": lambda s: timed_bdpt(scene, args.seconds, s)}
    images = {m: [] for m in methods}
    for run in range(args.runs):
        for name, go in methods.items():
            img, seconds, spp = go(run + 1)
            images[name].append(img)
            print("run %d %-4s %.1f s, %.0f spp/mpp" % (run, name, seconds, spp), flush=True)
    err2 = {m: np.mean([(i - ref) ** 2 / (ref ** 2 + eps) for i in imgs], axis=0)
            for m, imgs in images.items()}
    for m, e in err2.items():
        total, dark, bright = _quarters(e, ref)
        print("%-4s relMSE %.4g; darkest quarter %.4g, brightest quarter %.4g (%.1fx); "
              "8x8 block means %.4g" % (m, total, dark, bright, dark / bright,
                                        _blocks(images[m], ref)))
    bright = ref > 4.0 * ref.mean()                    # the lamp seen directly
    white = float(np.percentile(ref[~bright], 99))
    rms = {m: np.sqrt(e) for m, e in err2.items()}
    top = max(float(np.percentile(r, 99)) for r in rms.values())
    row = np.concatenate([_panel(ref, white, 2.2), _panel(images["mlt"][0], white, 2.2),
                          _panel(images["bdpt"][0], white, 2.2), _panel(rms["mlt"], top),
                          _panel(rms["bdpt"], top)], axis=1)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    mi.Bitmap(row.astype(np.float32)).convert(
        mi.Bitmap.PixelFormat.Y, mi.Struct.Type.UInt8, srgb_gamma=False).write(args.out)
    print("wrote %s (error scale: white = relative RMS error %.3g)" % (args.out, top))


if __name__ == "__main__":
    main()
