"""Charts of the benchmark suite (matplotlib, Agg backend): error against time and MIS
weighting per scene, time against samples and max_depth, strategy pyramids, and the
small palette copies that are committed."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from . import common as C


def fig(w=6, h=4):
    return C.matplotlib().subplots(figsize=(w, h), dpi=100)


def no_minor_labels(ax):
    from matplotlib.ticker import NullFormatter
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.yaxis.set_minor_formatter(NullFormatter())


def save(f, path: Path):
    path.parent.mkdir(parents=True, exist_ok=True)
    f.tight_layout()
    f.savefig(path, dpi=100)
    C.matplotlib().close(f)


def finish_loglog(f, ax, path: Path, xlabel: str, ylabel: str, title: str) -> None:
    """Labels, grid and legend of a log-log chart, saved to path."""
    no_minor_labels(ax)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    save(f, path)


def curves(result, key="time"):
    """method -> (xs, relmse list) in spp order; x = the record's ``key`` (time, spp)."""
    out = {}
    for r in result["records"]:
        out.setdefault(r["method"], []).append((r["spp"], r[key], r["relmse"]))
    return {m: ([p[1] for p in sorted(v)], [p[2] for p in sorted(v)]) for m, v in out.items()}


# -- per scene -------------------------------------------------------------------------------------
def scene_charts(result, charts: Path, methods) -> None:
    """A scene's charts, named by result["chart"] and result["weighting_chart"] (None:
    not drawn)."""
    if result.get("chart"):
        error(result, charts / result["chart"], methods)
    if result.get("weighting_chart"):
        weighting(result, charts / result["weighting_chart"], methods)


def error(result, path: Path, methods):
    f, ax = fig()
    cv = curves(result, "time")
    for m in methods:
        if m.name not in cv or (m.name == "bdpt-lafortune" and result.get("weighting_chart")):
            continue                                # in the weighting chart only
        xs, es = cv[m.name]
        ax.loglog(xs, es, m.style, color=m.color, marker="o", ms=3, label=m.label)
    eq = result.get("equal_time")
    if eq:
        ax.axvline(eq["x"], color="0.7", lw=0.8, ls=":")
    finish_loglog(f, ax, path, "render time / s (compile excluded)", "relative MSE",
                  "%s (%dx%d, max_depth %d)" % (result["scene"], result["width"], result["height"],
                                                result["max_depth"]))


def weighting(result, path: Path, methods):
    """The MIS weighting schemes' error against time (left) and against spp (right)."""
    f, axes = C.matplotlib().subplots(1, 2, figsize=(9, 3.6), dpi=100, sharey=True)
    for ax, key, xlabel in ((axes[0], "time", "render time / s (compile excluded)"),
                            (axes[1], "spp", "samples per pixel")):
        cv = curves(result, key)
        for m in methods:
            if m.name in C.WEIGHTING and m.name in cv:
                xs, es = cv[m.name]
                ax.loglog(xs, es, m.style, color=m.color, marker="o", ms=3, label=m.label)
        eq = (result.get("weighting") or {}).get(key)
        if eq:
            ax.axvline(eq["x"], color="0.7", lw=0.8, ls=":")
        if key == "spp" and cv.get("bdpt-power"):
            xs, es = cv["bdpt-power"]
            ax.loglog(xs, [es[0] * xs[0] / x for x in xs], color="0.6", lw=0.8, ls=":", label="1/spp")
        no_minor_labels(ax)
        ax.set_xlabel(xlabel)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("relative MSE")
    axes[1].legend(fontsize=7)
    f.suptitle("MIS weighting: %s (%dx%d, max_depth %d)" % (result["scene"], result["width"],
                                                           result["height"], result["max_depth"]),
               fontsize=10)
    save(f, path)


# -- scaling ---------------------------------------------------------------------------------------
def scaling(sc: dict, depth_res: int, depth_spp: int, charts: Path) -> None:
    """scaling_samples.png and scaling_depth.png from suite.scaling's results."""
    samples(sc, charts / "scaling_samples.png")
    depth(sc, depth_res, depth_spp, charts / "scaling_depth.png")


