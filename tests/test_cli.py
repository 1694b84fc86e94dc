"""The ``bdpt`` command line, driven as a user would: ``python -m bdpt_drjit ...`` in
a subprocess, on tiny images.  Also the EXR reader/writer (bdpt_drjit.exr)."""
import contextlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import mitsuba as mi
import pytest

from bdpt_drjit.exr import read_exr, read_layers, write_exr, write_layers
from bdpt_drjit.settings import PARAMS
from conftest import cli_env

ROOT = Path(__file__).resolve().parent.parent
CORNELL = str(ROOT / "scenes" / "cornell-box.xml")
NO_EMITTERS = str(ROOT / "scenes" / "no-emitters.xml")
TINY = ["-D", "resx=16", "-D", "resy=16"]

_SENSOR = ('<sensor type="%s"><film type="hdrfilm"><integer name="width" value="8"/>'
           '<integer name="height" value="8"/><rfilter type="box"/></film></sensor>')
SCENES = {
    "constant.xml": '<scene version="3.0.0"><emitter type="constant"/>%s'
                    '<shape type="sphere"/></scene>' % (_SENSOR % "perspective"),
    "directionalarea.xml": '<scene version="3.0.0"><shape type="rectangle">'
                           '<emitter type="directionalarea"/></shape>%s'
                           '<shape type="sphere"/></scene>' % (_SENSOR % "perspective"),
    "meter.xml": '<scene version="3.0.0"><sensor type="radiancemeter"><film type="hdrfilm">'
                 '<integer name="width" value="1"/><integer name="height" value="1"/></film>'
                 '</sensor><shape type="sphere"><emitter type="area"/></shape></scene>',
    "nosensor.xml": '<scene version="3.0.0"><shape type="sphere"><emitter type="area"/>'
                    '</shape></scene>',
    "malformed.xml": '<scene version="3.0.0"><shape type="sphere"></scene>',
    "unknown-plugin.xml": '<scene version="3.0.0"><shape type="spherez"/></scene>',
    "bad-bdpt.xml": '<scene version="3.0.0"><integrator type="bdpt"><string name="mis" '
                    'value="nope"/></integrator>%s<shape type="sphere"><emitter type="area"/>'
                    '</shape></scene>' % (_SENSOR % "perspective"),
    "two-sensors.xml": '<scene version="3.0.0">%s%s<shape type="sphere"><emitter type="area"/>'
                       '</shape></scene>' % (_SENSOR % "perspective", (_SENSOR % "perspective")
                                             .replace('"8"/>', '"12"/>', 1)),
}


def run_cli(*args, cwd=None, env=None, timeout=180):
    return subprocess.run([sys.executable, "-m", "bdpt_drjit", *map(str, args)], cwd=cwd,
                          env=cli_env(env), capture_output=True, text=True, timeout=timeout)


def ok(p):
    assert p.returncode == 0, "exit %d\nstdout:\n%s\nstderr:\n%s" % (p.returncode, p.stdout, p.stderr)
    assert "Traceback" not in p.stderr, p.stderr
    return p


def clean_error(p, *words):
    """A non-zero exit with a one-line 'bdpt: error:' message naming the problem."""
    assert p.returncode != 0, "expected a failure\nstdout:\n%s\nstderr:\n%s" % (p.stdout, p.stderr)
    assert "Traceback" not in p.stderr, p.stderr
    errors = [line for line in p.stderr.splitlines() if line.startswith("bdpt: error:")]
    assert len(errors) == 1, p.stderr
    for w in words:
        assert w.lower() in errors[0].lower(), "%r not in %r" % (w, errors[0])
    return errors[0]


def written(folder):
    return sorted(p.name for p in Path(folder).rglob("*")
                  if p.is_file() and p.suffix != ".xml")


@pytest.fixture
def scenes(tmp_path):
    d = tmp_path / "scenes"
    d.mkdir()
    for name, text in SCENES.items():
        (d / name).write_text(text)
    return d


