"""MIS partition of unity: for random paths, the weights that mis.py's recursion
gives every strategy able to sample the path sum to one, and equal the weights
computed by brute force from products of per-vertex area pdfs (Veach eq. 10.9).

A path x_0 .. x_k has x_0 on an emitter and x_k = z_0 on the camera (a pinhole, or
a point on a thin lens: ``test_thin_lens_weights_match_brute_force``).  Every per-vertex
quantity (directional pdfs both ways, cosines, distances) is drawn at random, and
vertices are made delta (specular) or the emitter a point light at random, so the
test exercises every branch of the chains, including delta vertices.  With
``media``, every edge also has random distance densities in each direction (media.py:
what a walk through media multiplies into a vertex's density), and vertices with
cosine 1 stand for medium vertices.
"""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import bdpt_drjit  # noqa: F401  (sets the variant)
from bdpt_drjit import mis

N = 4000  # random paths per path length


def random_path(rng, k, delta_prob=0.3, point_light_prob=0.3):
    """Arrays (one row per path) describing random paths of k edges."""
    P = {}
    P["dist2"] = rng.uniform(0.05, 4.0, (N, k))            # edge (x_i, x_{i+1})
    P["cos_fwd"] = rng.uniform(0.05, 1.0, (N, k))          # at x_i toward x_{i+1}
    P["cos_bwd"] = rng.uniform(0.05, 1.0, (N, k))          # at x_{i+1} toward x_i
    P["pdf_l"] = rng.uniform(0.05, 3.0, (N, k + 1))        # at x_i: sample x_{i+1} (from x_{i-1})
    P["pdf_e"] = rng.uniform(0.05, 3.0, (N, k + 1))        # at x_i: sample x_{i-1} (from x_{i+1})
    P["delta"] = rng.uniform(size=(N, k + 1)) < delta_prob  # interior vertices only
    P["delta"][:, 0] = False
    P["delta"][:, k] = False
    P["point_light"] = rng.uniform(size=N) < point_light_prob
    P["e_pos"] = rng.uniform(0.1, 2.0, N)                  # pmf / area
    P["nee_a"] = rng.uniform(0.1, 2.0, N)                  # P_nee(x_0 | x_1), area
    P["cam_w"] = rng.uniform(0.5, 3.0, N)                  # camera solid-angle pdf toward x_{k-1}
    # A delta lobe's pdf counts as 1 in both directions (mis.py's convention).
    P["pdf_l"] = np.where(P["delta"], 1.0, P["pdf_l"])
    P["pdf_e"] = np.where(P["delta"], 1.0, P["pdf_e"])
    P["e_pos"] = np.where(P["point_light"], 1.0, P["e_pos"])     # pmf=1, delta position
    P["nee_a"] = np.where(P["point_light"], 1.0, P["nee_a"])
    P["cos_fwd"][:, 0] = np.where(P["point_light"], 1.0, P["cos_fwd"][:, 0])
    P["lens_a"] = rng.uniform(0.5, 50.0, N)                # thin lens: 1 / (pi r^2)
    P["dens_fwd"] = np.ones((N, k))     # distance density along edge i from x_i
    P["dens_bwd"] = np.ones((N, k))     # ... and from x_{i+1}
    P["medium"] = np.zeros((N, k + 1), bool)   # medium vertices (add_media): never merged
    return P


def add_media(rng, P, k):
    """Distance densities on every edge, and medium vertices (cosine 1) at random."""
    P["dens_fwd"] = rng.uniform(0.02, 3.0, (N, k))
    P["dens_bwd"] = rng.uniform(0.02, 3.0, (N, k))
    medium = rng.uniform(size=(N, k + 1)) < 0.4
    medium[:, 0] = medium[:, k] = False
    medium &= ~P["delta"]
    P["cos_fwd"] = np.where(medium[:, :k], 1.0, P["cos_fwd"])
    P["cos_bwd"] = np.where(medium[:, 1:], 1.0, P["cos_bwd"])
    P["medium"] = medium
    return P


def strategy_valid(P, k, s, light_image):
    t = k + 1 - s
    ok = np.ones(N, bool)
    if t == 1 and not light_image:
        return ~ok
    if s == 0:
        return ~P["point_light"]
    if k == 1 and s == 1:                       # (1,1): emitter through the pinhole
        return ~P["point_light"]
    # the connection edge (x_{s-1}, x_s) needs both ends non-delta
    if s - 1 >= 1:
        ok &= ~P["delta"][:, s - 1]
    if s <= k - 1:
        ok &= ~P["delta"][:, s]
    return ok


