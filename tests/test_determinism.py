"""The same seed gives the same image: across processes, with a cold or a warm kernel
cache, with the integrator made by a scene file or by ``mi.load_dict``.  The default
budget is chosen from the pilot's counts priced by the unit costs of a fixed
calibration file (units.py; the tests' own, conftest), never from a clock."""
import subprocess
import sys

import numpy as np
import pytest

import mitsuba as mi
from conftest import cli_env, scene_path

_RENDER = r"""
import sys, numpy as np, mitsuba as mi, bdpt_drjit
how, scene_file, out = sys.argv[1:4]
if how == "xml":      # the scene's own <integrator type="bdpt">
    scene = mi.load_file(scene_file, resx=48, resy=48, integrator="bdpt")
    image = mi.render(scene, spp=32, seed=3)
else:
    scene = mi.load_file(scene_file, resx=48, resy=48)
    image = mi.render(scene, integrator=mi.load_dict({"type": "bdpt", "max_depth": 8}),
                      spp=32, seed=3)
np.save(out, np.array(image))
"""


def _render(tmp_path, how, scene, home=None):
    out = tmp_path / ("%s-%s.npy" % (how, "cold" if home else "warm"))
    env = {"HOME": str(home)} if home else None    # Dr.Jit's kernel cache is $HOME/.drjit
    subprocess.run([sys.executable, "-c", _RENDER, how, scene_path(scene), str(out)],
                   env=cli_env(env), check=True, capture_output=True, timeout=300)
    return np.load(out)


@pytest.mark.parametrize("scene", ["glass-pane.xml", "cornell-box.xml"])
def test_the_same_seed_gives_the_same_image(tmp_path, scene):
    """The same image up to the rounding of the film's float atomics (a pass adds its
    samples' filter footprints and splats onto the film's sums in thread order: about
    1e-7 relative); another budget would differ by its noise, 1e-2 and more.  Before,
    the budget followed the pilot's kernel timings: a cold kernel cache (compilation),
    the machine's load and the integrator's construction chose light_paths 0.25 or 0.5
    in the Cornell box for one seed."""
    home = tmp_path / "home"
    home.mkdir()
    cold_xml = _render(tmp_path, "xml", scene, home)
    warm_dict = _render(tmp_path, "dict", scene)
    assert cold_xml.mean() > 0
    np.testing.assert_allclose(cold_xml, warm_dict, rtol=1e-5, atol=1e-6)


def test_scene_files_load_without_mitsubas_merging(monkeypatch, tmp_path):
    """The API, the command line and a cluster's workers load a scene file without
    Mitsuba 3.9's merging of shapes that share a BSDF: the merge orders the scene's
    shapes, and with them ``scene.emitters()``, differently from process to process,
    and an emitter is drawn by its place in that list (Veach's bidirectional room: 4 of
    16 processes rendered another image for one seed, Mitsuba's ``path`` too).  Two
    cubes sharing a BSDF stay two shapes."""
    import mitsuba as mi
    import bdpt_drjit
    from bdpt_drjit import support
    scene_file = tmp_path / "cubes.xml"
    scene_file.write_text(
        '<scene version="3.0.0"><bsdf type="diffuse" id="white"/>'
        '<shape type="cube"><transform name="to_world"><translate x="-2"/></transform>'
        '<ref id="white"/></shape>'
        '<shape type="cube"><transform name="to_world"><translate x="2"/></transform>'
        '<ref id="white"/></shape>'
        '<shape type="rectangle"><transform name="to_world"><translate y="4"/></transform>'
        '<emitter type="area"/></shape><sensor type="perspective"><film type="hdrfilm">'
        '<integer name="width" value="8"/><integer name="height" value="8"/></film>'
        '</sensor></scene>')
    assert len(mi.load_file(str(scene_file)).shapes()) == 2       # Mitsuba's default merges
    assert len(support.load_file(scene_file).shapes()) == 3
    loaded = []
    load = mi.load_file
    monkeypatch.setattr(mi, "load_file", lambda *a, **k: loaded.append(k) or load(*a, **k))
    bdpt_drjit.render(str(scene_file), spp=1, seed=1, max_depth=2)
    from bdpt_drjit.cli.scene import load_scene
    load_scene(mi, scene_file, {})
    assert [k.get("optimize") for k in loaded] == [False, False]


@pytest.mark.auto_budget
@pytest.mark.parametrize("scene", ["glass-pane.xml", "point-caustic.xml"])
def test_a_small_render_reuses_the_pilot_of_an_earlier_one(scene):
    """A small render's pilot, whose samples are dropped (optimizer.Pilot.stride),
    draws the same numbers in every render; a render of the same scene state,
    settings, film and spp takes its outcome from the last such render and skips the
    pass (render._ReusedPilot): the image is the one rendering it gives (up to the
    film's float atomics), as in a fresh process.  Not once the scene changed."""
    renderer = sys.modules["bdpt_drjit.render"].Renderer
    loaded = mi.load_file(scene_path(scene), resx=64, resy=64)

    def render(seed, **kwargs):
        r = renderer(loaded, spp=32, seed=seed, max_depth=8, **kwargs)
        reused = r._pilot_reused
        while not r.done:
            r.run_pass()
        return r, reused

    cold, reused = render(3, reuse_pilot=False)
    assert not reused and not cold._pilot_kept                   # a dropped pilot
    render(5)
    render(5)                   # (the first render settles the scene's literals)
    warm, reused = render(3)
    assert reused and "earlier render" in warm.decision_text()
    assert warm.budget == cold.budget and warm.plan == cold.plan
    np.testing.assert_allclose(warm.tensor().numpy(), cold.tensor().numpy(), rtol=1e-5,
                               atol=1e-6)
    params = mi.traverse(loaded)
    key = next(k for k in params.keys() if k.endswith(("reflectance.value", "radiance.value",
                                                       "intensity.value")))
    params[key] = params[key] * 0.5
    params.update()
    assert not render(3)[1]