# -- render -----------------------------------------------------------------------------
def test_render_writes_exr_png_and_strategies(tmp_path):
    out = tmp_path / "out.exr"
    out.write_bytes(b"not an exr: must be overwritten")
    p = ok(run_cli("render", CORNELL, *TINY, "--spp", 8, "--seed", 5, "-o", out,
                   "--strategy-images", cwd=tmp_path))
    img, meta = read_exr(out)
    assert img.shape == (16, 16, 3) and img.dtype == np.float32
    assert np.all(np.isfinite(img))
    assert 0.1 < img.mean() < 0.6          # the Cornell box is about 0.3
    assert meta["spp"] == 8 and isinstance(meta["spp"], int)
    assert meta["seed"] == 5 and meta["passes"] >= 1 and meta["render_time"] > 0
    assert meta["scene"].endswith("cornell-box.xml") and meta["bdpt_version"]
    assert meta["max_depth"] == 8          # from the scene's integrator
    assert (tmp_path / "out.png").stat().st_size > 0
    # Per-strategy layers add up to the image; the contact sheet has a row per k.
    layers, smeta = read_layers(tmp_path / "out.strategies.exr")
    assert smeta["spp"] == 8
    np.testing.assert_allclose(layers[""], img)
    strategies = {k: v for k, v in layers.items() if k}
    assert "s1t2" in strategies and "s0t2" in strategies
    np.testing.assert_allclose(sum(strategies.values()), img, rtol=1e-4, atol=1e-5)
    import mitsuba as mi
    sheet = np.array(mi.Bitmap(str(tmp_path / "out.strategies.png")))
    kmax = max(int(k[1:].split("t")[0]) + int(k.split("t")[1]) - 1 for k in strategies)
    assert sheet.shape[0] == 2 + kmax * (16 + 2)
    # One summary line with spp, time, rate and the outputs.
    summary = p.stdout.strip().splitlines()[-1]
    assert "8 spp" in summary and "samples/s" in summary and str(out) in summary
    assert not [f for f in written(tmp_path) if f.endswith(".tmp")]


def test_render_default_scene_and_output_name(tmp_path):
    ok(run_cli("render", *TINY, "--spp", 2, "--max-depth", 2, "-q", cwd=tmp_path))
    img, meta = read_exr(tmp_path / "cornell-box.exr")
    assert img.shape == (16, 16, 3) and meta["spp"] == 2 and meta["max_depth"] == 2
    assert (tmp_path / "cornell-box.png").exists()


def test_render_settings_and_res(tmp_path):
    out = tmp_path / "t.exr"
    ok(run_cli("render", CORNELL, "--res", "12x8", "--spp", 2, "--technique", "1,2",
               "--mis", "balance", "--rr-depth", 3, "--hide-emitters", "-o", out))
    img, meta = read_exr(out)
    assert img.shape == (8, 12, 3)
    assert meta["technique"] == "1,2" and meta["mis"] == "balance" and meta["rr_depth"] == 3
    assert meta["hide_emitters"] == 1


def test_renderer_options_come_from_params():
    """Every integrator parameter is an option, with its choices, bounds and doc."""
    text = " ".join(ok(run_cli("render", "--help")).stdout.split())
    for p in PARAMS:
        assert p.flag in text, p.flag
        for choice in p.choices or ():
            assert choice in text
        assert " ".join(p.doc.replace("``", "").split()[:4]) in text, p.name


def test_old_option_spellings_still_work_and_warn(tmp_path):
    out = tmp_path / "old.exr"
    p = ok(run_cli("render", CORNELL, *TINY, "--spp", 2, "--max-depth", 3, "--strategy-set",
                   "pt", "--strategies", "-o", out))
    warnings = [line for line in p.stderr.splitlines() if "deprecated" in line]
    assert warnings == ["bdpt: warning: --strategy-set is deprecated; use --strategy-subset",
                        "bdpt: warning: --strategies is deprecated; use --strategy-images"]
    _, meta = read_exr(out)
    assert meta["strategy_subset"] == "pt" and meta["light_image"] == 0
    layers, _ = read_layers(tmp_path / "old.strategies.exr")
    assert "s1t2" in layers and not [k for k in layers if k.endswith("t1")]


def test_sensor_option(tmp_path, scenes):
    """--sensor N renders the scene's N-th sensor (here 12x8; the first is 8x8)."""
    out = tmp_path / "s1.exr"
    ok(run_cli("render", scenes / "two-sensors.xml", "--spp", 1, "--sensor", 1, "-o", out))
    img, meta = read_exr(out)
    assert img.shape == (8, 12, 3) and meta["sensor"] == 1
    p = ok(run_cli("info", scenes / "two-sensors.xml", "--sensor", 1))
    assert "[1: rendered]" in p.stdout and "[0; --sensor 0 renders it]" in p.stdout


def test_no_emitters_warns_and_renders_black(tmp_path):
    out = tmp_path / "black.exr"
    p = ok(run_cli("render", NO_EMITTERS, "-D", "resx=8", "-D", "resy=8", "--spp", 2, "-o", out))
    assert "no emitters" in p.stderr and "black" in p.stderr
    img, meta = read_exr(out)
    assert meta["spp"] == 2 and np.all(img == 0)


