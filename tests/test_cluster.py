"""Rendering on a Ray cluster (bdpt_drjit.cluster), on a local:2 cluster of this machine.

A pass's samples depend only on (seed, index), and the driver adds the workers' raw film
sums in pass order, so a cluster render is the local render of the same seed and plan,
to float rounding: whichever worker ran a pass, however often, and wherever it stopped.
"""
import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from bdpt_drjit import units
from bdpt_drjit.exr import read_exr
from test_cli import CORNELL, clean_error, cli_env, ok, run_cli

try:
    import ray  # noqa: F401
    HAVE_RAY = True
except ImportError:
    HAVE_RAY = False
needs_ray = pytest.mark.skipif(not HAVE_RAY, reason="Ray is not installed "
                               "(pip install 'bdpt-drjit[cluster]'; ./dev test installs it)")

# 128 passes of 2 spp at 24x24: long enough to kill a worker in the middle.  The budget
# is fixed (an "auto" one is chosen from measured times: test_auto_budget_on_a_cluster).
SCENE = [CORNELL, "-D", "resx=24", "-D", "resy=24", "--max-depth", "4", "--seed", "7",
         "--samples-per-pass", "2", "--light-paths", "1", "--connections", "all"]
SPP = 256


@contextlib.contextmanager
def rendering(out, spp):
    """A local:2 cluster render in a subprocess, once it shows progress: the process and
    its stderr so far; killed if the test leaves it running."""
    proc = subprocess.Popen([sys.executable, "-m", "bdpt_drjit", "render", *SCENE, "-o", str(out),
                             "--spp", str(spp), "--cluster", "local:2"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=cli_env())
    try:
        yield proc, _wait_for_progress(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def same_image(path, ref_path):
    img, meta = read_exr(path)
    ref, ref_meta = read_exr(ref_path)
    np.testing.assert_allclose(img, ref, rtol=1e-5, atol=1e-6)
    assert meta["spp"] == ref_meta["spp"] and meta["passes"] == ref_meta["passes"]
    return meta


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return tmp_path_factory.mktemp("cluster")


@pytest.fixture(scope="module")
def local_render(folder):
    """The plain local render that every cluster render here must equal."""
    out = folder / "local.exr"
    ok(run_cli("render", *SCENE, "--spp", SPP, "-q", "-o", out))
    return out


@pytest.fixture(scope="module")
def cluster_render(folder):
    out = folder / "cluster.exr"
    p = ok(run_cli("render", *SCENE, "--spp", SPP, "--cluster", "local:2", "-o", out))
    return out, p


@needs_ray
def test_cluster_render_is_the_local_render(local_render, cluster_render):
    out, p = cluster_render
    meta = same_image(out, local_render)
    assert meta["spp"] == SPP and isinstance(meta["spp"], int) and meta["passes"] == SPP // 2
    assert meta["cluster"] == "local:2" and meta["workers"] == 2 and meta["seed"] == 7
    assert "on 2 workers" in p.stdout.strip().splitlines()[-1]
    assert "2 workers alive" in p.stderr and "2 workers ready" in p.stderr


@needs_ray
def test_auto_budget_on_a_cluster(folder, local_render):
    """The pilot runs on one worker, every later pass uses the budget it chose (the
    workers share one plan: no re-decisions), and the image agrees with the
    fixed-budget render (both are unbiased)."""
    out = folder / "auto.exr"
    auto = SCENE[:-4]
    assert auto[-2:] == ["--samples-per-pass", "2"]
    ok(run_cli("render", *auto, "--spp", 64, "--cluster", "local:2", "-q", "-o", out))
    img, meta = read_exr(out)
    ref, _ = read_exr(local_render)
    assert meta["spp"] == 64 and meta["budget_decision"].startswith("chose " + meta["budget"])
    assert "; after " not in meta["budget_decision"]
    # What the pilot's worker priced, with the driver's unit costs (the tests' file).
    assert "camera_rays=0 " not in meta["cost_counts"] and "light_rays=" in meta["cost_counts"]
    assert "path_ray=%.3g" % units.load().path_ray in meta["unit_costs"]
    # Whole-image means: 24x24 pixels of 64 and 256 spp, a few percent apart at most.
    assert abs(img[..., :3].mean() / ref[..., :3].mean() - 1) < 0.03


def _descendants(pid: int) -> list:
    children = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(d.name))
    out, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            out.append(child)
            todo.append(child)
    return out


def _cmdline(pid: int) -> str:
    try:
        return Path("/proc/%d/cmdline" % pid).read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def _wait_for_progress(proc) -> list:
    lines = []
    for line in proc.stderr:
        lines.append(line)
        if line.startswith("bdpt: [") and "passes" in line:
            return lines
    raise AssertionError("the render ended before it showed progress:\n" + "".join(lines))


@needs_ray
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="finds workers in /proc")
def test_killed_worker_loses_only_its_pass(folder, local_render):
    """SIGKILL one worker process while it renders a pass: the pass runs again (the
    same seed) and the image is still exactly the local render, with the full spp."""
    out = folder / "killed.exr"
    with rendering(out, SPP) as (proc, lines):
        end = time.perf_counter() + 30
        busy = []
        while not busy and time.perf_counter() < end:     # a worker in the middle of a pass
            busy = [p for p in _descendants(proc.pid)
                    if _cmdline(p).startswith("ray::_Worker.render")]
        assert busy, "no worker was rendering"
        os.kill(busy[0], signal.SIGKILL)
        stdout, stderr = proc.communicate(timeout=120)
    stderr = "".join(lines) + stderr
    assert proc.returncode == 0, stderr
    assert "Traceback" not in stderr and "(raylet)" not in stdout + stderr
    lost = [line for line in stderr.splitlines() if "was lost during pass" in line]
    assert len(lost) == 1 and "pid %d" % busy[0] in lost[0], stderr
    assert "(1 pass run again)" in stdout
    meta = same_image(out, local_render)
    assert meta["spp"] == SPP