def brute_force_pdf(P, k, s, lens=False):
    """Product of the area pdfs of strategy s (x_k's pinhole delta is common).  With
    ``lens``, x_k is a thin-lens point: every strategy with t >= 1 samples it with the
    lens's area density (the camera subpath by its aperture sample, the light image
    by its lens sample)."""
    p = np.array(P["lens_a"]) if lens else np.ones(N)
    for i in range(s):                          # light side x_0 .. x_{s-1}
        if i == 0:
            p *= P["nee_a"] if (s == 1 and k > 1) else P["e_pos"]
        else:
            # (at i = 1 pdf_l[0] plays the emission direction pdf)
            p *= (P["pdf_l"][:, i - 1] * P["cos_bwd"][:, i - 1] / P["dist2"][:, i - 1]
                  * P["dens_fwd"][:, i - 1])
    for i in range(s, k):                       # camera side x_s .. x_{k-1}
        pdf_w = P["cam_w"] if i == k - 1 else P["pdf_e"][:, i + 1]
        p *= pdf_w * P["cos_fwd"][:, i] / P["dist2"][:, i] * P["dens_bwd"][:, i]
    return p


def F(x):
    return mi.Float(np.asarray(x, dtype=np.float32))


def B(x):
    return mi.Bool(np.asarray(x, dtype=bool))


def rate(k, s, r, kappa):
    """The sampling rate m_s of strategy s (mis.py): N_L / N_C for t = 1, kappa for
    connections, 1 for s <= 1."""
    t = k + 1 - s
    return r if t == 1 else (1.0 if s <= 1 else kappa)


def merge_valid(P, k, i, eta):
    """Can the path be made by merging at x_i: a surface vertex (not in a medium) that
    scatters smoothly, neither on the emitter nor on the camera, merging on."""
    if eta <= 0 or not 1 <= i <= k - 1:
        return np.zeros(N, bool)
    return ~P["delta"][:, i] & ~P["medium"][:, i]


def brute_force_merge_pdf(P, k, i, eta, lens=False):
    """Merging at x_i (tech. rep. eq. 17, rate included): x_0 .. x_i sampled by the
    light subpath (x_0 by its emission position density), x_i .. x_{k-1} by the camera
    subpath, so x_i twice, times eta = pi r^2 N_L."""
    p = eta * (np.array(P["lens_a"]) if lens else np.ones(N)) * P["e_pos"]
    for l in range(1, i + 1):
        p = p * (P["pdf_l"][:, l - 1] * P["cos_bwd"][:, l - 1] / P["dist2"][:, l - 1]
                 * P["dens_fwd"][:, l - 1])
    for l in range(i, k):
        pdf_w = P["cam_w"] if l == k - 1 else P["pdf_e"][:, l + 1]
        p = p * pdf_w * P["cos_fwd"][:, l] / P["dist2"][:, l] * P["dens_bwd"][:, l]
    return p