# -- progressive rendering --------------------------------------------------------------------
@contextlib.contextmanager
def background_render(out, *extra, stderr=subprocess.PIPE):
    """A render of ~2000 passes (far longer than a test waits), killed if the test
    leaves it running.  Fixed budgets: every pass is a round of 2 spp (an "auto"
    render opens with a pilot round of two half passes)."""
    proc = subprocess.Popen([sys.executable, "-m", "bdpt_drjit", "render", CORNELL, *TINY,
                             "--spp", "4096", "--samples-per-pass", "2", "--max-depth", "3",
                             "--light-paths", "1", "--connections", "all",
                             "-o", str(out), *map(str, extra)],
                            stdout=subprocess.PIPE, stderr=stderr, text=True, env=cli_env())
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_stops_after_current_pass(tmp_path, sig):
    out = tmp_path / "int.exr"
    spp, per_pass = 4096, 2
    lines = []
    with background_render(out) as proc:
        for line in proc.stderr:
            lines.append(line)
            if line.startswith("bdpt: [") and "passes" in line:
                break
        assert proc.poll() is None, "render ended before it could be interrupted:\n" + "".join(lines)
        assert "samples/s" in lines[-1] and "left" in lines[-1]
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=120)
    stderr = "".join(lines) + stderr
    assert proc.returncode == 128 + sig, stderr      # 130 for SIGINT, 143 for SIGTERM
    assert "Traceback" not in stderr
    img, meta = read_exr(out)
    assert np.all(np.isfinite(img)) and img.mean() > 0
    done = meta["spp"]
    assert 0 < done < spp and done % per_pass == 0
    assert meta["passes"] == done // per_pass
    assert "interrupted" in stderr and "%d of %d spp" % (done, spp) in stderr
    assert (tmp_path / "int.png").exists()
    assert not [f for f in written(tmp_path) if f.endswith(".tmp")]


