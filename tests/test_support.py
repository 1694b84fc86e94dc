"""What bdpt supports (bdpt_drjit/support.py): ``bdpt info`` and ``bdpt render`` run the
same checks, so info's verdict and the render agree on every scene we have; content
bdpt would ignore is refused naming it; pass-through BSDFs and
meshes whose normals oppose their winding render with a warning."""
import contextlib
import io
import os
import subprocess
import sys
import warnings

import mitsuba as mi
import numpy as np
import pytest

import bdpt_drjit
from bdpt_drjit import support
from bdpt_drjit.cli import main
from conftest import EXTERNAL, SCENES, cli_env

PLUGINS = SCENES / "plugins"


def _scene_files():
    own = sorted(SCENES.rglob("*.xml"))
    # Fragments are included by other scenes, not scenes themselves.
    external = sorted(p for p in EXTERNAL.rglob("*.xml") if "fragments" not in p.parts)
    return own + external if EXTERNAL.exists() else own + [None]


def _cli(*argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in argv])
    return code, out.getvalue(), err.getvalue()


@pytest.mark.parametrize("path", _scene_files(),
                         ids=lambda p: "external-missing" if p is None else "/".join(p.parts[-2:]))
def test_info_and_render_agree(path, tmp_path):
    """info says "supported" exactly when the render (8x8, 1 spp, max_depth 3)
    succeeds; a refusal is the same one line in both."""
    if path is None:
        pytest.skip("external scenes not found at %s: set BDPT_SHARED to the project's "
                    "../shared folder" % EXTERNAL)
    res = ["--res", "8x8"]
    code, out, err = _cli("info", path, *res)
    if code != 0 and "has no parameter $resx" in err:    # a scene without $resx: as it is
        res = []
        code, out, err = _cli("info", path)
    assert code == 0, err
    status = [line for line in out.splitlines() if line.startswith("status:")][0]
    rcode, _, rerr = _cli("render", path, *res, "--spp", 1, "--max-depth", 3, "--quiet",
                          "-o", tmp_path / "out.exr")
    if "status:     supported" in status:
        assert rcode == 0, "info: %s\nrender: %s" % (status, rerr)
    else:
        assert rcode != 0, "info refused (%s) but render succeeded" % status
        error = [line for line in rerr.splitlines() if line.startswith("bdpt: error:")][-1]
        assert error.split("bdpt: error: ")[1] in status