def chain_weights(P, k, h, light_image, r=1.0, kappa=1.0, eta=0.0):
    """Weights of all strategies as the engine computes them (mis.py); with ``eta`` > 0
    also the merges, as ``w[("vm", i)]`` for merging at x_i."""
    vm = lambda i: F(np.where(P["medium"][:, i], 0.0, eta))     # noqa: E731
    emission_pdf = F(P["e_pos"] * P["pdf_l"][:, 0])
    # light subpath: states at x_1 .. x_{k-1}
    light = {}
    d_vc = mis.light_start(h, emission_pdf, F(P["cos_fwd"][:, 0]), B(P["point_light"]))
    fwd, bwd = P["dens_fwd"], P["dens_bwd"]
    d_vcm, d_vc = mis.light_first_hit(h, d_vc, F(P["nee_a"]), emission_pdf,
                                      F(P["dist2"][:, 0]), F(P["cos_bwd"][:, 0]),
                                      F(fwd[:, 0]), F(bwd[:, 0]))
    m = lambda depth: 1.0 if depth == 1 else kappa      # noqa: E731  (d_vcm's strategy)
    for i in range(1, k):
        light[i] = (d_vcm, d_vc)
        if i + 1 < k:
            d_vcm, d_vc = mis.after_scatter(h, d_vcm, d_vc, F(P["cos_fwd"][:, i]),
                                            F(P["pdf_l"][:, i]), F(P["pdf_e"][:, i]),
                                            B(P["delta"][:, i]), m(i), vm(i))
            d_vcm, d_vc = mis.after_hit(h, d_vcm, d_vc, F(P["dist2"][:, i]), F(P["cos_bwd"][:, i]),
                                        F(fwd[:, i]), F(bwd[:, i]))
    # camera subpath: states at x_{k-1} .. x_0
    cam = {}
    d_vcm, d_vc = mis.camera_start(h, F(P["cam_w"]), r, light_image)
    d_vcm, d_vc = mis.after_hit(h, d_vcm, d_vc, F(P["dist2"][:, k - 1]), F(P["cos_fwd"][:, k - 1]),
                                F(bwd[:, k - 1]), F(fwd[:, k - 1]))
    for i in range(k - 1, -1, -1):
        cam[i] = (d_vcm, d_vc)
        if i > 0:
            d_vcm, d_vc = mis.after_scatter(h, d_vcm, d_vc, F(P["cos_bwd"][:, i - 1]),
                                            F(P["pdf_e"][:, i]), F(P["pdf_l"][:, i]),
                                            B(P["delta"][:, i]), m(k - i), vm(i))
            d_vcm, d_vc = mis.after_hit(h, d_vcm, d_vc, F(P["dist2"][:, i - 1]),
                                        F(P["cos_fwd"][:, i - 1]), F(bwd[:, i - 1]), F(fwd[:, i - 1]))

    w = {}
    for s in range(0, k + 1):
        t = k + 1 - s
        if s == 0:
            dv = cam[0]
            direct = F(P["e_pos"]) if k == 1 else F(P["nee_a"])
            if k == 1 and not light_image:
                direct = F(np.zeros(N))
            w[s] = mis.weight_emission_hit(h, dv[0], dv[1], direct, emission_pdf)
        elif s == 1 and t == 1:
            cam_a = F(P["cam_w"] * P["cos_fwd"][:, 0] / P["dist2"][:, 0] * bwd[:, 0] / r)
            w[s] = mis.weight_emitter_to_camera(h, cam_a, F(P["e_pos"]))
        elif s == 1:
            dv = cam[1]
            bsdf_pdf = np.where(P["point_light"], 0.0, P["pdf_e"][:, 1])
            nee_w = P["nee_a"] * P["dist2"][:, 0] / P["cos_fwd"][:, 0]
            w[s] = mis.weight_nee(h, dv[0], dv[1], F(bsdf_pdf * bwd[:, 0]), F(nee_w),
                                  emission_pdf * F(fwd[:, 0]),
                                  F(P["cos_bwd"][:, 0]), F(P["cos_fwd"][:, 0]), F(P["pdf_l"][:, 1]),
                                  m(k - 1), vm(1))
        elif t == 1:
            lv = light[k - 1]
            cam_a = F(P["cam_w"] * P["cos_fwd"][:, k - 1] / P["dist2"][:, k - 1]
                      * bwd[:, k - 1] / r)
            w[s] = mis.weight_light_to_camera(h, lv[0], lv[1], cam_a, F(P["pdf_e"][:, k - 1]),
                                              m(k - 1), vm(k - 1))
        else:
            lv, cv = light[s - 1], cam[s]
            cam_pdf_a = (P["pdf_e"][:, s] * P["cos_fwd"][:, s - 1] / P["dist2"][:, s - 1]
                         * bwd[:, s - 1])
            light_pdf_a = (P["pdf_l"][:, s - 1] * P["cos_bwd"][:, s - 1] / P["dist2"][:, s - 1]
                           * fwd[:, s - 1])
            w[s] = mis.weight_connect(h, lv[0], lv[1], cv[0], cv[1], F(cam_pdf_a),
                                      F(P["pdf_l"][:, s]), F(light_pdf_a), F(P["pdf_e"][:, s - 1]),
                                      m(s - 1), m(k - s), kappa, vm(s - 1), vm(s))
    for i in range(1, k if eta > 0 else 1):
        lv, cv = light[i], cam[i]
        w[("vm", i)] = mis.weight_merge(h, lv[0], lv[1], F(P["pdf_e"][:, i]), cv[0], cv[1],
                                        F(P["pdf_l"][:, i]), F(np.full(N, eta)), m(i), m(k - i))
    return {s: np.array(v, dtype=np.float64) for s, v in w.items()}