def test_a_signal_stops_a_render_whose_passes_run_mitsubas_path(tmp_path):
    """Where the default budget path-traces, the passes run Mitsuba's path, which reads
    nothing back: they were queued, not rendered, and a Ctrl-C waited for all of them
    (minutes).  Now it stops within a pass and writes the passes done."""
    out = tmp_path / "pane.exr"
    proc = subprocess.Popen([sys.executable, "-m", "bdpt_drjit", "render",
                             str(ROOT / "scenes" / "glass-pane.xml"), "--res", "64x64",
                             "--spp", "1000000", "-o", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=cli_env())
    try:
        lines = []
        for line in proc.stderr:     # the progress after the pilot's round
            lines.append(line)
            if line.startswith("bdpt: [") and int(line.split()[2].split("/")[0]) > 2:
                break
        time.sleep(4)                # long enough to queue thousands of passes before
        proc.send_signal(signal.SIGINT)
        start = time.perf_counter()
        _, stderr = proc.communicate(timeout=60)
        waited = time.perf_counter() - start
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    stderr = "".join(lines) + stderr
    assert proc.returncode == 130, stderr
    assert waited < 10, stderr
    img, meta = read_exr(out)
    assert 0 < meta["spp"] < 1000000 and np.all(np.isfinite(img)) and img.mean() > 0
    assert "light_paths=0" in meta["budget"], meta["budget"]


def test_a_time_budget_holds_where_the_passes_run_mitsubas_path(tmp_path):
    """The time budget of a render whose passes run Mitsuba's path (the pilot chose path
    tracing behind the glass pane): the reported render time is the time the passes
    took (--time 5 took 29 s before, its passes counted before they ran)."""
    out = tmp_path / "pane.exr"
    start = time.perf_counter()
    p = ok(run_cli("render", ROOT / "scenes" / "glass-pane.xml", "--res", "64x64", "--spp",
                   1000000, "--time", 3, "-o", out))
    elapsed = time.perf_counter() - start
    _, meta = read_exr(out)
    assert "light_paths=0" in meta["budget"] and "time budget" in p.stderr
    assert 2.7 <= meta["render_time"] < 3.3
    # The process's wall time: the render and Python's, Mitsuba's and the scene's start
    # (2-3 s here; before, the queued passes took 8 s more).
    assert elapsed < meta["render_time"] + 5, (elapsed, meta["render_time"])


def test_time_budget(tmp_path):
    out = tmp_path / "timed.exr"
    start = time.perf_counter()
    p = ok(run_cli("render", CORNELL, *TINY, "--spp", 1000000, "--samples-per-pass", 4,
                   "--max-depth", 3, "--time", 1, "-o", out))
    elapsed = time.perf_counter() - start
    _, meta = read_exr(out)
    assert 0 < meta["spp"] < 1000000 and meta["spp"] % 4 == 0
    assert meta["render_time"] >= 0.8
    assert "time budget" in p.stderr
    assert elapsed < 60


def test_a_time_budget_spent_in_the_pilot_stops_after_its_round(tmp_path):
    """On a large film the default budget's pilot round is two passes (the pilot on
    the even pixels, then the odd ones with the budget chosen: optimizer.Pilot.stride,
    here 4 x PILOT_LANES pixels at 1 spp per pass); a time budget spent in the first
    stopped there and wrote the odd pixels black (seen on a GPU, whose first pass
    compiled for longer than the budget)."""
    from bdpt_drjit.optimizer import PILOT_LANES
    lanes = PILOT_LANES["cuda" if os.environ.get("BDPT_VARIANT", "").startswith("cuda")
                        else "llvm"]
    out = tmp_path / "pilot.exr"
    p = ok(run_cli("render", CORNELL, "-D", f"resx={lanes // 32}", "-D", "resy=128", "--spp", 16,
                   "--samples-per-pass", 1, "--max-depth", 3, "--time", 0.001, "-o", out))
    _, meta = read_exr(out)
    assert meta["spp"] == 1 and meta["passes"] == 2 and "time budget" in p.stderr


def test_time_budget_on_a_film_split_in_pixel_ranges(tmp_path):
    """A film too large for one pass at 1 spp is rendered in pixel ranges; a time
    budget (or a checkpoint) must never leave pixels without camera samples: the
    render stops at the end of a round, with spp >= 1, and equals a 1-spp render."""
    small = ["--memory-budget", "1M", "-D", "resx=64", "-D", "resy=64", "--max-depth", 3]
    timed, full = tmp_path / "timed.exr", tmp_path / "one.exr"
    p = ok(run_cli("render", CORNELL, *small, "--spp", 8, "--time", 0.001,
                   "--checkpoint", 0.001, "-o", timed))
    ok(run_cli("render", CORNELL, *small, "--spp", 1, "-o", full))
    img, meta = read_exr(timed)
    ref, ref_meta = read_exr(full)
    assert meta["passes"] == ref_meta["passes"] > 1           # one round of pixel ranges
    assert meta["spp"] == 1 and "time budget" in p.stderr
    np.testing.assert_allclose(img, ref, rtol=1e-5, atol=1e-6)


def test_time_and_checkpoint_use_many_passes(tmp_path):
    out = tmp_path / "ck.exr"
    # --time / --checkpoint without --samples-per-pass: spp/16 per pass, the default
    # "auto" budget's pilot pass among them.
    ok(run_cli("render", CORNELL, *TINY, "--spp", 32, "--max-depth", 3, "--time", 300,
               "--checkpoint", 0.01, "-o", out))
    _, meta = read_exr(out)
    assert meta["spp"] == 32 and meta["passes"] == 16 and meta["samples_per_pass"] == 2
    assert "chose" in meta["budget_decision"]
    # The memory budget as resolved here ("auto" follows the machine: backend.py), so
    # that the header says which passes, and so which image, the seed gave.
    from bdpt_drjit import backend
    assert int(meta["memory_budget"]) == backend.default_memory_budget()


def _wait_until_importing(proc, library="drjit", timeout=60.0):
    """Wait until ``proc`` has begun loading Dr.Jit's extension modules (on Linux: the
    library appears in /proc/PID/maps), so that a delay after that hits the import,
    not Python's own start-up (site-packages' .pth files, 50-100 ms here)."""
    maps = Path("/proc/%d/maps" % proc.pid)
    end = time.perf_counter() + timeout
    while maps.exists() and time.perf_counter() < end and proc.poll() is None:
        with contextlib.suppress(OSError):
            if library in maps.read_text():
                return
        time.sleep(0.002)


@pytest.mark.parametrize("delay, sig", [(0.0, signal.SIGINT), (0.05, signal.SIGINT),
                                        (0.1, signal.SIGINT), (0.15, signal.SIGINT),
                                        (0.2, signal.SIGINT), (0.3, signal.SIGINT),
                                        (0.45, signal.SIGINT), (0.1, signal.SIGTERM)])
def test_signal_while_starting(tmp_path, delay, sig):
    """Ctrl-C or SIGTERM while Mitsuba is imported, the scene loaded or the first pass
    compiled: one line and exit status 128 + signal, never a traceback or an abort."""
    with background_render(tmp_path / "start.exr", "-q") as proc:
        _wait_until_importing(proc)
        time.sleep(delay)
        proc.send_signal(sig)
        _, stderr = proc.communicate(timeout=120)
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert proc.returncode == 128 + sig, stderr
    assert len(lines) == 1 and lines[0].startswith("bdpt: interrupted (%s)" % sig.name), stderr


def _wait_for(condition, what, timeout=60.0):
    end = time.perf_counter() + timeout
    while not condition():
        assert time.perf_counter() < end, "timed out waiting for " + what
        time.sleep(0.02)


@pytest.mark.parametrize("restore", [True, False], ids=["checkpoint-fails", "final-write-fails"])
def test_failed_write(tmp_path, restore):
    """A checkpoint that cannot be written (here: the output became a directory, so
    the atomic rename fails) is one warning and rendering goes on; if the final write
    fails too, the exit status says so, in one line."""
    out, log = tmp_path / "ck.exr", tmp_path / "stderr.txt"
    with open(log, "w") as err, background_render(out, "--checkpoint", "0.05", "-q",
                                                  stderr=err) as proc:
        _wait_for(lambda: out.exists() or proc.poll() is not None, "the first checkpoint")
        while not out.is_dir():          # a checkpoint may land between the two steps
            with contextlib.suppress(FileNotFoundError, FileExistsError):
                out.unlink()
                out.mkdir()
        _wait_for(lambda: "not saved" in log.read_text() or proc.poll() is not None,
                  "a failed checkpoint")
        if restore:
            out.rmdir()
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=120)
    stderr = log.read_text()
    assert "Traceback" not in stderr
    warnings = [line for line in stderr.splitlines()
                if line.startswith("bdpt: warning: checkpoint")]
    assert len(warnings) == 1, stderr         # said once while the problem lasts
    assert "cannot write %s" % out in warnings[0] and "rendering goes on" in warnings[0]
    if restore:
        assert proc.returncode == 130, stderr
        img, meta = read_exr(out)
        assert meta["spp"] > 0 and np.all(np.isfinite(img))
    else:
        assert proc.returncode == 1, stderr
        errors = [line for line in stderr.splitlines() if line.startswith("bdpt: error:")]
        assert len(errors) == 1 and "cannot write %s" % out in errors[0], stderr


