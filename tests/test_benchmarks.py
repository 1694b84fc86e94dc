"""Smoke test of the benchmark suite: ``python -m benchmarks.run --smoke --out DIR``
(2 scenes at 16x16, 2 spp levels, no RSS subprocesses) must exit 0 and write its
results, charts and RESULTS.md into DIR, and nothing into the repository; the same
for ``--weighting`` (the MIS weighting schemes, one scene); and the blocks of
RESULTS.md that a published run rewrites."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import cli_env

ROOT = Path(__file__).resolve().parent.parent


def run_benchmark(out: Path, *args):
    pytest.importorskip("matplotlib")
    return subprocess.run([sys.executable, "-m", "benchmarks.run", "--smoke", "--out", str(out), *args],
                          cwd=str(ROOT), capture_output=True, text=True, timeout=300,
                          env=cli_env())


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench-smoke")
    return run_benchmark(out), out


@pytest.fixture(scope="module")
def weighting(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench-weighting")
    return run_benchmark(out, "--weighting", "--scenes", "cornell-diffuse"), out


def test_smoke_exits_zero(smoke):
    proc, _ = smoke
    assert proc.returncode == 0, "benchmarks.run --smoke failed:\n%s\n%s" % (proc.stdout[-3000:],
                                                                          proc.stderr[-3000:])


def test_smoke_outputs(smoke):
    proc, out = smoke
    assert proc.returncode == 0
    res = json.loads((out / "results.json").read_text())
    assert res["mode"] == "smoke"
    scenes = [s for s in res["scenes"] if s]
    assert scenes, "no scene was benchmarked"
    for s in scenes:
        methods = {r["method"] for r in s["records"]}
        assert {"bdpt-power", "path"} <= methods
        for r in s["records"]:
            assert r["time"] > 0 and r["relmse"] >= 0
            assert r["nonfinite"] == 0, "%s %s: non-finite pixels" % (s["scene"], r["method"])
        assert (out / "charts" / s["chart"]).stat().st_size > 0
        assert (out / "charts" / s["weighting_chart"]).stat().st_size > 0
        assert list((out / "refs").glob(s["scene"] + "_*.npy")) or s["reference"]["method"] == "exr"
    assert res["throughput"]["ratio_samples"] > 0
    assert (out / "charts" / "scaling_samples.png").exists()
    assert (out / "charts" / "scaling_depth.png").exists()
    for p in res["pyramids"]:
        assert p is None or p["max_abs_sum_error"] < 1e-3 * max(1.0, p["image_mean"])
    md = (out / "RESULTS.md").read_text()
    assert "SMOKE" in md and "python -m benchmarks.run --smoke" in md


def test_profile_pass_reports_kernels_against_path():
    """``python -m benchmarks.profile_pass``: one warm pass's launches, kernels and peak
    memory per lane, beside Mitsuba's path on the same samples."""
    proc = subprocess.run([sys.executable, "-m", "benchmarks.profile_pass", "--res", "16",
                           "--spp", "2", "--max-depth", "3"], cwd=str(ROOT), capture_output=True,
                          text=True, timeout=300, env=cli_env())
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.splitlines()
    assert lines[1].startswith("bdpt pass: 512 lanes") and "JIT" in lines[1]
    assert any(line.startswith("Mitsuba's path: 512 lanes") for line in lines)
    assert lines[-1].startswith("bdpt / path:")


def test_weighting_renders_the_four_schemes_and_reports_them(weighting):
    proc, out = weighting
    assert proc.returncode == 0, "benchmarks.run --weighting failed:\n%s\n%s" % (proc.stdout[-3000:],
                                                                                proc.stderr[-3000:])
    res = json.loads((out / "results.json").read_text())
    assert res["config"]["weighting"] and "throughput" not in res and "pyramids" not in res
    (s,) = res["scenes"]
    assert {r["method"] for r in s["records"]} == {"bdpt-power", "bdpt-balance", "bdpt-uniform",
                                                  "bdpt-lafortune"}
    assert s["chart"] is None and (out / "charts" / s["weighting_chart"]).stat().st_size > 0
    eq = s["weighting"]["time"]["methods"]
    assert eq["bdpt-power"]["err_ratio"] == 1 and eq["bdpt-uniform"]["err_at_x"] > 0
    md = (out / "RESULTS.md").read_text()
    assert "## MIS weighting schemes" in md and "| cornell-diffuse |" in md
    assert "## Error at equal time" not in md          # no baseline (path) in this run
    assert "--weighting" in md


