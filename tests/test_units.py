"""The unit costs' file (units.py): where it lives, what it holds, when it is measured
again."""
import json
import sys

import drjit as dr
import mitsuba as mi
import pytest

from bdpt_drjit import units
from bdpt_drjit.render import Renderer
from bdpt_drjit.units import UnitCosts
from conftest import scene_path


def test_the_cache_holds_each_variants_units(tmp_path, monkeypatch):
    monkeypatch.delenv("BDPT_CALIBRATION", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert units.load() is None                      # nothing measured yet
    mine = UnitCosts(1e-7, 2e-7, 3e-8, 4e-7, 5e-8)
    where = units.save(mine)
    assert where.parent == tmp_path / "bdpt-drjit" and mi.variant() in where.name
    assert units.load() == mine
    data = json.loads(where.read_text())
    assert data["machine"] == units.machine(mi.variant())


def test_a_pinned_file_holds_variants_side_by_side(tmp_path, monkeypatch):
    pinned = tmp_path / "units.json"
    monkeypatch.setenv("BDPT_CALIBRATION", str(pinned))
    assert units.path() == pinned and units.load() is None
    units.save(UnitCosts(path_ray=0.5), "llvm_ad_mono")
    units.save(UnitCosts(path_ray=0.25), "llvm_ad_rgb")
    assert units.load("llvm_ad_mono").path_ray == 0.5
    assert units.load("llvm_ad_rgb").path_ray == 0.25


def test_a_file_of_another_format_is_measured_again(tmp_path, monkeypatch):
    pinned = tmp_path / "units.json"
    monkeypatch.setenv("BDPT_CALIBRATION", str(pinned))
    units.save(UnitCosts())
    data = json.loads(pinned.read_text())
    pinned.write_text(json.dumps(dict(data, format=units.FORMAT - 1)))
    assert units.load() is None
    pinned.write_text("not json")
    assert units.load() is None


def test_a_timed_pass_prices_its_camera_rays_and_film_puts():
    """The calibration's timed pass (render._timed_pass) splits its kernels into the
    light side and the camera side; path_ray prices Mitsuba's path whole (camera rays,
    walk, film), so the camera side must hold the camera rays' making and the film's
    put, the light side its splats' put.  They were left out (the film's scatters ran
    after the pass's laps), and the glass pane's light_paths=0.25 connections=0 was
    priced at 1.18x path's kernel time where it took 1.64x.  Only the counts' reads
    (kernels of one lane) stay unpriced."""
    scene = mi.load_file(scene_path("cornell-box.xml"), resx=32, resy=16)
    r = Renderer(scene, spp=4, seed=1, max_depth=5, light_paths=1, connections=0,
                 samples_per_pass=2)
    r.timings = {}
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history()
        r.render_pass(0)
        dr.eval(*[block.tensor() for block in r.film.blocks()])
        unpriced = [e for e in dr.kernel_history() if e["type"] == dr.KernelType.JIT]
    priced = [e for e in r.kernel_history if e["type"] == dr.KernelType.JIT]
    assert len(priced) >= 4 and all(t > 0 for t in r.timings[0][:2])
    assert [e["size"] for e in unpriced if e["size"] > 1] == []


def test_a_calibration_on_a_busy_cpu_says_so(tmp_path, monkeypatch):
    """Units measured while other jobs kept the cores busy misprice every later
    decision: the calibration measures its share of the CPU time its threads could use
    and, where it is short (units.BUSY_SHARE), warns and says how to measure again; on
    an idle CPU, or a GPU, nothing."""
    render = sys.modules["bdpt_drjit.render"]
    assert units.busy_warning("llvm_ad_rgb", 0.98) is None
    assert units.busy_warning("cuda_ad_rgb", 0.6) is None
    assert "bdpt calibrate" in units.busy_warning("llvm_ad_rgb", 0.6)
    if not mi.variant().startswith("llvm"):
        return
    monkeypatch.setenv("BDPT_CALIBRATION", str(tmp_path / "units.json"))
    monkeypatch.setattr(render, "_calibration_run", lambda *a: tuple(range(1, 8)))
    shares = []
    monkeypatch.setattr(units, "busy_warning", lambda v, share: shares.append(share) or "busy")
    with pytest.warns(UserWarning, match="busy"):
        measured = render.calibrate(repeats=1)
    assert len(shares) == 1 and 0 <= shares[0] < 2
    assert units.load() == measured == UnitCosts(*range(1, 8))      # stored all the same