@needs_ray
def test_interrupt_keeps_a_prefix_of_passes(folder):
    """Ctrl-C: the passes in flight finish, the image is passes 0..k-1 (the local render
    of k x 2 spp, exactly), the header has the true spp, and the exit status is 130."""
    out = folder / "stopped.exr"
    with rendering(out, 100000) as (proc, lines):
        proc.send_signal(signal.SIGINT)
        _, stderr = proc.communicate(timeout=120)
    stderr = "".join(lines) + stderr
    assert proc.returncode == 130, stderr
    assert "passes in flight" in stderr and "Traceback" not in stderr
    img, meta = read_exr(out)
    done = meta["spp"]
    assert 0 < done < 100000 and meta["passes"] == done // 2
    assert "interrupted (SIGINT) after %d of 100000 spp" % done in stderr
    ref = folder / "prefix.exr"
    ok(run_cli("render", *SCENE, "--spp", done, "-q", "-o", ref))
    same_image(out, ref)


@needs_ray
def test_time_budget_on_a_film_split_in_pixel_ranges(tmp_path):
    """--time and --checkpoint on a cluster, with passes that are pixel ranges: the render
    stops at the end of a round (every pixel has its camera samples) and equals the local
    render of that many spp."""
    small = [CORNELL, "--memory-budget", "1M", "-D", "resx=64", "-D", "resy=64",
             "--max-depth", 3]
    timed = tmp_path / "timed.exr"
    p = ok(run_cli("render", *small, "--spp", 8, "--time", 0.001, "--checkpoint", 0.001,
                   "--cluster", "local:2", "-o", timed))
    assert "time budget" in p.stderr
    _, meta = read_exr(timed)
    assert 1 <= meta["spp"] < 8 and meta["passes"] % 4 == 0          # 4 ranges per round
    ref = tmp_path / "ref.exr"
    ok(run_cli("render", *small, "--spp", meta["spp"], "-q", "-o", ref))
    same_image(timed, ref)