BUDGETS = [(1.0, 1.0), (0.25, 1.0), (2.0, 0.0), (0.5, 0.3), (1.0, 2.5)]   # (N_L/N_C, kappa)


@pytest.mark.parametrize("heuristic", ["power", "balance", "uniform"])
@pytest.mark.parametrize("light_image", [True, False])
@pytest.mark.parametrize("k", [1, 2, 3, 4, 5, 6])
@pytest.mark.parametrize("r, kappa", BUDGETS)
def test_weights_sum_to_one_and_match_brute_force(heuristic, light_image, k, r, kappa):
    """Every budget: light subpaths per camera sample r, connection rate kappa (0:
    connections off, so that s <= 1 and t = 1 are MIS'ed alone)."""
    check_against_brute_force(np.random.default_rng(1000 * k + 7), heuristic, light_image,
                              k, r, kappa)


@pytest.mark.parametrize("heuristic", ["power", "balance"])
@pytest.mark.parametrize("k", [1, 2, 3, 4, 5])
@pytest.mark.parametrize("r, kappa", [(1.0, 1.0), (0.5, 0.3)])
def test_thin_lens_weights_match_brute_force(heuristic, k, r, kappa):
    """A thin lens: x_k = z_0 is a lens point of area density 1 / (pi r^2), which every
    strategy the renderer evaluates (t >= 1) samples; the t = 0 strategy (a light
    subpath hitting the lens) is left out of the render and of the brute-force sum
    alike.  The chains, which carry no lens density, give the brute-force weights:
    the lens density cancels (camera.Camera)."""
    check_against_brute_force(np.random.default_rng(500 * k + 3), heuristic, True, k, r,
                              kappa, lens=True)


@pytest.mark.parametrize("heuristic", ["power", "balance"])
@pytest.mark.parametrize("k", [1, 2, 3, 4, 5])
@pytest.mark.parametrize("r, kappa", [(1.0, 1.0), (0.5, 0.3), (1.0, 0.0)])
def test_media_weights_match_brute_force(heuristic, k, r, kappa):
    """Paths through media: each edge's distance densities (both directions) and
    medium vertices (cosine 1) enter the chains (mis.after_hit) as they enter the
    brute-force product of per-vertex densities."""
    check_against_brute_force(np.random.default_rng(300 * k + 11), heuristic, True, k, r,
                              kappa, media=True)


def check_against_brute_force(rng, heuristic, light_image, k, r, kappa, lens=False,
                              media=False, eta=0.0):
    P = random_path(rng, k)
    if media:
        P = add_media(rng, P, k)
    h = mis.Heuristic(heuristic)
    w = chain_weights(P, k, h, light_image, r, kappa, eta)
    valid = {s: strategy_valid(P, k, s, light_image) & (rate(k, s, r, kappa) > 0)
             for s in range(k + 1)}
    pdfs = {s: brute_force_pdf(P, k, s, lens) * rate(k, s, r, kappa) for s in range(k + 1)}
    for i in range(1, k if eta > 0 else 1):
        valid["vm", i] = merge_valid(P, k, i, eta)
        pdfs["vm", i] = brute_force_merge_pdf(P, k, i, eta, lens)
    hp = {s: np.where(valid[s], (pdfs[s] ** 2 if heuristic == "power" else
                                 pdfs[s] if heuristic == "balance" else 1.0), 0.0)
          for s in pdfs}
    denom = sum(hp.values())
    total = np.zeros(N)
    any_valid = np.zeros(N, bool)
    for s in pdfs:
        ws = np.where(valid[s], w[s], 0.0)      # invalid strategies never contribute
        assert np.all(np.isfinite(ws))
        expected = np.where(valid[s], hp[s] / np.where(denom > 0, denom, 1), 0.0)
        np.testing.assert_allclose(ws, expected, rtol=1e-4, atol=1e-6,
                                   err_msg="merging at x_%d" % s[1] if isinstance(s, tuple)
                                   else "strategy s=%d, t=%d" % (s, k + 1 - s))
        total += ws
        any_valid |= valid[s]
    np.testing.assert_allclose(total[any_valid], 1.0, atol=1e-4)