# -- media (issue "Mitsuba citizen", item 3) ------------------------------------------
def _box_with(medium_at: str) -> mi.Scene:
    fog = {"type": "homogeneous", "id": "fog", "sigma_t": 2.0}
    T = mi.ScalarTransform4f
    sensor = {"type": "perspective", "to_world": T().look_at(origin=[0, 1, 3], target=[0, 0, 0], up=[0, 1, 0]),
              "film": {"type": "hdrfilm", "width": 8, "height": 8}}
    box = {"type": "cube", "bsdf": {"type": "null"}}
    light = {"type": "point", "position": [0, 2, 0]}
    if medium_at == "sensor":
        sensor["medium"] = fog
    elif medium_at == "emitter":
        light["medium"] = fog
    else:
        box[medium_at] = fog
    return mi.load_dict({"type": "scene", "sensor": sensor, "box": box, "light": light,
                         "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(3)}})


@pytest.mark.parametrize("where", ["interior", "sensor", "emitter"])
def test_media_render_where_they_are_declared(where):
    """Media were ignored (a fog cube in the Cornell box 25% off volpath), then
    refused; now they render (agreement with volpath: test_media.py)."""
    img = bdpt_drjit.render(_box_with(where), spp=2).image
    assert np.isfinite(img).all() and img.mean() > 0


def test_camera_in_an_undeclared_medium_is_refused():
    """The box's exterior fog surrounds the camera, whose sensor declares no medium."""
    with pytest.raises(bdpt_drjit.UnsupportedPluginError, match="rays start inside 'fog'"):
        bdpt_drjit.render(_box_with("exterior"), spp=1)


def test_cli_renders_a_fog_cube(tmp_path):
    """``bdpt render`` of a fog cube exited 0 with the fog ignored, and ``bdpt info``
    called it supported; now both mean it."""
    scene = SCENES / "media" / "fog-cube.xml"
    env = cli_env()
    p = subprocess.run([sys.executable, "-m", "bdpt_drjit", "render", str(scene), "--res", "8x8",
                        "--spp", "1", "-o", str(tmp_path / "fog.exr")],
                       capture_output=True, text=True, timeout=300, env=env)
    assert p.returncode == 0 and (tmp_path / "fog.exr").exists(), p.stderr
    info = subprocess.run([sys.executable, "-m", "bdpt_drjit", "info", str(scene)],
                          capture_output=True, text=True, timeout=300, env=env)
    assert "REFUSED" not in info.stdout and "homogeneous" in info.stdout, info.stdout


# -- warnings -------------------------------------------------------------------------
def test_reversed_vertex_normals_warn():
    """A floor whose vertex normals oppose its winding: bdpt (like ptracer) gives it
    zero weight, path does not (measured, 16x16: path 0.045, ptracer 0.0025, bdpt
    0.0025).  Render and info warn; meshes with consistent normals do not."""
    scene = mi.load_file(str(PLUGINS / "reversed-normals.xml"), resx=8, resy=8)
    floor = [s for s in scene.shapes() if s.id() == "floor"][0]
    assert support.reversed_normals(floor) == 1.0
    with pytest.warns(UserWarning, match="vertex normals oppose its triangle winding on 100%"):
        bdpt_drjit.render(scene, spp=1, max_depth=2)
    lowpoly = mi.load_file(str(SCENES / "stress" / "smooth-lowpoly.xml"))
    assert all(support.reversed_normals(s) == 0.0 for s in lowpoly.shapes() if s.is_mesh())


def test_a_scene_edited_between_renders_is_inspected_anew():
    """A render inspects a scene once while its state is the same (support.facts):
    with the floor's vertex normals flipped through mi.traverse between renders, the
    next render no longer warns of them."""
    scene = mi.load_file(str(PLUGINS / "reversed-normals.xml"), resx=8, resy=8)
    sensor = scene.sensors()[0]
    assert support.facts(scene, sensor) is support.facts(scene, sensor)
    with pytest.warns(UserWarning, match="oppose its triangle winding"):
        bdpt_drjit.render(scene, spp=1, max_depth=2)
    params = mi.traverse(scene)
    name = [k for k in params.keys() if k.startswith("floor.") and k.endswith("vertex_normals")]
    params[name[0]] = -params[name[0]]
    params.update()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        bdpt_drjit.render(scene, spp=1, max_depth=2)
    assert not [w for w in caught if "triangle winding" in str(w.message)]


def test_reversed_normals_weigh_triangles_by_area():
    """Two triangles of areas 1/2 and 2, vertex normals reversed on the larger: 80% of
    the area (the fraction is computed in one kernel where the mesh lives)."""
    import numpy as np
    mesh = mi.Mesh("two", 6, 2, has_vertex_normals=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.array(
        [0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1, 2, 0, 1, 0, 2, 1], dtype=np.float32))
    params["faces"] = mi.UInt32(np.array([0, 1, 2, 3, 4, 5], dtype=np.uint32))
    params["vertex_normals"] = mi.Float(np.array([0, 0, 1] * 3 + [0, 0, -1] * 3, dtype=np.float32))
    params.update()
    assert support.reversed_normals(mesh) == pytest.approx(0.8)


def test_null_lobes_warn_and_are_listed_by_info():
    code, out, _ = _cli("info", PLUGINS / "null-pane.xml")
    assert code == 0 and "status:     supported" in out and "1 warning above" in out
    assert "rectangle 'pane' with null" in out and "counts as a bounce" in out


def test_every_verdict_names_its_element():
    scene = mi.load_file(str(PLUGINS / "projector-wall.xml"))
    verdicts = support.inspect(scene, scene.sensors()[0])
    names = {v.name for v in verdicts}
    assert "projector 'projector'" in names and "perspective" in names
    assert {"rectangle 'wall' with diffuse", "cube 'box' with diffuse"} <= names
    assert all(v.status == support.SUPPORTED for v in verdicts)
    assert np.isfinite(bdpt_drjit.render(scene, spp=1, max_depth=2).image).all()


def test_specfilm_is_refused_naming_the_film(tmp_path):
    """A specfilm (spectral variants) made the render fail inside the film stage with
    Mitsuba's 'ImageBlock::put(): non-standard image block configuration!'."""
    scene = tmp_path / "specfilm.xml"
    scene.write_text(
        '<scene version="3.0.0"><sensor type="perspective"><film type="specfilm">'
        '<integer name="width" value="8"/><integer name="height" value="8"/>'
        '<spectrum name="band1" value="400:1, 700:1"/></film></sensor>'
        '<shape type="rectangle"/><emitter type="point"><point name="position" x="0" '
        'y="0" z="2"/></emitter></scene>')
    env = cli_env()
    p = subprocess.run([sys.executable, "-m", "bdpt_drjit", "render", str(scene), "--variant",
                        "llvm_ad_spectral", "--spp", "1", "-o", str(tmp_path / "s.exr")],
                       capture_output=True, text=True, timeout=300, env=env)
    errors = [line for line in p.stderr.splitlines() if line.startswith("bdpt: error:")]
    assert p.returncode != 0 and len(errors) == 1 and "'specfilm'" in errors[0], p.stderr
