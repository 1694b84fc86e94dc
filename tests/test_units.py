"""The unit costs' file (units.py): where it lives, what it holds, when it is measured
again."""
import json

import mitsuba as mi

from bdpt_drjit import units
from bdpt_drjit.units import UnitCosts


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