# eta = pi r^2 N_L: small (merging rarely wins), about the connections' densities, large
ETAS = [1e-3, 0.7, 40.0]


@pytest.mark.parametrize("heuristic", ["power", "balance", "uniform"])
@pytest.mark.parametrize("light_image", [True, False])
@pytest.mark.parametrize("k", [1, 2, 3, 4, 5, 6])
@pytest.mark.parametrize("r, kappa", [(1.0, 1.0), (0.5, 0.3), (2.0, 0.0)])
@pytest.mark.parametrize("eta", ETAS)
def test_merging_weights_sum_to_one_and_match_brute_force(heuristic, light_image, k, r,
                                                          kappa, eta):
    """Vertex merging (VCM) as k - 1 more strategies of a path of k edges: merging at
    every interior vertex that scatters smoothly, at rate eta, beside every
    connection strategy at its own rate; delta vertices merge nowhere."""
    check_against_brute_force(np.random.default_rng(900 * k + 17), heuristic, light_image,
                              k, r, kappa, eta=eta)


@pytest.mark.parametrize("heuristic", ["power", "balance"])
@pytest.mark.parametrize("k", [2, 3, 4, 5])
@pytest.mark.parametrize("eta", ETAS)
def test_merging_weights_with_media_and_lens(heuristic, k, eta):
    """Medium vertices connect but never merge; a thin lens's density cancels from
    merges as from connections."""
    check_against_brute_force(np.random.default_rng(40 * k + 1), heuristic, True, k, 1.0,
                              1.0, media=True, eta=eta)
    check_against_brute_force(np.random.default_rng(41 * k + 2), heuristic, True, k, 0.5,
                              0.3, lens=True, eta=eta)


@pytest.mark.parametrize("k", [1, 2, 3, 5])
def test_lafortune_weights_sum_to_one(k):
    """L&W's specularity-based weights sum to one over the strategies s = 0..k-1 that
    can sample the path, for random specularities, with delta vertices (W = 1) and
    point lights (s = 0 impossible).  A strategy joining z_{t-1} to z_t cannot where
    either is delta; the camera walk's products use W'(z_m) = 1 where z_{m+1} is delta
    (mis.lafortune_specularity): with W alone a path through a delta light-side vertex
    gave its whole weight to a connection that cannot be made."""
    rng = np.random.default_rng(k)
    W = rng.choice([0.0, 0.5, 1.0], size=(N, k + 1))     # W(z_m), m = 1..k (index m)
    delta = W == 1.0
    point = rng.uniform(size=N) < 0.3
    Wp = W.copy()                                        # W'(z_m): 1 before a delta z_{m+1}
    Wp[:, 1:k - 1] = np.where(delta[:, 2:k], 1.0, W[:, 1:k - 1])
    total, any_can = np.zeros(N), np.zeros(N, dtype=bool)
    for s in range(0, k):
        t = k + 1 - s
        prod = np.prod(Wp[:, 1:t - 1], axis=1) if t > 2 else np.ones(N)
        if s == 0:
            w = np.array(mis.weight_lafortune(F(np.prod(Wp[:, 1:k], axis=1)), None, "hit"))
            can = ~point                                  # a point light is never hit
        elif s == 1:
            w = np.array(mis.weight_lafortune(F(prod), F(W[:, t - 1]), "nee", B(point)))
            can = ~delta[:, t - 1]
        else:
            w = np.array(mis.weight_lafortune(F(prod), F(W[:, t - 1]), "connect"))
            can = ~delta[:, t - 1] & ~delta[:, t]
        assert np.all(w >= 0)
        total += np.where(can, w, 0.0)
        any_can |= can
    # No strategy of the scheme can sample a point light seen directly or through delta
    # vertices only from the light's side (light tracing's paths: no light image here).
    # Where the point light's first vertex y_1 = z_{k-1} is delta, the share that goes
    # on along the camera path past the last possible connection reaches neither s = 0
    # nor next-event estimation, and is lost: the render warns of such scenes
    # (support.warn_of_light_tracing_paths).
    assert any_can.mean() > 0.5
    lost = point & delta[:, k - 1]
    np.testing.assert_allclose(total[~lost], np.where(any_can, 1.0, 0.0)[~lost], atol=1e-5)
    assert np.all(total[lost] <= 1.0 + 1e-5)


