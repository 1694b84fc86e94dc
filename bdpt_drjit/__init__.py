"""bdpt-drjit: a wavefront bidirectional path tracer on Dr.Jit, with Mitsuba 3 as its
scene system.

    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")          # optional: $BDPT_VARIANT or llvm_ad_rgb if unset
    import bdpt_drjit                      # registers the integrator "bdpt"
    res = bdpt_drjit.render("scene.xml", spp=64, max_depth=8, seed=1)
    res.image                              # (H, W, C) NumPy array

Layout: mis.py (all MIS weights), walk.py (subpath walks), connect.py (the
strategies), film.py (camera block and light-image splats), render.py (passes),
api.py (``render``: here or on a cluster), emitters.py / camera.py (the emitter and
sensor models), integrators/bdpt.py (the Mitsuba plugin).
"""
import os

from ._signals import held_during_import
from ._version import __version__

# The variant chosen when none is set: BDPT_VARIANT=cuda_ad_rgb runs the tests, the
# benchmarks and the CLI's default on a GPU.
DEFAULT_VARIANT = os.environ.get("BDPT_VARIANT") or "llvm_ad_rgb"


def register() -> None:
    """Register the ``bdpt``, ``pssmlt`` and ``mlt`` integrators with Mitsuba for the current
    variant (done on import and, through Mitsuba's variant callback, after every
    ``mi.set_variant``)."""
    if mi.variant() is None:
        return
    from integrators.bdpt import register as _register
    from integrators.mlt import register as _register_mmlt
    from integrators.pssmlt import register as _register_mlt
    _register()
    _register_mlt()
    _register_mmlt()


def _on_variant_change(old, new) -> None:
    register()


# Ctrl-C while Mitsuba's extension modules load would break them: hold it until done.
with held_during_import():
    from ._llvm import prepare as _prepare_llvm

    _prepare_llvm()

    import mitsuba as mi

    if mi.variant() is None:
        try:
            mi.set_variant(DEFAULT_VARIANT)
        except ImportError:      # no usable LLVM: render() reports it with install advice
            pass

    from .support import UnsupportedPluginError
    from .exr import read_exr, write_exr
    from .render import Renderer, RenderResult
    from .api import render            # after .render: bdpt_drjit.render is the function
    from .settings import HEURISTICS, PARAMS, Settings

    register()
    mi.detail.add_variant_callback(_on_variant_change)

__all__ = ["render", "Renderer", "RenderResult", "Settings", "register",
           "UnsupportedPluginError", "HEURISTICS", "PARAMS", "read_exr", "write_exr"]