# -- merge ----------------------------------------------------------------------------------
def test_merge_is_spp_weighted_and_matches_single_render(tmp_path):
    common = ["render", CORNELL, "-D", "resx=32", "-D", "resy=32", "--max-depth", 4, "-q"]
    a, b, single = tmp_path / "a.exr", tmp_path / "b.exr", tmp_path / "single.exr"
    ok(run_cli(*common, "--spp", 16, "--seed", 1, "-o", a))
    ok(run_cli(*common, "--spp", 48, "--seed", 2, "-o", b))
    ok(run_cli(*common, "--spp", 64, "--seed", 3, "-o", single))
    merged = tmp_path / "merged.exr"
    p = ok(run_cli("merge", a, b, "-o", merged))
    assert "64" in p.stdout
    ia, _ = read_exr(a)
    ib, _ = read_exr(b)
    im, meta = read_exr(merged)
    assert meta["spp"] == 64
    assert [int(s) for s in str(meta["seed"]).split(",")] == [1, 2]
    np.testing.assert_allclose(im, (16 * ia + 48 * ib) / 64, rtol=1e-6, atol=1e-7)
    assert (tmp_path / "merged.png").exists()
    # The merge is an unbiased 64 spp estimate: compare it with an independent 64 spp
    # render.  The difference image has zero mean in every pixel; its pixels are
    # (nearly) independent, so their spread bounds the error of the whole-image mean.
    isingle, _ = read_exr(single)
    d = (im - isingle).mean(axis=2).ravel()
    z = d.mean() / (d.std(ddof=1) / np.sqrt(d.size))
    assert abs(z) < 4, "merged mean %.5f vs single %.5f (z = %.2f)" % (im.mean(), isingle.mean(), z)
    # A merged image merges again, keeping track of every seed; a repeated seed is refused.
    again = tmp_path / "again.exr"
    ok(run_cli("merge", merged, single, "-o", again))
    _, meta2 = read_exr(again)
    assert meta2["spp"] == 128 and str(meta2["seed"]) == "1,2,3"
    clean_error(run_cli("merge", merged, a, "-o", tmp_path / "bad.exr"), "seed 1")
    assert not (tmp_path / "bad.exr").exists()


def test_merge_refuses_bad_inputs(tmp_path):
    img = np.ones((8, 8, 3), np.float32)
    write_exr(tmp_path / "a.exr", img, {"spp": 4, "seed": 1})
    write_exr(tmp_path / "same-seed.exr", img, {"spp": 4, "seed": 1})
    write_exr(tmp_path / "small.exr", np.ones((4, 8, 3), np.float32), {"spp": 4, "seed": 2})
    write_exr(tmp_path / "nospp.exr", img, {"seed": 3})
    (tmp_path / "junk.exr").write_text("junk")
    out = tmp_path / "out.exr"
    cases = [(["a.exr", "small.exr"], ["size"]),
             (["a.exr", "same-seed.exr"], ["seed"]),
             (["a.exr", "nospp.exr"], ["nospp.exr", "spp"]),
             (["a.exr", "missing.exr"], ["missing.exr", "not found"]),
             (["a.exr", "junk.exr"], ["junk.exr"]),
             (["a.exr"], ["two"])]
    for inputs, words in cases:
        clean_error(run_cli("merge", *inputs, "-o", out, cwd=tmp_path), *words)
        assert not out.exists() and not (tmp_path / "out.png").exists()