def chain_groups(P, k, eta=0.0):
    """The pilot's balance-weight groups (u_pt, u_lt, u_vm) of every strategy, as the
    engine computes them: balance heuristic, unit rates, with each subpath's far-end
    scalar d_end (mis.end_after_hit / end_after_scatter) and, with merging at rate
    ``eta``, the merge part d_vm of d_vc (mis.vm_after_hit / vm_after_scatter); the
    merges' own groups as ``out["vm", i]``."""
    h = mis.Heuristic("balance")
    vm = lambda i: F(np.where(P["medium"][:, i], 0.0, eta))     # noqa: E731
    emission_pdf = F(P["e_pos"] * P["pdf_l"][:, 0])
    light = {}
    d_vc = mis.light_start(h, emission_pdf, F(P["cos_fwd"][:, 0]), B(P["point_light"]))
    d_vcm, d_vc = mis.light_first_hit(h, d_vc, F(P["nee_a"]), emission_pdf,
                                      F(P["dist2"][:, 0]), F(P["cos_bwd"][:, 0]))
    d_end, d_vm = F(np.zeros(N)), F(np.zeros(N))
    for i in range(1, k):
        light[i] = (d_vcm, d_vc, d_end, d_vm)
        if i + 1 < k:
            args = (F(P["cos_fwd"][:, i]), F(P["pdf_l"][:, i]), F(P["pdf_e"][:, i]), B(P["delta"][:, i]))
            d_end = mis.end_after_scatter(d_end, d_vcm, d_vc, *args, i == 1, True)
            d_vm = mis.vm_after_scatter(d_vm, *args, vm(i))
            d_vcm, d_vc = mis.after_scatter(h, d_vcm, d_vc, *args, 1.0, vm(i))
            d_end = mis.end_after_hit(d_end, F(P["dist2"][:, i]), F(P["cos_bwd"][:, i]), False)
            d_vm = mis.vm_after_hit(d_vm, F(P["dist2"][:, i]), F(P["cos_bwd"][:, i]))
            d_vcm, d_vc = mis.after_hit(h, d_vcm, d_vc, F(P["dist2"][:, i]), F(P["cos_bwd"][:, i]))
    cam = {}
    d_vcm, d_vc = mis.camera_start(h, F(P["cam_w"]), 1.0, True)
    d_end, d_vm = mi.Float(d_vcm), F(np.zeros(N))
    d_end = mis.end_after_hit(d_end, F(P["dist2"][:, k - 1]), F(P["cos_fwd"][:, k - 1]), True)
    d_vcm, d_vc = mis.after_hit(h, d_vcm, d_vc, F(P["dist2"][:, k - 1]), F(P["cos_fwd"][:, k - 1]))
    for i in range(k - 1, -1, -1):
        cam[i] = (d_vcm, d_vc, d_end, d_vm)
        if i > 0:
            args = (F(P["cos_bwd"][:, i - 1]), F(P["pdf_e"][:, i]), F(P["pdf_l"][:, i]), B(P["delta"][:, i]))
            d_end = mis.end_after_scatter(d_end, d_vcm, d_vc, *args, k - i == 1, False)
            d_vm = mis.vm_after_scatter(d_vm, *args, vm(i))
            d_vcm, d_vc = mis.after_scatter(h, d_vcm, d_vc, *args, 1.0, vm(i))
            d_end = mis.end_after_hit(d_end, F(P["dist2"][:, i - 1]), F(P["cos_fwd"][:, i - 1]), k - i + 1 == 1)
            d_vm = mis.vm_after_hit(d_vm, F(P["dist2"][:, i - 1]), F(P["cos_fwd"][:, i - 1]))
            d_vcm, d_vc = mis.after_hit(h, d_vcm, d_vc, F(P["dist2"][:, i - 1]), F(P["cos_fwd"][:, i - 1]))
    out = {}
    record = lambda v: type("Light", (), dict(zip(("d_vcm", "d_vc", "d_end", "d_vm"), v)))  # noqa: E731
    for s in range(0, k + 1):
        t = k + 1 - s
        if s == 0:
            dv = cam[0]
            direct = F(P["e_pos"]) if k == 1 else F(P["nee_a"])
            out[s] = mis.groups_emission_hit(dv[0], dv[1], dv[2], k == 1, direct, emission_pdf, dv[3])
        elif s == 1 and t == 1:
            x = P["cam_w"] * P["cos_fwd"][:, 0] / P["dist2"][:, 0] / P["e_pos"]
            out[s] = (F(x / (1 + x)), F(1 / (1 + x)), F(np.zeros(N)))
        elif s == 1:
            dv = cam[1]
            nee_w = P["nee_a"] * P["dist2"][:, 0] / P["cos_fwd"][:, 0]
            w_light = np.where(P["point_light"], 0.0, P["pdf_e"][:, 1]) / nee_w
            ratio = P["e_pos"] * P["pdf_l"][:, 0] * P["cos_bwd"][:, 0] / (nee_w * P["cos_fwd"][:, 0])
            out[s] = mis.groups_nee(dv[0], dv[1], dv[2], k - 1 == 1, F(w_light), F(ratio),
                                    F(P["pdf_l"][:, 1]), 1.0, dv[3], vm(1))
        elif t == 1:
            lv = light[k - 1]
            cam_a = F(P["cam_w"] * P["cos_fwd"][:, k - 1] / P["dist2"][:, k - 1])
            out[s] = mis.groups_light_image(lv[0], lv[1], lv[2], k - 1 == 1, cam_a,
                                            F(P["pdf_e"][:, k - 1]), 1.0, 1.0, lv[3], vm(k - 1))
        else:
            lv, cv = light[s - 1], cam[s]
            cam_pdf_a = P["pdf_e"][:, s] * P["cos_fwd"][:, s - 1] / P["dist2"][:, s - 1]
            light_pdf_a = P["pdf_l"][:, s - 1] * P["cos_bwd"][:, s - 1] / P["dist2"][:, s - 1]
            out[s] = mis.groups_connect(record(lv), s - 1 == 1, cv[0], cv[1], cv[2], k - s == 1,
                                        F(cam_pdf_a), F(P["pdf_l"][:, s]), F(light_pdf_a),
                                        F(P["pdf_e"][:, s - 1]), 1.0, 1.0, 1.0, cv[3],
                                        vm(s - 1), vm(s))
    for i in range(1, k if eta > 0 else 1):
        lv, cv = light[i], cam[i]
        out["vm", i] = mis.groups_merge(record(lv), i == 1, F(P["pdf_e"][:, i]), cv[0], cv[1],
                                        cv[2], cv[3], k - i == 1, F(P["pdf_l"][:, i]),
                                        F(np.full(N, eta)))
    return {s: tuple(np.array(x, dtype=np.float64) for x in u) for s, u in out.items()}