@needs_ray
def test_scene_file_missing_on_the_workers(tmp_path):
    """A mesh outside the scene's folder is not shipped to the workers: one clear error
    naming the worker, the file and the rule; no hang, nothing written."""
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "quad.obj").write_text(
        "v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\nf 1 2 3\nf 1 3 4\n")
    scene = tmp_path / "scene" / "quad.xml"
    scene.parent.mkdir()
    scene.write_text(
        '<scene version="3.0.0"><sensor type="perspective"><transform name="to_world">'
        '<lookat origin="0,0,4" target="0,0,0" up="0,1,0"/></transform><film type="hdrfilm">'
        '<integer name="width" value="8"/><integer name="height" value="8"/></film></sensor>'
        '<shape type="obj"><string name="filename" value="../meshes/quad.obj"/></shape>'
        '<shape type="sphere"><emitter type="area"/></shape></scene>')
    ok(run_cli("render", scene, "--spp", 2, "-q", "-o", tmp_path / "here.exr"))  # the driver sees it
    start = time.perf_counter()
    p = run_cli("render", scene, "--spp", 2, "--cluster", "local:2", "-o", tmp_path / "out.exr",
                timeout=120)
    assert time.perf_counter() - start < 60
    error = clean_error(p, "could not load the scene", "quad.obj", "file not found",
                        str(scene.parent), "inside that folder")
    assert "worker" in error
    assert not (tmp_path / "out.exr").exists()


