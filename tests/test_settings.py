"""Parameters are declared once (bdpt_drjit.settings.PARAMS): the plugin, its
reference table, the command line and the README all follow that declaration."""
import re
import warnings
from pathlib import Path

import mitsuba as mi
import pytest

import bdpt_drjit  # noqa: F401  (registers "bdpt")
from bdpt_drjit.settings import LEGACY_REFUSED, PARAMS, Settings

README = Path(__file__).resolve().parent.parent / "README.md"


def test_readme_table_lists_every_parameter_with_its_default():
    rows = re.findall(r"^\| `(\w+)` \| ([^|]+) \|", README.read_text(), re.M)
    assert [(n, d.strip()) for n, d in rows] == [(p.name, p.default_text) for p in PARAMS]


def test_plugin_documents_and_accepts_every_parameter():
    from integrators.bdpt import BDPTIntegrator
    for p in PARAMS:
        assert "   * - %s\n" % p.name in BDPTIntegrator.__doc__
        value = {"technique": "1,2", "mis": "balance", "strategy_subset": "pt"}.get(p.name, p.default)
        if p.name == "technique":
            props = {"max_depth": 4, "technique": value}
        else:
            props = {p.name: value}
        mi.load_dict({"type": "bdpt", **props})


def test_renamed_and_legacy_names():
    with pytest.warns(DeprecationWarning, match="strategy_subset"):
        assert Settings.from_dict({"strategies": "pt"}).strategy_subset == "pt"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert Settings.from_dict({"lightImage": False, "maxDepth": 3}).max_depth == 3
    integ = mi.load_dict({"type": "bdpt", "lightImage": False})
    assert integ.settings == {"light_image": False}
    for key in LEGACY_REFUSED:
        with pytest.raises(ValueError, match=key):
            Settings.from_dict({key: True})


@pytest.mark.parametrize("settings, words", [
    (dict(max_depth=8, technique=(9, 9)), ["technique 9,9", "max_depth 8"]),
    (dict(strategy_subset="pt", technique=(2, 1)), ["light-tracing", "strategy_subset 'pt'"]),
    (dict(mis="lafortune", technique=(2, 1)), ["lafortune"]),
    (dict(rr_depth=0), ["rr_depth", ">= 1"]),
    (dict(light_image="maybe"), ["light_image", "true or false"]),
])
def test_bad_values_name_the_parameter(settings, words):
    with pytest.raises(ValueError) as e:
        Settings(**settings)
    for w in words:
        assert w in str(e.value)
    if settings.get("strategy_subset") == "pt":        # the user never set light_image
        assert "light_image" not in str(e.value)