@pytest.mark.parametrize("k", [1, 2, 3, 4, 5, 6])
@pytest.mark.parametrize("eta", [0.0] + ETAS)
def test_pilot_groups_match_brute_force(k, eta):
    """The optimizer's per-sample groups: the shares of the balance heuristic's
    denominator held by path tracing (s <= 1, t >= 2), the light image (t = 1),
    merging (every merge, at rate ``eta``) and connections, for every strategy of
    random paths, delta vertices included, the merges' own samples too."""
    rng = np.random.default_rng(77 * k)
    P = random_path(rng, k)
    groups = chain_groups(P, k, eta)
    valid = {s: strategy_valid(P, k, s, True) for s in range(k + 1)}
    pdfs = {s: np.where(valid[s], brute_force_pdf(P, k, s), 0.0) for s in range(k + 1)}
    group = {s: "lt" if k + 1 - s == 1 else ("pt" if s <= 1 else "con") for s in range(k + 1)}
    for i in range(1, k if eta > 0 else 1):
        valid["vm", i] = merge_valid(P, k, i, eta)
        pdfs["vm", i] = np.where(valid["vm", i], brute_force_merge_pdf(P, k, i, eta), 0.0)
        group["vm", i] = "vm"
    total = sum(pdfs.values())
    for s in pdfs:
        mask = valid[s] & (total > 0)
        share = {g: sum(pdfs[j] for j in pdfs if group[j] == g) / np.where(total > 0, total, 1)
                 for g in ("pt", "lt", "vm")}
        for g, got in zip(("pt", "lt", "vm"), groups[s]):
            np.testing.assert_allclose(got[mask], share[g][mask], rtol=2e-4, atol=1e-6,
                                       err_msg="%s group %s" % (s, g))