@needs_ray
def test_merge_and_cluster_are_the_same_estimator(folder, cluster_render):
    """Separate renders (seeds 1, 2) merged by 'bdpt merge', and the cluster render
    (seed 7), estimate the same image: their difference has zero mean."""
    parts = []
    for seed in (1, 2):
        part = folder / ("part%d.exr" % seed)
        ok(run_cli("render", CORNELL, "-D", "resx=24", "-D", "resy=24", "--max-depth", 4,
                   "--spp", SPP // 2, "--seed", seed, "-q", "-o", part))
        parts.append(part)
    merged = folder / "merged.exr"
    ok(run_cli("merge", *parts, "-o", merged, "-q"))
    im, meta = read_exr(merged)
    ic, cmeta = read_exr(cluster_render[0])
    assert meta["spp"] == cmeta["spp"] == SPP
    d = (im - ic).mean(axis=2).ravel()
    z = d.mean() / (d.std(ddof=1) / np.sqrt(d.size))
    assert abs(z) < 4, "merged %.5f vs cluster %.5f (z = %.2f)" % (im.mean(), ic.mean(), z)


@needs_ray
def test_python_api_on_a_cluster():
    """bdpt_drjit.render(path, cluster="local:2"): the local render's image and
    strategy images; a loaded mi.Scene is refused (there is no file to ship)."""
    import bdpt_drjit
    import mitsuba as mi
    kw = dict(spp=8, seed=3, max_depth=3, samples_per_pass=1, strategy_images=True,
              scene_params={"resx": 12, "resy": 12})
    here = bdpt_drjit.render(CORNELL, **kw)
    there = bdpt_drjit.render(CORNELL, cluster="local:2", **kw)
    np.testing.assert_allclose(there.image, here.image, rtol=1e-5, atol=1e-6)
    assert there.spp == 8 and there.passes == 8 and there.stats["workers"] == 2
    assert set(there.strategy_images) == set(here.strategy_images)
    for st, img in here.strategy_images.items():
        np.testing.assert_allclose(there.strategy_images[st], img, rtol=1e-5, atol=1e-6)
    with pytest.raises(TypeError, match="file path"):
        bdpt_drjit.render(mi.load_file(CORNELL, resx=8, resy=8), cluster="local:2", spp=1)



@needs_ray
def test_workers_plan_with_the_drivers_memory_budget(monkeypatch):
    """The default memory budget follows the machine (backend.py: 2 GiB on a CPU, a
    share of a GPU's memory): workers whose machine differs from the driver's would
    plan other passes, and the cluster refused to render.  Here the driver's default
    is 1 MiB, which splits the film into pixel ranges, and the workers' 2 GiB: they
    render the driver's plan, and the image is the local one."""
    import bdpt_drjit
    from bdpt_drjit import backend
    monkeypatch.setattr(backend, "default_memory_budget", lambda: 1 << 20)  # this process
    kw = dict(spp=2, seed=3, max_depth=3, light_paths=1, connections="all",
              scene_params={"resx": 40, "resy": 40})
    here = bdpt_drjit.render(CORNELL, **kw)
    there = bdpt_drjit.render(CORNELL, cluster="local:2", **kw)
    assert there.passes == here.passes > 2          # pixel ranges: more than 1 per spp
    np.testing.assert_allclose(there.image, here.image, rtol=1e-5, atol=1e-6)

@pytest.mark.parametrize("address", ["local:0", "local", "http://x", "nowhere"])
def test_bad_cluster_address(tmp_path, address):
    clean_error(run_cli("render", *SCENE, "--spp", 2, "--cluster", address,
                        "-o", tmp_path / "out.exr"), "--cluster", "local:N", "ray://")
    assert not (tmp_path / "out.exr").exists()


@needs_ray
def test_no_cluster_at_the_address(tmp_path):
    """Nothing listens there (port 1 of this machine): one error at once, not Ray's
    minutes of retries."""
    start = time.perf_counter()
    clean_error(run_cli("render", *SCENE, "--spp", 2, "--cluster", "127.0.0.1:1",
                        "-o", tmp_path / "out.exr"), "nothing answers at 127.0.0.1:1",
                "ray start --head")
    assert time.perf_counter() - start < 30
    assert not (tmp_path / "out.exr").exists()


def test_without_ray(tmp_path):
    """Without Ray bdpt renders as ever, and --cluster says how to install it."""
    fake = tmp_path / "no-ray" / "ray"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("raise ImportError(\"No module named 'ray'\")\n")
    env = {"PYTHONPATH": os.pathsep.join([str(fake.parent), cli_env()["PYTHONPATH"]])}
    ok(run_cli("render", *SCENE, "--spp", 2, "-q", "-o", tmp_path / "plain.exr", env=env))
    clean_error(run_cli("render", *SCENE, "--spp", 2, "--cluster", "local:2",
                        "-o", tmp_path / "out.exr", env=env),
                "needs Ray", "pip install 'bdpt-drjit[cluster]'")
    assert not (tmp_path / "out.exr").exists()


# -- the driver's rules, without Ray processes -----------------------------------------------
class _FakeRenderer:
    """A plan of pixel ranges: 2 ranges of 50 pixels per round, 3 rounds (3 spp)."""
    plan = [(0, 50, 1), (50, 50, 1)] * 3
    pixels, spp = 100, 3
    pilot, budget, _pilot_round, _pilot_kept = None, None, 0, True

    def is_round_end(self, passes, spp_done):
        from bdpt_drjit.render import Renderer
        return Renderer.is_round_end(self, passes, spp_done)

    def pass_spp(self, index):
        from bdpt_drjit.render import Renderer
        return Renderer.pass_spp(self, index)


def _run(**slots):
    from types import SimpleNamespace

    from bdpt_drjit.cluster import ClusterRun
    return ClusterRun(SimpleNamespace(slots=[], **slots), _FakeRenderer())


def test_wind_down_finishes_the_round_of_the_passes_sent():
    run = _run()
    assert run.at_round_end and not run.done and run.spp_done == 0
    run.in_flight = {"ref": (None, 2, 0.0)}           # pass 2 opens round 2
    assert run.wind_down() and run.limit == 4          # ... which must be finished
    run.in_flight = {}
    run.finished = {i: {"raw": {"camera_samples": 1}, "time": 0.1, "rays": 1} for i in range(5)}
    run._merge()                                       # pass 4 is past the limit: dropped
    assert run.done and run.passes_done == 4 and run.spp_done == 2 and run.at_round_end
    idle = _run()
    assert not idle.wind_down() and idle.done and idle.passes_done == 0


@needs_ray
def test_workers_must_run_the_drivers_code():
    from types import SimpleNamespace

    from bdpt_drjit.cluster import Cluster, ClusterError, _Slot, _versions, code_fingerprint
    cluster = Cluster.__new__(Cluster)
    cluster.scene_path = Path(CORNELL)
    mine = {"code": code_fingerprint(), "versions": _versions()}
    slot = _Slot(1, None, host="node7", pid=42)
    r = SimpleNamespace(plan=[(0, 16, 2)] * 4)
    good = dict(mine, error=None, plan=list(r.plan), package="/x")
    cluster._check_worker(slot, good, mine, r)
    for bad, words in ((dict(good, code="0" * 16), "other code"),
                       (dict(good, versions=dict(mine["versions"], mitsuba="3.0.0")), "3.0.0"),
                       (dict(good, plan=r.plan[:3]), "other passes"),
                       (dict(good, error="file not found"), "could not load the scene")):
        with pytest.raises(ClusterError, match=words):
            cluster._check_worker(slot, bad, mine, r)