def test_a_report_replaces_its_block_of_results_md(tmp_path):
    from benchmarks import common as C
    from benchmarks.report import as_block
    page = tmp_path / "RESULTS.md"
    page.write_text("# Results\n\n## Suite\n\nReading.\n\n<!-- suite: begin -->\nold\n"
                    "<!-- suite: end -->\n\n## Other\n")
    C.replace_block(page, "suite", as_block("# Benchmark results (FULL run)\n\nReproduce: x\n\n"
                                            "## Scene suite\n\n```\n# not a heading\n```\n"))
    assert page.read_text() == ("# Results\n\n## Suite\n\nReading.\n\n<!-- suite: begin -->\n"
                                "Reproduce: x\n\n### Scene suite\n\n```\n# not a heading\n```\n"
                                "<!-- suite: end -->\n\n## Other\n")
    with pytest.raises(SystemExit, match="weighting: begin"):
        C.replace_block(page, "weighting", "text")


def test_the_published_blocks_exist_in_results_md():
    """The blocks that benchmarks.run (--section: suite, weighting, media, scaling) and
    cluster_scaling publish into, each once."""
    from benchmarks import common as C
    for name in ("suite", "weighting", "media", "scaling", "cluster_scaling"):
        C.check_block(C.BENCH / "RESULTS.md", name)


def test_efficiency_against_path_without_a_reference():
    """``python -m benchmarks.efficiency``: each method's 1 / (relative variance across
    seeds x time) as a ratio to path's, path's being 1."""
    proc = subprocess.run([sys.executable, "-m", "benchmarks.efficiency", "--res", "16",
                           "--spp", "4", "--seeds", "2", "--scenes", "cornell-diffuse"],
                          cwd=str(ROOT), capture_output=True, text=True, timeout=300, env=cli_env())
    assert proc.returncode == 0, proc.stderr[-3000:]
    row = [line for line in proc.stdout.splitlines() if line.startswith("| cornell-diffuse")]
    assert len(row) == 1
    default, veach, path = [c.strip() for c in row[0].split("|")[3:6]]
    assert path.startswith("**1.00** (8 spp,")
    assert default.startswith("**") and "(4 spp," in default and "(2 spp," in veach


def _smallvcm_rgbe(rgb: np.ndarray) -> bytes:
    """RGBE bytes as SmallVCM's Framebuffer::SaveHDR writes them (frexp, truncation)."""
    v = rgb.max(-1)
    m, e = np.frexp(v)
    scale = np.where(v >= 1e-32, m * 256.0 / np.where(v > 0, v, 1.0), 0.0)
    out = np.zeros(rgb.shape[:-1] + (4,), np.uint8)
    out[..., :3] = (rgb * scale[..., None]).astype(np.uint8)
    out[..., 3] = np.where(v >= 1e-32, e + 128, 0)
    h, w = rgb.shape[:2]
    head = b"#?RADIANCE\n# SmallVCM\nFORMAT=32-bit_rle_rgbe\n\n-Y %d +X %d\n" % (h, w)
    return head + out.tobytes()


def test_smallvcm_hdr_reads_back_within_its_8_bit_mantissa(tmp_path):
    from benchmarks.smallvcm import read_hdr
    rgb = np.random.default_rng(3).lognormal(0.0, 2.0, (5, 7, 3))
    rgb[0, 0] = 0.0                                  # black pixels stay black
    path = tmp_path / "x.hdr"
    path.write_bytes(_smallvcm_rgbe(rgb))
    back = read_hdr(path)
    assert back.shape == (5, 7, 3) and np.all(back[0, 0] == 0.0)
    # a channel is kept to 1/256 of its pixel's largest, rows top-down as written
    assert np.all(np.abs(back - rgb) <= rgb.max(-1, keepdims=True) / 256.0)


def test_smallvcm_benchmark_skips_without_its_binary(tmp_path):
    r = subprocess.run([sys.executable, "-m", "benchmarks.smallvcm", str(tmp_path / "none")],
                       cwd=str(ROOT), capture_output=True, text=True, timeout=300, env=cli_env())
    assert r.returncode == 0 and "not found" in r.stdout


def test_benchmarks_load_scenes_without_mitsubas_merging(monkeypatch):
    """The benchmarks load their scenes as the API does (support.load_file): Mitsuba's
    merging of shapes that share a BSDF orders ``scene.emitters()`` differently from
    process to process, so an A/B run whose worker processes loaded Veach's room in
    different orders compared different images for the same seeds (RESULTS.md's
    per-process effect: 2 of 8 fresh processes drew its two lights in the other
    order)."""
    import mitsuba as mi
    from benchmarks import deep, throughput
    from benchmarks.scenes import SCENES
    loaded = []
    load = mi.load_file
    monkeypatch.setattr(mi, "load_file", lambda *a, **k: loaded.append(k) or load(*a, **k))
    SCENES["cornell-diffuse"].load(8, 8)
    throughput.load_scene(ROOT / "scenes" / "cornell-box.xml", 8, 8, 4)
    deep.load("deep-box", 8)
    assert [k.get("optimize") for k in loaded] == [False, False, False]