# -- bad input ----------------------------------------------------------------------------
BAD = [
    ("missing scene", ["render", "no-such-scene.xml"], ["no-such-scene.xml", "not found"]),
    ("malformed xml", ["render", "{scenes}/malformed.xml"], ["malformed.xml", "mismatch"]),
    ("unknown plugin", ["render", "{scenes}/unknown-plugin.xml"], ["spherez"]),
    ("directionalarea emitter", ["render", "{scenes}/directionalarea.xml"],
     ["unsupported", "directionalarea"]),
    ("radiancemeter sensor", ["render", "{scenes}/meter.xml"], ["unsupported", "radiancemeter"]),
    ("no sensor", ["render", "{scenes}/nosensor.xml"], ["no sensor"]),
    ("spp 0", ["render", CORNELL, *TINY, "--spp", "0"], ["--spp", "positive"]),
    ("spp negative", ["render", CORNELL, *TINY, "--spp", "-4"], ["--spp"]),
    ("spp 0 via -D", ["render", CORNELL, *TINY, "-D", "spp=0"], ["spp", "positive"]),
    ("max_depth -2", ["render", CORNELL, *TINY, "--max-depth", "-2"], ["--max-depth", "-1"]),
    ("unknown variant", ["render", CORNELL, *TINY, "--variant", "llvm_foo_rgb"],
     ["variant", "llvm_foo_rgb"]),
    ("scalar variant", ["render", CORNELL, *TINY, "--variant", "scalar_rgb"], ["scalar_rgb", "JIT"]),
    ("unknown parameter", ["render", CORNELL, *TINY, "-D", "nonsense=3"], ["$nonsense"]),
    ("bad -D", ["render", CORNELL, "-D", "resx"], ["key=value"]),
    ("bad --res", ["render", CORNELL, "--res", "16"], ["--res"]),
    ("bad technique", ["render", CORNELL, *TINY, "--technique", "x"], ["--technique"]),
    ("output not exr", ["render", CORNELL, *TINY, "-o", "{tmp}/out.png"], [".exr"]),
    ("output dir missing", ["render", CORNELL, *TINY, "-o", "{tmp}/nowhere/out.exr"],
     ["cannot write", "does not exist"]),
    ("output parent is a file", ["render", CORNELL, *TINY, "-o", "{tmp}/scenes/meter.xml/out.exr"],
     ["cannot write"]),
    ("info missing scene", ["info", "no-such-scene.xml"], ["not found"]),
    ("info missing image", ["info", "no-such-image.exr"], ["no-such-image.exr", "not found"]),
    ("bad bdpt parameter in the scene", ["render", "{scenes}/bad-bdpt.xml"],
     ["bad-bdpt.xml", "heuristic 'nope'", "choose one of"]),
    ("technique past max_depth", ["render", CORNELL, *TINY, "--technique", "9,9"],
     ["technique 9,9", "max_depth 8", "black"]),
    ("light-tracing technique outside pt",
     ["render", CORNELL, *TINY, "--technique", "2,1", "--strategy-subset", "pt"],
     ["technique 2,1", "strategy_subset 'pt'"]),
    ("rr_depth 0", ["render", CORNELL, *TINY, "--rr-depth", "0"], ["--rr-depth", "positive"]),
    ("memory budget too small", ["render", CORNELL, *TINY, "--memory-budget", "1K"],
     ["--memory-budget", "1 MiB"]),
    ("sensor out of range", ["render", CORNELL, *TINY, "--sensor", "1"],
     ["--sensor 1", "1 sensor"]),
    ("info sensor out of range", ["info", "{scenes}/two-sensors.xml", "--sensor", "2"],
     ["--sensor 2", "2 sensors"]),
    ("unknown command option", ["render", "--frobnicate"], ["--frobnicate"]),
]


@pytest.mark.parametrize("args, words", [b[1:] for b in BAD], ids=[b[0] for b in BAD])
def test_bad_input(tmp_path, scenes, args, words):
    args = [a.format(scenes=scenes, tmp=tmp_path) for a in args]
    if args[0] == "render" and "-o" not in args:
        args += ["-o", str(tmp_path / "out.exr")]
    error = clean_error(run_cli(*args, cwd=tmp_path), *words)
    assert written(tmp_path) == [], "files were written: %s" % written(tmp_path)
    if "2,1" in args:          # the user never set light_image: not blamed
        assert "light_image" not in error, error


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root can write anywhere")
def test_unwritable_directory(tmp_path):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        clean_error(run_cli("render", CORNELL, *TINY, "-o", locked / "out.exr"), "cannot write")
    finally:
        locked.chmod(0o700)
    assert written(locked) == []


