"""What bdpt supports (bdpt_drjit/support.py): ``bdpt info`` and ``bdpt render`` run the
same checks, so info's verdict and the render agree on every scene we have."""
import contextlib
import io

import mitsuba as mi
import numpy as np
import pytest

import bdpt_drjit
from bdpt_drjit import support
from bdpt_drjit.cli import main
from conftest import EXTERNAL, SCENES

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


def test_every_verdict_names_its_element():
    scene = mi.load_file(str(PLUGINS / "projector-wall.xml"))
    verdicts = support.inspect(scene, scene.sensors()[0])
    names = {v.name for v in verdicts}
    assert "projector 'projector'" in names and "perspective" in names
    assert {"rectangle 'wall' with diffuse", "cube 'box' with diffuse"} <= names
    assert all(v.status == support.SUPPORTED for v in verdicts)
    assert np.isfinite(bdpt_drjit.render(scene, spp=1, max_depth=2).image).all()