def samples(sc: dict, path: Path) -> None:
    f, ax = fig()
    for m in (C.BDPT_POWER, C.PATH):
        pts = sorted((r["samples"], r["time"]) for r in sc["pixels_spp"] if r["method"] == m.name)
        ax.loglog([p[0] for p in pts], [p[1] for p in pts], "o", color=m.color, ms=4, label=m.label)
        ft = sc["fits"][m.name]
        xs = np.geomspace(pts[0][0], pts[-1][0], 50)
        ax.loglog(xs, ft["overhead_s"] + ft["per_sample_s"] * xs, "-", color=m.color, lw=0.8,
                  label="fit %.3g s + N/%.3g/s" % (ft["overhead_s"], 1 / ft["per_sample_s"])
                  if ft["per_sample_s"] > 0 else "fit")
    finish_loglog(f, ax, path, "samples (pixels x spp)", "render time / s",
                  "Time vs pixels x spp (Cornell box, max_depth 8)")


def depth(sc: dict, res: int, spp: int, path: Path) -> None:
    f, ax = fig()
    for m in (C.BDPT_POWER, C.PATH):
        pts = [(r["max_depth"], r["time"]) for r in sc["depth"] if r["method"] == m.name]
        ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", color=m.color, ms=4, label=m.label + " time")
    ax.set_xlabel("max_depth")
    ax.set_ylabel("render time / s")
    b = [r for r in sc["depth"] if r["method"] == "bdpt-power"]
    ax2 = ax.twinx()
    ax2.plot([r["max_depth"] for r in b], [r["connections"] for r in b], "s--", color="0.5", ms=3,
             label="connection strategies (s,t>=2)")
    ax2.plot([r["max_depth"] for r in b], [r["kernels_per_pass"] for r in b], "^:", color="C2", ms=3,
             label="BDPT kernel launches / pass")
    ax2.set_ylabel("count")
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, fontsize=7, loc="upper left")
    ax.set_title("Time vs max_depth (Cornell box %dx%d, %d spp)" % (res, res, spp), fontsize=10)
    ax.grid(True, alpha=0.3)
    save(f, path)


# -- strategy pyramid -------------------------------------------------------------------------------
def pyramid(name: str, img: np.ndarray, strat: dict, K: int, path: Path) -> Path:
    """The MIS-weighted strategy images (s, t) of paths of k = 1..K edges, row k,
    column s, at path; the full image next to it (its path is returned)."""
    h, w = img.shape[:2]
    # Each cell has its own exposure (printed in its title): at one common exposure most
    # strategies are nearly black.  The cell's mean tells its share of the image.
    base_exposure = C.auto_exposure(img)
    plt = C.matplotlib()
    f, axes = plt.subplots(K, K + 1, figsize=(1.25 * (K + 1), 1.25 * h / w * K + 0.6), dpi=100, squeeze=False)
    for k in range(1, K + 1):
        for s in range(0, K + 1):
            pyramid_cell(axes[k - 1][s], img, strat, s, k, base_exposure)
    f.suptitle("%s: MIS-weighted strategies (power); row k = s+t-1 edges, column s;\n"
               "title: share of the image's mean, exposure relative to the full image"
               % name, fontsize=7)
    f.subplots_adjust(wspace=0.05, hspace=0.25, left=0.04, right=0.99, bottom=0.01, top=0.88)
    path.parent.mkdir(parents=True, exist_ok=True)
    f.savefig(path, dpi=100)
    plt.close(f)
    full = path.with_name(path.stem + "_image.png")
    from PIL import Image  # matplotlib depends on pillow
    Image.fromarray(C.to_srgb8(img, base_exposure)).resize((w * max(1, 192 // w), h * max(1, 192 // w)),
                                                      Image.NEAREST).save(full)
    return full


def pyramid_cell(ax, img, strat: dict, s: int, k: int, base_exposure: float) -> None:
    ax.set_xticks([])
    ax.set_yticks([])
    t = k + 1 - s
    if s > k or t < 1:
        ax.axis("off")
        return
    im = strat.get((s, t))
    if im is None:
        im = np.zeros_like(img)
        ax.set_facecolor("0.85")
    exposure = C.auto_exposure(im) if np.any(im > 0) else base_exposure
    ax.imshow(C.to_srgb8(im, exposure), interpolation="nearest")
    share = float(np.mean(im)) / max(float(np.mean(img)), 1e-12)
    ax.set_title("s=%d t=%d  %.0f%%  x%.2g" % (s, t, 100 * share, exposure / base_exposure),
                 fontsize=5.5, pad=1)
    if s == 0:
        ax.set_ylabel("k=%d" % k, fontsize=7)


def small_png(src: Path, dst: Path) -> None:
    """Copy a chart as a palette PNG (a third of the size, to be committed)."""
    try:
        from PIL import Image
        with Image.open(src) as im:
            im.convert("RGB").quantize(colors=128).save(dst, optimize=True)
    except Exception:  # noqa: BLE001  (no pillow, odd image: plain copy)
        shutil.copy2(src, dst)