def _old_llvm():
    import glob
    for pat in ("/usr/lib/x86_64-linux-gnu/libLLVM-1[0-5].so", "/usr/lib/llvm-1[0-5]/lib/libLLVM*.so",
                "/usr/lib/aarch64-linux-gnu/libLLVM-1[0-5].so"):
        found = sorted(glob.glob(pat))
        if found:
            return found[-1]
    return None


@pytest.mark.skipif(_old_llvm() is None, reason="no LLVM <= 15 on this machine to test with")
def test_old_llvm_is_refused(tmp_path):
    p = run_cli("render", CORNELL, *TINY, "-o", tmp_path / "out.exr",
                env={"DRJIT_LIBLLVM_PATH": _old_llvm()})
    clean_error(p, "LLVM", ">= 16", "install")
    assert written(tmp_path) == []


def test_missing_llvm_is_refused(tmp_path):
    p = run_cli("render", CORNELL, *TINY, "-o", tmp_path / "out.exr", "--variant", "llvm_ad_rgb",
                env={"DRJIT_LIBLLVM_PATH": str(tmp_path / "libLLVM-missing.so")})
    clean_error(p, "LLVM", "install")
    assert written(tmp_path) == []


# -- info -------------------------------------------------------------------------------------
def test_unit_costs_are_measured_once_and_by_calibrate(tmp_path):
    """Without a calibration file the first "auto" render measures the machine's unit
    costs (units.py) and says so; later renders read them; ``bdpt calibrate`` measures
    again.  The EXR header records the counts and the units the decision priced."""
    env = {"BDPT_CALIBRATION": "", "XDG_CACHE_HOME": str(tmp_path / "cache")}
    args = ["render", CORNELL, *TINY, "--spp", 16, "--max-depth", 3]
    first = ok(run_cli(*args, "-o", tmp_path / "a.exr", env=env))
    assert "measuring this machine's unit costs" in first.stderr
    variant = mi.variant()          # the CLI's default: the tests' variant (BDPT_VARIANT)
    files = list((tmp_path / "cache" / "bdpt-drjit").glob("bdpt-units-%s-*.json" % variant))
    assert len(files) == 1
    stored = json.loads(files[0].read_text())["variants"][variant]
    assert set(stored) == {"camera_ray", "light_ray", "stored_vertex", "connection", "path_ray",
                           "grid_vertex", "merge_step"}
    assert all(0 < v < 1e-3 for v in stored.values()), stored
    second = ok(run_cli(*args, "-o", tmp_path / "b.exr", env=env))
    assert "measuring" not in second.stderr
    _, meta = read_exr(tmp_path / "b.exr")
    assert "camera_rays=" in meta["cost_counts"]
    assert "path_ray=%.3g" % stored["path_ray"] in meta["unit_costs"]
    again = ok(run_cli("calibrate", "--repeats", 1, env=env))
    assert str(files[0]) in again.stdout


def test_info(scenes):
    p = ok(run_cli("info", CORNELL, "--res", "16x16"))
    out = p.stdout
    assert "perspective" in out and "16x16" in out and "area" in out
    assert "twosided" in out and "diffuse" in out and "supported" in out
    assert "REFUSED" not in out
    # The unit costs decisions price with (the tests' file), and no calibration by info.
    pinned = json.loads(Path(os.environ["BDPT_CALIBRATION"]).read_text())
    camera_ray = pinned["variants"][mi.variant()]["camera_ray"]
    assert "units:      camera_ray=%.3g" % camera_ray in out and "calibration.json" in out
    fresh = ok(run_cli("info", CORNELL, env={"BDPT_CALIBRATION": str(scenes / "none.json")}))
    assert "not measured yet" in fresh.stdout and "measuring" not in fresh.stderr
    p = ok(run_cli("info", scenes / "directionalarea.xml"))
    assert "directionalarea" in p.stdout and "REFUSED" in p.stdout
    p = ok(run_cli("info", scenes / "constant.xml"))
    assert "constant" in p.stdout and "REFUSED" not in p.stdout
    p = ok(run_cli("info", NO_EMITTERS))
    assert "black" in p.stdout


