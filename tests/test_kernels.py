"""Kernels are reused: a render with a new seed compiles nothing that an earlier
render compiled; a new spp or film size recompiles no walk (the small kernels of
Mitsuba's ``ImageBlock.put`` and ``sample_ray`` bake the film size, as in Mitsuba's
own ``path``).  Counted with Dr.Jit's kernel history, not timed."""
import drjit as dr
import mitsuba as mi
import pytest

import bdpt_drjit
from conftest import scene_path

# The largest kernel that may be compiled for a new film size or spp: the camera
# rays (~310 operations) and the film's puts (~30); the walks have 700-2100.
SMALL = 400


def launches(render):
    dr.kernel_history()
    render()
    return [e for e in dr.kernel_history() if e["type"] == dr.KernelType.JIT]


def compiled(entries):
    """Kernels not found in memory (compiled now, or loaded from the disk cache)."""
    return [e for e in entries if not e.get("cache_hit", 1) or e.get("cache_disk", 0)]


@pytest.fixture(autouse=True)
def history():
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        yield


@pytest.mark.parametrize("max_depth", [8, -1])
def test_new_seed_compiles_nothing(max_depth):
    scene = mi.load_file(scene_path("cornell-box.xml"), resx=24, resy=24)
    launches(lambda: bdpt_drjit.render(scene, spp=4, seed=1, max_depth=max_depth))
    for seed in (2, 3, 12345):
        again = launches(lambda: bdpt_drjit.render(scene, spp=4, seed=seed, max_depth=max_depth))
        assert again and not compiled(again), "seed %d compiled %d kernels" % (seed, len(compiled(again)))


def test_new_spp_and_film_size_recompile_no_walk():
    small = mi.load_file(scene_path("cornell-box.xml"), resx=24, resy=24)
    other = mi.load_file(scene_path("cornell-box.xml"), resx=40, resy=30)
    launches(lambda: bdpt_drjit.render(small, spp=4, seed=1, max_depth=-1))
    for render in (lambda: bdpt_drjit.render(small, spp=7, seed=2, max_depth=-1),
                   lambda: bdpt_drjit.render(other, spp=4, seed=3, max_depth=-1)):
        big = [e for e in compiled(launches(render)) if e.get("operation_count", 0) > SMALL]
        assert not big, ["%d ops" % e["operation_count"] for e in big]


@pytest.mark.auto_budget
def test_re_decisions_with_a_new_seed_compile_nothing():
    """An auto render that re-decides (the light image alone at first hits, so the
    moment pass's splats decide) with a new seed compiles nothing.  The splats it
    records differ in number with every seed, and their luminance was ``dr.mean``,
    which bakes the array's width into the kernel: 2 small kernels per render."""
    scene = mi.load_file(scene_path("cornell-box.xml"), resx=64, resy=64)

    def render(seed):
        return bdpt_drjit.render(scene, spp=64, seed=seed, max_depth=5,
                                 first_hits="light_image", samples_per_pass=4)
    launches(lambda: render(1))
    for seed in (2, 3):
        again = launches(lambda: render(seed))
        assert again and not compiled(again), "seed %d compiled %d kernels" % (seed, len(compiled(again)))
    assert "after 16 spp" in render(4).stats["decision"]


def test_luminance_compiles_one_kernel_for_every_width():
    from bdpt_drjit.optimizer import luminance
    for width in (5, 7):
        out = launches(lambda: dr.eval(luminance(mi.Spectrum(dr.arange(mi.Float, width)))))
        if width == 7:
            assert out and not compiled(out)


@pytest.mark.auto_budget
def test_a_pass_reads_the_host_a_few_times():
    """Copies (reads to the host, each a sync on a GPU) stay few in every pass of an
    auto render.  The pilot's moment sums gathered each candidate's rates at a
    literal index, which Dr.Jit reads to the host: 124 copies in its BDPT pass."""
    scene = mi.load_file(scene_path("cornell-box.xml"), resx=32, resy=32)
    from bdpt_drjit.render import Renderer
    renderer = Renderer(scene, spp=32, seed=1, max_depth=5)
    copies = []
    while not renderer.done:
        dr.kernel_history()
        renderer.run_pass()
        copies.append(sum(e["type"] == dr.KernelType.Memcpy for e in dr.kernel_history()))
    assert renderer.pilot is not None and len(copies) >= 2
    assert max(copies) <= 6, copies


def test_numpy_values_are_read_by_the_same_kernels_whatever_their_alignment():
    """Dr.Jit reads a NumPy array in place and compiles its readers for the address's
    alignment; backend.device_array copies values to an aligned buffer first, so that
    a kernel reading them is the same whatever NumPy's allocation."""
    import numpy as np
    from bdpt_drjit.backend import device_array
    hashes = set()
    for offset in range(4):                      # 0, 4, 8, 12 bytes past 64
        raw = np.zeros(1024 + 64, dtype=np.uint32)
        start = -(raw.ctypes.data // 4) % 16 + offset
        values = raw[start:start + 1024]
        values[:] = np.arange(1024)
        x = device_array(mi.UInt32, values)
        entries = launches(lambda: dr.eval(x * 3 + 1))
        hashes |= {e["hash"] for e in entries if e["size"] == 1024}  # not earlier tests'
    assert len(hashes) == 1


@pytest.mark.auto_budget
def test_a_path_traced_render_with_a_new_seed_compiles_nothing():
    """Where the pilot chooses path tracing, its passes (Mitsuba's path, recorded whole
    with the seed opaque: render._recorded_path_pass) compile nothing for a new seed."""
    scene = mi.load_file(scene_path("glass-pane.xml"), resx=24, resy=24)
    for seed in (1, 2):
        out = bdpt_drjit.render(scene, spp=32, seed=seed, max_depth=8)
    assert out.stats["path_tracer_spp"] > 0, "the premise: path tracing is chosen"
    again = launches(lambda: bdpt_drjit.render(scene, spp=32, seed=3, max_depth=8))
    assert again and not compiled(again), len(compiled(again))


def test_the_set_up_of_a_render_reads_little_back():
    """A render's set-up reads almost nothing back from the device (each read a sync):
    the scene's transforms went through repr, one read per matrix entry (289 copies in
    the glass pane's set-up), and every mesh's normals were checked again by a kernel
    and a read per render (support.facts keeps them while the scene is the same)."""
    from bdpt_drjit.render import Renderer
    scene = mi.load_file(scene_path("glass-pane.xml"), resx=16, resy=16)
    Renderer(scene, spp=32, seed=1, max_depth=8)
    dr.kernel_history()
    Renderer(scene, spp=32, seed=2, max_depth=8)
    copies = [e for e in dr.kernel_history() if e["type"] == dr.KernelType.Memcpy]
    assert len(copies) <= 2, len(copies)