def test_info_of_an_image(tmp_path):
    """``bdpt info out.exr`` shows the render's header, as pbrt's imgtool info does."""
    out = tmp_path / "r.exr"
    ok(run_cli("render", CORNELL, *TINY, "--spp", 2, "--seed", 7, "--mis", "balance",
               "--strategy-images", "-o", out))
    text = ok(run_cli("info", out)).stdout
    fields = dict(re.findall(r"^(\w+):\s+(.*)$", text, re.M))
    assert fields["size"] == "16x16" and fields["channels"] == "R, G, B"
    assert fields["spp"] == "2" and fields["seed"] == "7" and fields["mis"] == "balance"
    assert fields["scene"].endswith("cornell-box.xml") and float(fields["render_time"]) > 0
    assert fields["max_depth"] == "8" and fields["technique"] == "all"
    layers = ok(run_cli("info", tmp_path / "r.strategies.exr")).stdout
    assert "s1t2" in layers and "seed:" in layers
    write_exr(tmp_path / "plain.exr", np.ones((4, 6, 3), np.float32))
    assert "nothing from bdpt" in ok(run_cli("info", tmp_path / "plain.exr")).stdout
    (tmp_path / "junk.exr").write_text("junk")
    clean_error(run_cli("info", tmp_path / "junk.exr"), "junk.exr", "OpenEXR")


def test_console_script_and_help():
    exe = shutil.which("bdpt")
    if exe is None:
        pytest.skip("the bdpt console script is not installed (pip install -e .)")
    p = subprocess.run([exe, "render", "--help"], capture_output=True, text=True, timeout=60,
                       env=cli_env())
    assert p.returncode == 0 and "--spp" in p.stdout and "--strategy-images" in p.stdout
    p = subprocess.run([exe], capture_output=True, text=True, timeout=60, env=cli_env())
    assert p.returncode != 0 and "Traceback" not in p.stderr


# -- EXR module -------------------------------------------------------------------------------
def test_exr_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    meta = {"spp": 64, "seed": 7, "scene": "x.xml", "render_time": 1.5, "flag": True,
            "huge": 2 ** 40, "npint": np.int64(3), "obj": (1, 2)}
    for c in (1, 3, 4, 5):
        img = rng.random((5, 7, c), dtype=np.float32) * 100
        path = tmp_path / ("c%d.exr" % c)
        write_exr(path, img, meta)
        back, m = read_exr(path)
        assert back.dtype == np.float32 and back.shape == img.shape
        np.testing.assert_array_equal(back, img)
        assert m["spp"] == 64 and isinstance(m["spp"], int) and m["seed"] == 7
        assert m["scene"] == "x.xml" and m["render_time"] == 1.5 and m["flag"] == 1
        assert m["huge"] == str(2 ** 40) and m["npint"] == 3 and m["obj"] == "(1, 2)"
        assert "channels" not in m
    # 2-D input is one channel; existing files are replaced.
    write_exr(tmp_path / "c1.exr", np.zeros((2, 3)))
    back, m = read_exr(tmp_path / "c1.exr")
    assert back.shape == (2, 3, 1) and m == {}
    # Layers.
    layers = {"s1t2": rng.random((4, 4, 3), dtype=np.float32),
              "s0t3": rng.random((4, 4, 3), dtype=np.float32)}
    write_layers(tmp_path / "l.exr", layers, {"spp": 2}, image=layers["s1t2"] + layers["s0t3"])
    back, m = read_layers(tmp_path / "l.exr")
    assert set(back) == {"", "s1t2", "s0t3"} and m["spp"] == 2
    for k, v in layers.items():
        np.testing.assert_array_equal(back[k], v)
    import OpenEXR
    names = set(OpenEXR.File(str(tmp_path / "l.exr"), separate_channels=True).channels())
    assert {"s1t2.R", "s1t2.G", "s1t2.B", "R", "G", "B"} <= names
    assert not [f for f in written(tmp_path) if f.endswith(".tmp")]


def test_exr_failed_write_keeps_old_file(tmp_path):
    path = tmp_path / "keep.exr"
    write_exr(path, np.ones((2, 2, 3)), {"spp": 1})
    with pytest.raises(ValueError):
        write_exr(path, np.zeros((2, 2, 3)), {"channels": "reserved"})
    with pytest.raises(ValueError):
        write_exr(path, np.zeros((0, 2, 3)))
    img, meta = read_exr(path)
    assert np.all(img == 1) and meta["spp"] == 1
    assert written(tmp_path) == ["keep.exr"]


def test_strategy_images_at_unbounded_depth_stay_readable(tmp_path):
    """--strategy-images with max_depth -1 writes a bounded number of layers (per
    (s,t) up to k = 8, per path length up to 16, then one), well under OpenImageIO's
    1024-channel limit; they add up to the image."""
    out = tmp_path / "deep.exr"
    ok(run_cli("render", CORNELL, "-D", "resx=32", "-D", "resy=18", "--spp", 4,
               "--max-depth", -1, "--strategy-images", "-o", out))
    layers, _ = read_layers(tmp_path / "deep.strategies.exr")
    named = {k: v for k, v in layers.items() if k}
    assert len(named) <= 53 and 3 * len(layers) < 1024
    np.testing.assert_allclose(sum(named.values()), layers[""], rtol=1e-4, atol=1e-5)
