"""Multiple importance sampling for BDPT: the heuristic and the ratio chains.

Every MIS weight of the renderer is computed here, in O(1) per connection, from two
quantities that each subpath vertex carries (Georgiev, "Implementing Vertex
Connection and Merging", 2012 -- the VCM technical report -- section 6, with the
merging terms dropped; the same recursion SmallVCM's BPT mode uses):

    d_vcm, d_vc  (tech. rep. eqs. 31-33, 41-43)

They hold, already passed through the heuristic, the partial sums of pdf ratios
p_j / p_s (Veach's thesis eq. 10.9, Adamsen 2009 section 7.4) of every strategy that
would have sampled the vertices *behind* the current one from the other side.
A connection then needs only the pdfs at its two endpoints.

Conventions (Veach's): s light vertices y_0..y_{s-1}, t camera vertices
z_0..z_{t-1}; z_0 is on the camera (the pinhole, a lens point, or a point of an
orthographic film plane: camera.py), y_0 a point on an emitter.  Pdf names carry
their measure: ``*_pdf_w`` solid angle, ``*_pdf_a`` area.  "Pinhole" below stands
for z_0 whatever the camera.  All "cos" are geometric-normal cosines (they convert
solid angle to area, Veach eq. 8.10).

Strategies may be sampled at different rates (Veach's n_i in eq. 9.10; the budgets
of efficiency-aware MIS, Grittmann et al. 2022): the light image with N_L light
subpaths per N_C camera samples, and connections with a density factor kappa (0:
off; 1: each camera vertex to every vertex of one light subpath; M N_L / V: M
vertices drawn from a pool of V, Davidovic et al. 2014).  A strategy j of density
m_j p_j has weight h(m_j p_j) / sum_i h(m_i p_i).  In the chains, N_L / N_C enters
at the camera's start (``camera_start``); kappa multiplies every connection term
as it joins a chain (``after_scatter``'s and the weights' ``m_vcm``: d_vcm at a
subpath's first vertex stands for s = 1 or t = 1, beyond it for a connection) and
divides the rivals of a connection (``weight_connect``'s ``m_self``).

Vertex merging (``merging``, merge.py; tech. rep. sections 4-5, eqs. 20 and 34-40):
a camera surface vertex z that scatters smoothly merges with the pass's stored light
vertices y_i (i >= 1) within a radius r.  Merging at path vertex x_i has the density
of the connection strategy with light vertices x_0..x_{i-1}, times the light's area
density of x_i and the disc pi r^2 (eq. 17), at the rate N_L: every camera sample
merges against all N_L light subpaths of its pass.  Its rate-weighted density
relative to the connections is eta = pi r^2 N_L (eq. 20 with n_VC = 1, n_VM = N_L,
the report's eta_VCM), whatever N_C, the light image's rate or kappa.  The report
carries a third quantity d_vm; with connections on it is d_vc / eta, so here d_vc
alone carries the merging terms: the "+ eta" of eq. 35 (SmallVCM's
``mMisVmWeightFactor``) joins d_vc at every surface vertex that scatters smoothly,
and each strategy adds eta for its own endpoints where they could merge (eqs. 38-41).
Medium vertices connect but never merge (no eta term there); y_0 and z_0 never merge.
The merge itself (``weight_merge``, eq. 37) divides both partial sums by eta, which
is the report's d_vm = d_vc / eta.  Merging needs a ratio heuristic (power, balance,
uniform): Lafortune's weights have no densities (settings.py refuses the pair).

Consistency rules that make the weights of all strategies of a path sum to one
(checked by tests/test_mis.py against a brute-force evaluation):
  * Russian roulette is left out of every pdf (the weights are then functions of the
    path alone; roulette stays unbiased because it divides the throughput).
  * The emitter-selection pmf is part of every light pdf (emission and NEE).
  * Delta lobes contribute a pdf of 1 in both directions and forbid connections at
    their vertex (d_vcm = 0, tech. rep. section 6.1 "specular vertices").
  * y_0's pdf is the emission position pdf (pmf / area) in strategies with s >= 2 and
    (1,1), and the next-event pdf P_nee(y_0 | y_1) in (1,t>=2): Mitsuba samples
    spheres by solid angle for next-event estimation, so the two may differ.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .settings import HEURISTICS


class Heuristic:
    """The MIS heuristic as a map on pdf ratios: w_s = 1 / sum_j h(p_j / p_s).

    ``power``: h(x) = x^2 (Veach eq. 9.13, beta = 2); ``balance``: h(x) = x (eq. 9.10);
    ``uniform``: h(x) = 1 for x > 0, so every strategy that can produce the path gets
    the same weight (Adamsen 2009 section 7.3).  All three are multiplicative,
    h(ab) = h(a) h(b), which is what lets the ratio chains apply h factor by factor.
    ``lafortune`` is not a ratio heuristic: see ``weight_lafortune``.
    """

    def __init__(self, name: str = "power"):
        if name not in HEURISTICS:
            raise ValueError("bdpt: unknown mis heuristic %r (choose one of %s)"
                             % (name, ", ".join(HEURISTICS)))
        self.name = name

    @property
    def is_lafortune(self) -> bool:
        return self.name == "lafortune"

    def __call__(self, x):
        if self.name == "power":
            return dr.square(x)
        if self.name == "balance":
            return x
        return dr.select(x > 0, 1.0, 0.0)


def _div(a, b):
    """a / b with 0 where b is 0 or the result is not finite (no NaN enters a chain)."""
    r = a / b
    return dr.select((b != 0) & dr.isfinite(r), r, 0.0)


def _plus_vm(h: Heuristic, x, m_vm):
    """x + h(m_vm): a merging term, left out of the kernel where merging is off (a Python
    0), so that BDPT's kernels stay what they were without merging."""
    if isinstance(m_vm, (int, float)) and m_vm == 0:
        return x
    return x + h(m_vm)


def _weight(denominator):
    """1 / (sum of heuristic ratios), 0 if the sum is degenerate."""
    w = dr.rcp(denominator)
    return dr.select(dr.isfinite(w) & (denominator > 0), w, 0.0)


# ---------------------------------------------------------------------------
# Subpath starts
# ---------------------------------------------------------------------------

def camera_start(h: Heuristic, cam_pdf_w, light_paths_per_camera_sample: float,
                 light_image: bool):
    """(d_vcm, d_vc) at the camera vertex z_0 (tech. rep. eq. 31).

    ``cam_pdf_w`` is the solid-angle density of the camera ray over the film (crop)
    area, 1 / (A cos^3), with cos measured at z_0 (the pinhole, or the ray's own
    lens point for a thin lens).  The light tracer (t = 1) contributes to a pixel
    with N_L light paths against the camera's N_C samples, so its effective camera
    pdf is cam_pdf_w * N_C / N_L (tech. rep. eq. 46's division by the light path
    count).  Without the light image (light_image = false, or an orthographic camera,
    whose delta direction no light vertex can be connected along) the t = 1
    strategies are gone: d_vcm = 0 removes exactly their terms from every chain.

    d_vc = 0: no light subpath can hit z_0 (t = 0).  A pinhole and an orthographic
    camera cannot be hit; a thin lens could be, and its t = 0 strategy is left out
    of the render and, consistently, of every chain (camera.Camera).  A thin lens's
    position density 1 / (pi r^2) is common to all strategies evaluated, so it
    appears nowhere.
    """
    if not light_image:
        return mi.Float(0.0), mi.Float(0.0)
    return h(_div(light_paths_per_camera_sample, cam_pdf_w)), mi.Float(0.0)


def light_start(h: Heuristic, emission_pdf, cos_emit, delta_position):
    """d_vc at y_0 (tech. rep. eq. 32); d_vcm waits for y_1 (see ``light_first_hit``).

    ``emission_pdf`` = pmf * pdf_pos_a * pdf_dir_w, the density of the emitted ray.
    A delta-position emitter (point, spot) or a directional light cannot be hit by a
    camera path: d_vc = 0.
    """
    return dr.select(delta_position, 0.0, h(_div(cos_emit, emission_pdf)))


def light_first_hit(h: Heuristic, d_vc0, nee_pdf_a, emission_pdf, dist2, cos_hit,
                    dens_fwd=1.0, dens_rev=1.0):
    """(d_vcm, d_vc) at y_1 (tech. rep. eqs. 32 and 34 combined).

    ``nee_pdf_a`` = P_nee(y_0 | y_1) in area measure (pmf included): the density with
    which next-event estimation from y_1 would have chosen y_0.  For a delta-position
    emitter it is the selection pmf (the position delta cancels against the
    emission's).  ``dens_*``: the edge's distance densities in media (``after_hit``).
    """
    inv = _div(1.0, h(cos_hit * dens_fwd))
    d_vcm = h(_div(nee_pdf_a * dist2, emission_pdf)) * inv
    d_vc = d_vc0 * h(dens_rev) * inv
    return d_vcm, d_vc


# ---------------------------------------------------------------------------
# Updates along a subpath
# ---------------------------------------------------------------------------

def after_hit(h: Heuristic, d_vcm, d_vc, dist2, cos_hit, dens_fwd=1.0, dens_rev=1.0):
    """Convert to area measure at the vertex just found (tech. rep. eq. 34).

    In media (media.py) a vertex's density also holds the density of the distances
    drawn to reach it: ``dens_fwd`` along the edge just followed, ``dens_rev`` the
    other way, into the vertex behind (which the reverse term of d_vc stands for;
    pbrt-v3 section 16.3.2 converts densities the same way).  ``cos_hit`` is 1 at a
    medium vertex.
    """
    inv = _div(1.0, h(cos_hit * dens_fwd))
    return d_vcm * h(dist2) * inv, d_vc * h(dens_rev) * inv


def after_escape(h: Heuristic, d_vcm, d_vc, dens_fwd, dens_rev):
    """``after_hit`` for a ray that escaped to the environment through media: the
    chains stay in solid angle (no distance, no cosine at infinity)."""
    inv = _div(1.0, h(dens_fwd))
    return d_vcm * inv, d_vc * h(dens_rev) * inv


def after_scatter(h: Heuristic, d_vcm, d_vc, cos_out, pdf_fwd_w, pdf_rev_w, delta,
                  m_vcm=1.0, m_vm=0.0):
    """Account for the direction sampled at the current vertex (tech. rep. eqs. 35-36).

    ``pdf_fwd_w``: density of the sampled direction; ``pdf_rev_w``: density of the
    reverse direction, i.e. of sampling where the subpath came from, had it arrived
    from the new direction.  A delta lobe's pdfs cancel: d_vcm = 0 forbids
    connecting at this vertex and d_vc only picks up the cosine (section 6.1).
    ``m_vcm``: the rate of the strategy d_vcm stands for (module docstring).
    ``m_vm``: eta where this vertex could merge (a surface vertex; merging on), else 0:
    merging here is one more strategy behind the next vertex (tech. rep. eq. 35's
    eta term; SmallVCM adds its ``mMisVmWeightFactor`` in the same place).
    """
    d_vc_smooth = h(_div(cos_out, pdf_fwd_w)) * _plus_vm(h, d_vc * h(pdf_rev_w)
                                                         + h(m_vcm) * d_vcm, m_vm)
    d_vcm_smooth = h(_div(1.0, pdf_fwd_w))
    return (dr.select(delta, 0.0, d_vcm_smooth),
            dr.select(delta, d_vc * h(cos_out), d_vc_smooth))


# ---------------------------------------------------------------------------
# Weights of the four kinds of strategies
# ---------------------------------------------------------------------------

def weight_emission_hit(h: Heuristic, d_vcm, d_vc, direct_pdf_a, emission_pdf):
    """s = 0: the camera subpath hit an emitter (tech. rep. eq. 48).

    ``direct_pdf_a``: density with which the s = 1 strategy would pick the hit point
    (P_nee from the previous camera vertex, or pmf/area when that vertex is the
    pinhole, i.e. the (1,1) strategy).  ``emission_pdf``: emission density of the
    ray leaving the emitter toward the previous camera vertex.
    """
    return _weight(1.0 + h(direct_pdf_a) * d_vcm + h(emission_pdf) * d_vc)


def weight_nee(h: Heuristic, d_vcm, d_vc, bsdf_pdf_w, nee_pdf_w, emission_pdf,
               cos_cam, cos_light, bsdf_rev_w, m_vcm=1.0, m_vm=0.0):
    """s = 1: next-event estimation at camera vertex z_{t-1} (tech. rep. eqs. 44-45).

    ``bsdf_pdf_w``: density of the camera vertex's BSDF sampling the light direction
    (0 for delta lights: the s = 0 strategy cannot hit them).  ``nee_pdf_w``: the NEE
    density of that direction (pmf included).  ``cos_cam``/``cos_light``: cosines at
    the camera vertex and at the emitter (1 for delta-position emitters).  ``m_vm``:
    eta where the camera vertex could merge with y_1 (eq. 45's eta term).
    """
    w_light = h(_div(bsdf_pdf_w, nee_pdf_w))
    w_camera = h(_div(emission_pdf * cos_cam, nee_pdf_w * cos_light)) * _plus_vm(
        h, h(m_vcm) * d_vcm + d_vc * h(bsdf_rev_w), m_vm)
    return _weight(w_light + 1.0 + w_camera)


def weight_light_to_camera(h: Heuristic, d_vcm, d_vc, cam_pdf_a, bsdf_rev_w, m_vcm=1.0,
                           m_vm=0.0):
    """t = 1, s >= 2: light vertex y_{s-1} splatted through the pinhole (eq. 46).

    ``cam_pdf_a``: the camera's area density at the light vertex, already scaled by
    N_C / N_L (see ``camera_start``).  ``bsdf_rev_w``: density at y_{s-1} of sampling
    the direction back to y_{s-2} had the path arrived from the camera.  ``m_vm``: eta
    where y_{s-1} could merge with z_1 (eq. 46's eta term).
    """
    return _weight(1.0 + h(cam_pdf_a) * _plus_vm(h, h(m_vcm) * d_vcm + d_vc * h(bsdf_rev_w),
                                                 m_vm))


def weight_emitter_to_camera(h: Heuristic, cam_pdf_a, emission_pos_pdf_a):
    """(1,1): the emitter point y_0 seen directly through the pinhole.

    Its only rival is (0,2), the camera ray hitting y_0: w = 1 / (1 + h(p_02 / p_11)).
    """
    return _weight(1.0 + h(_div(cam_pdf_a, emission_pos_pdf_a)))


def weight_connect(h: Heuristic, light_d_vcm, light_d_vc, cam_d_vcm, cam_d_vc,
                   cam_bsdf_pdf_a, cam_bsdf_rev_w, light_bsdf_pdf_a, light_bsdf_rev_w,
                   m_light_vcm=1.0, m_cam_vcm=1.0, m_self=1.0, m_light_vm=0.0,
                   m_cam_vm=0.0):
    """s >= 2, t >= 2: connect y_{s-1} to z_{t-1} by a shadow ray (eqs. 40, 47).

    ``cam_bsdf_pdf_a``: density of z_{t-1}'s BSDF sampling y_{s-1} (area measure at
    y_{s-1}); ``light_bsdf_pdf_a`` likewise from y_{s-1} to z_{t-1}.  The ``*_rev_w``
    are each vertex's density of sampling its own predecessor had it arrived along
    the connecting edge.  ``m_self``: the connection's own rate (kappa).  ``m_*_vm``:
    eta where that endpoint could merge (eqs. 40-41's eta terms).
    """
    w_light = h(cam_bsdf_pdf_a) * _plus_vm(
        h, h(m_light_vcm) * light_d_vcm + light_d_vc * h(light_bsdf_rev_w), m_light_vm)
    w_camera = h(light_bsdf_pdf_a) * _plus_vm(
        h, h(m_cam_vcm) * cam_d_vcm + cam_d_vc * h(cam_bsdf_rev_w), m_cam_vm)
    return _weight(1.0 + _div(w_light + w_camera, h(m_self)))


def weight_merge(h: Heuristic, light_d_vcm, light_d_vc, light_rev_w, cam_d_vcm, cam_d_vc,
                 cam_rev_w, eta, m_light_vcm=1.0, m_cam_vcm=1.0):
    """Merging light vertex y_i with camera vertex z_j (tech. rep. eqs. 37-39).

    The merged path takes z_j's position and BSDF: ``light_rev_w`` is z_j's density of
    sampling the light's incoming direction (toward y_{i-1}) had the path come from the
    camera, i.e. its forward pdf (SmallVCM's ``cameraBsdfDirPdfW``); ``cam_rev_w`` its
    density of sampling the camera's direction (toward z_{j-1}) had the path come from
    the light (``cameraBsdfRevPdfW``).  Every rival's rate-weighted density over the
    merge's eta p: the light side's connections and merges behind y_i, the camera
    side's behind z_j, both over eta (the report's d_vm = d_vc / eta).
    """
    w_light = h(m_light_vcm) * light_d_vcm + light_d_vc * h(light_rev_w)
    w_camera = h(m_cam_vcm) * cam_d_vcm + cam_d_vc * h(cam_rev_w)
    return _weight(1.0 + _div(w_light + w_camera, h(eta)))


# ---------------------------------------------------------------------------
# Lafortune & Willems' specularity-based weights
# ---------------------------------------------------------------------------

def lafortune_specularity(bsdf_flags, delta_sampled=False):
    """W(z) of a camera vertex (L&W 1993, "Selecting the weights"): the share of the
    estimate that continues along the camera path rather than connecting at z.

    1 where the path crossed z through a delta lobe (no connection can make such a
    path); otherwise the BSDF's degree of specularity, here 1/2 if it has a glossy
    lobe and 0 if all its lobes are diffuse.

    The camera walk multiplies W'(z_m) = 1 instead where the next vertex z_{m+1} is
    delta: a connection ending at z_m would join it to z_{m+1}, a light vertex no
    connection can use, so the share it would take goes on along the camera path.
    With W alone, the weights summed to one over all strategies but not over those that
    can sample the path: a caustic (light, glass, floor, camera) put all its weight on
    connecting the floor to the glass vertex and was lost (Mitsuba's glass and mirror
    spheres rendered 2% dark, the weighting benchmark's glass caustic 9%).
    """
    glossy = mi.has_flag(bsdf_flags, mi.BSDFFlags.Glossy)
    return dr.select(delta_sampled, 1.0, dr.select(glossy, 0.5, 0.0))


def weight_lafortune(prod_before, w_here, strategy: str, delta_light=False):
    """L&W weight of a strategy ending its camera subpath at z_{t-1}.

    ``prod_before`` = prod_{m < t-1} W(z_m); ``w_here`` = W(z_{t-1}).  For a path of k
    edges the weights telescope to one over s = 0 .. k-1:
      s = 0 (emitter hit at z_k):     prod_{m <= k-1} W(z_m)
      s >= 1 (connect at z_{t-1}):    prod_{m < t-1} W(z_m) * (1 - W(z_{t-1}))
    with W' for W in the products (lafortune_specularity), over the strategies that can
    sample the path.
    A delta-position emitter cannot be hit, so NEE keeps the s = 0 share as well.
    The light image (t = 1) is not part of the scheme (weight 0).
    """
    if strategy == "hit":
        return prod_before
    if strategy == "nee":
        return prod_before * dr.select(delta_light, 1.0, 1.0 - w_here)
    return prod_before * (1.0 - w_here)


# ---------------------------------------------------------------------------
# Every weighting decision of a render
# ---------------------------------------------------------------------------

class Weights:
    """The MIS weight of each kind of strategy, for one render's strategy set.

    The strategy code (connect.py, splat.py) evaluates a contribution and the
    densities at its endpoints, named by measure, and asks here for the weight.
    The decisions that depend on which strategies are on live here alone:

    * no MIS for a single technique or the light-tracing subset (one strategy per
      path length): every weight is 1;
    * the rates of the light image (N_L / N_C) and of connections (kappa) of the
      pass (``set_rates``; the module docstring): the path-tracing subset is the
      rates 0 and 0, s = 0 and s = 1 then being each other's only rivals;
    * (1,1), the emitter seen through the pinhole, is the only rival of (0,2);
    * Lafortune & Willems' weights, which use no densities at all.
    """

    def __init__(self, heuristic: str, strategies, shadow: bool = False):
        """``shadow``: merges are evaluated for a moment pass's samples only (the vcm
        pilot, optimizer.py): the image's weights, chains and contributions are those
        without merging, and ``moment_d_vc`` / ``vm_moment`` give the moments' own."""
        self.h = Heuristic(heuristic)
        self.on = strategies.use_mis
        self.lafortune = self.on and self.h.is_lafortune
        self.rival_11 = bool(strategies.enabled(1, 1))
        self.light_image = strategies.light_image
        # The light image is the only strategy left for paths whose z_1 scatters
        # smoothly (budgets.Budget.light_first_hits): a t = 1 contribution has a smooth
        # z_1 (= y_{s-1}, connected to the camera) and so weight 1, and the camera walk
        # evaluates nothing at a z_1 hit and continues past z_1 only through a delta
        # lobe, where d_vcm = 0 already drops the t = 1 term from every chain.
        self.light_first_hits = strategies.light_first_hits
        # Are there strategies beyond s <= 1?  Without them the chains stay 0 and the
        # densities that only feed them (reverse pdfs, emission densities) are not
        # computed: path tracing then costs what Mitsuba's path costs.
        # merges_evaluated: merge queries run; merging: they are part of the image's MIS.
        self.merges_evaluated = self.on and strategies.merging
        self.shadow = shadow and self.merges_evaluated
        self.merging = self.merges_evaluated and not self.shadow
        self.chains = self.on and (strategies.light_image or strategies.connects or self.merging)
        self.set_rates(1.0, 1.0)
        self.set_merging(0.0)

    def set_rates(self, light_ratio: float, kappa: float) -> None:
        """This pass's N_L / N_C and connection rate (opaque: no kernel per value)."""
        self.light_ratio = dr.opaque(mi.Float, light_ratio)
        self.kappa = dr.opaque(mi.Float, kappa)

    def set_merging(self, eta: float) -> None:
        """This pass's merging rate eta = pi r^2 N_L (opaque: no kernel per radius)."""
        self.eta = dr.opaque(mi.Float, eta)

    def vm(self, surface=True):
        """The merging term of a vertex: eta at a surface vertex with merging on (a
        medium vertex never merges), else 0 (a Python 0 leaves it out of the kernels)."""
        if not self.merging:
            return 0.0
        if surface is True:
            return self.eta
        return dr.select(surface, self.eta, 0.0)

    def vm_moment(self, surface=True):
        """``vm`` of the moments: eta wherever merges are evaluated, in the image or not."""
        if not self.merges_evaluated:
            return 0.0
        return self.eta if surface is True else dr.select(surface, self.eta, 0.0)

    def moment_d_vc(self, d_vc, d_vm):
        """d_vc as the moments' weights see it: with merging's part d_vm, which the
        image's chain lacks in a shadow pass (and already holds otherwise)."""
        return d_vc + d_vm if self.shadow else d_vc

    def rate(self, depth):
        """The rate of the strategy that d_vcm stands for at a subpath's vertex of this
        depth: s = 1 or t = 1 at the first vertex, a connection beyond it."""
        return dr.select(depth == 1, 1.0, self.kappa)

    # -- the chains along a subpath (see the functions above) ------------------------
    def camera_start(self, cam_pdf_w):
        return camera_start(self.h, cam_pdf_w, self.light_ratio, self.light_image)

    def light_start(self, emission_pdf_aw, cos_emit, delta):
        return light_start(self.h, emission_pdf_aw, cos_emit, delta)

    def after_hit(self, d_vcm, d_vc, dist2, cos_hit, dens_fwd=1.0, dens_rev=1.0):
        return after_hit(self.h, d_vcm, d_vc, dist2, cos_hit, dens_fwd, dens_rev)

    def after_escape(self, d_vcm, d_vc, dens_fwd, dens_rev):
        return after_escape(self.h, d_vcm, d_vc, dens_fwd, dens_rev)

    def after_scatter(self, d_vcm, d_vc, cos_out, pdf_fwd_w, pdf_rev_w, delta, depth,
                      surface=True):
        return after_scatter(self.h, d_vcm, d_vc, cos_out, pdf_fwd_w, pdf_rev_w, delta,
                             self.rate(depth), self.vm(surface))

    @staticmethod
    def specularity(bsdf_flags, delta_sampled=False):
        return lafortune_specularity(bsdf_flags, delta_sampled)

    # -- the weights of the strategies ---------------------------------------------
    def emission_hit(self, d_vcm, d_vc, lw, from_pinhole, nee_pdf_a, pos_pdf_a, emission_pdf_aw):
        """s = 0 at an area emitter.  The rival s = 1 strategy picks the hit point by
        next-event estimation from the previous camera vertex (``nee_pdf_a``), or,
        when that vertex is the pinhole, by the emission sampling of (1,1)."""
        if not self.on:
            return mi.Float(1.0)
        if self.lafortune:
            return weight_lafortune(lw, None, "hit")
        return weight_emission_hit(self.h, d_vcm, d_vc,
                                   self.direct_pdf_a(from_pinhole, nee_pdf_a, pos_pdf_a),
                                   emission_pdf_aw)

    def direct_pdf_a(self, from_pinhole, nee_pdf_a, pos_pdf_a):
        """The density with which the rival s = 1 strategy picks an emitter hit."""
        return dr.select(from_pinhole, pos_pdf_a if self.rival_11 else 0.0, nee_pdf_a)

    def environment_hit(self, d_vcm, d_vc, lw, from_pinhole, nee_pdf_w, emission_pdf_aw):
        """s = 0 on a ray that escaped: the chains as the last scatter left them, and
        the rivals' densities in solid angle (y_0 at infinity has no distance, tech.
        rep. section 5.1; SmallVCM's background light).  A camera ray that escapes
        at once has no rival: y_0 at infinity cannot be connected to the pinhole."""
        if not self.on:
            return mi.Float(1.0)
        if self.lafortune:
            return weight_lafortune(lw, None, "hit")
        w = weight_emission_hit(self.h, d_vcm, d_vc, nee_pdf_w, emission_pdf_aw)
        return dr.select(from_pinhole, 1.0, w)

    @staticmethod
    def nee_density_w(ds, pdf_emitter_direction_w, directional):
        """The solid-angle density with which next-event estimation picked ``ds``.
        An area emitter: Mitsuba's ``pdf_emitter_direction`` (not ``ds.pdf``: the
        s = 0 strategy and the light subpaths can only query the former, and for a
        sphere seen from inside the two differ slightly).  A delta-position emitter:
        its pmf per unit area, pmf * d^2 in solid angle (cos = 1), as in SmallVCM.
        A directional light: a discrete direction at infinity, its pmf alone."""
        pdf = dr.select(ds.delta, ds.pdf * dr.square(ds.dist), pdf_emitter_direction_w)
        return dr.select(directional, ds.pdf, pdf)

    def nee(self, d_vcm, d_vc, lw, depth, specularity, delta_light, bsdf_pdf_w, nee_pdf_w,
            emission_pdf_aw, cos_cam, cos_light, bsdf_rev_w, surface=True):
        """s = 1 at camera vertex z_{t-1} (t - 1 = ``depth``); a delta light cannot be
        hit (s = 0)."""
        if not self.on:
            return mi.Float(1.0)
        if self.lafortune:
            return weight_lafortune(lw, specularity, "nee", delta_light)
        return weight_nee(self.h, d_vcm, d_vc, dr.select(delta_light, 0.0, bsdf_pdf_w),
                          nee_pdf_w, emission_pdf_aw, cos_cam, cos_light, bsdf_rev_w,
                          self.rate(depth), self.vm(surface))

    def light_to_camera(self, d_vcm, d_vc, depth, cam_pdf_a, bsdf_rev_w, surface=True):
        """t = 1 at light vertex y_{s-1} (s - 1 = ``depth``); ``cam_pdf_a``: the
        camera's area density there.  The light image's rate is N_L / N_C."""
        if not self.on or self.light_first_hits:
            return mi.Float(1.0)
        return weight_light_to_camera(self.h, d_vcm, d_vc, cam_pdf_a / self.light_ratio,
                                      bsdf_rev_w, self.rate(depth), self.vm(surface))

    def emitter_to_camera(self, cam_pdf_a, pos_pdf_a):
        """(1,1), the light image at y_0."""
        if not self.on or self.light_first_hits:
            return mi.Float(1.0)
        return weight_emitter_to_camera(self.h, cam_pdf_a / self.light_ratio, pos_pdf_a)

    def connect(self, light, cam_d_vcm, cam_d_vc, cam_depth, lw, specularity,
                cam_bsdf_pdf_a, cam_bsdf_rev_w, light_bsdf_pdf_a, light_bsdf_rev_w,
                light_surface=True, cam_surface=True):
        """s, t >= 2: stored light vertex ``light`` (y_{s-1}) to camera vertex
        z_{t-1} (t - 1 = ``cam_depth``)."""
        if not self.on:
            return mi.Float(1.0)
        if self.lafortune:
            return weight_lafortune(lw, specularity, "connect")
        return weight_connect(self.h, light.d_vcm, light.d_vc, cam_d_vcm, cam_d_vc,
                              cam_bsdf_pdf_a, cam_bsdf_rev_w, light_bsdf_pdf_a, light_bsdf_rev_w,
                              self.rate(light.s - 1), self.rate(cam_depth), self.kappa,
                              self.vm(light_surface), self.vm(cam_surface))

    def merge(self, light, cam_d_vcm, cam_d_vc, cam_depth, light_rev_w, cam_rev_w,
              light_d_vc=None):
        """Merging stored light vertex ``light`` (y_i, i = s - 1) at camera vertex z_j
        (j = ``cam_depth``), both surfaces; ``*_rev_w`` as in ``weight_merge``;
        ``light_d_vc``: in place of light.d_vc (a shadow pass's ``moment_d_vc``).  Weight
        1 where merging is the only strategy (``ppm``)."""
        if not self.merges_evaluated:
            return mi.Float(1.0)
        return weight_merge(self.h, light.d_vcm, light.d_vc if light_d_vc is None else light_d_vc,
                            light_rev_w, cam_d_vcm, cam_d_vc, cam_rev_w, self.eta,
                            self.rate(light.s - 1), self.rate(cam_depth))

    def first_light_vertex(self, d_vc0, nee_pdf_a, nee_pdf_w, infinite, emission_pdf_aw,
                           dist2, cos_hit, dens_fwd=1.0, dens_rev=1.0):
        """(d_vcm, d_vc) at y_1.  y_0 at infinity (environment, directional light):
        the next-event density is a solid-angle one and no distance enters (tech. rep.
        section 5.1; SmallVCM skips dist^2 for infinite lights)."""
        nee = dr.select(infinite, nee_pdf_w, nee_pdf_a)
        return light_first_hit(self.h, d_vc0, nee, emission_pdf_aw,
                               dr.select(infinite, 1.0, dist2), cos_hit, dens_fwd, dens_rev)


# ---------------------------------------------------------------------------
# The pilot's balance-weight groups (optimizer.py)
# ---------------------------------------------------------------------------
# In a moment pass (balance heuristic; the pilot's rates are 1, a later one's are its
# budget's) each contribution also reports its balance weight's denominator split into
# path tracing (s <= 1), the light image (t = 1) and connections, as the shares
# (u_pt, u_lt) of the total.  The s <= 1 terms of a light-side strategy and the t = 1
# term of a camera-side one lie at the far ends of the chains: one scalar per
# subpath, d_end, carries them (``end_after_*``); at a subpath's first vertex they are
# the chain itself.  The totals are the weights' own, rates included (``m_vcm``: the
# rate of the current vertex's d_vcm term; ``light_ratio``; ``kappa``): with the
# rates left out, a pass without connections reported a share for them.

def end_after_hit(d_end, dist2, cos_hit, first, dens_fwd=1.0, dens_rev=1.0):
    """d_end at the vertex just found: as d_vcm at the first vertex, as d_vc beyond."""
    return d_end * dr.select(first, dist2, dens_rev) * _div(1.0, cos_hit * dens_fwd)


def end_after_scatter(d_end, d_vcm, d_vc, cos_out, pdf_fwd_w, pdf_rev_w, delta, first,
                      light_side):
    """d_end after scattering at the current vertex.  Camera side: the t = 1 term, in
    d_vcm's place at z_1 (d_end = d_vcm there), in d_vc's beyond.  Light side: at y_1
    every term of the chain is s <= 1, so d_end starts as the new d_vc."""
    start = (d_vc * pdf_rev_w + d_vcm) if light_side else d_end
    prev = dr.select(first, start, d_end * pdf_rev_w)
    delta_prev = dr.select(first, d_vc if light_side else 0.0, d_end) * cos_out
    return dr.select(delta, delta_prev, _div(cos_out, pdf_fwd_w) * prev)


# Merging's share (u_vm): the eta terms of a chain are its merges, so a third scalar
# per subpath, d_vm, carries the part of d_vc that eta put there (d_vc is affine in eta
# under the balance heuristic): it follows d_vc's recursion without the d_vcm term
# (``vm_after_scatter``; ``vm_after_hit`` is d_vc's conversion).  It is 0 at both
# subpaths' starts (y_0 and z_0 never merge).  A strategy's merging share is then its
# d_vm terms and its own endpoints' eta terms over its balance total.

class Chains:
    """A light vertex's chains as the groups read them (``groups_connect``, ``groups_merge``)."""
    def __init__(self, d_vcm, d_vc, d_end, d_vm):
        self.d_vcm, self.d_vc, self.d_end, self.d_vm = d_vcm, d_vc, d_end, d_vm


def vm_after_hit(d_vm, dist2, cos_hit, dens_fwd=1.0, dens_rev=1.0):
    """d_vm at the vertex just found (d_vc's part of ``after_hit``)."""
    return d_vm * dens_rev * _div(1.0, cos_hit * dens_fwd)


def vm_after_scatter(d_vm, cos_out, pdf_fwd_w, pdf_rev_w, delta, m_vm):
    """d_vm after scattering (``after_scatter``'s d_vc with d_vcm's term left out);
    ``m_vm``: eta where this vertex could merge."""
    return dr.select(delta, d_vm * cos_out, _div(cos_out, pdf_fwd_w) * (d_vm * pdf_rev_w + m_vm))


def _shares(pt, lt, vm, total):
    return _div(pt, total), _div(lt, total), _div(vm, total)


def groups_emission_hit(d_vcm, d_vc, d_end, from_pinhole, direct_pdf, emission_pdf, d_vm=0.0):
    """s = 0; from the pinhole the only rival is (1,1), a light-image strategy."""
    rival = direct_pdf * d_vcm
    total = 1.0 + rival + emission_pdf * d_vc
    return _shares(dr.select(from_pinhole, 1.0, 1.0 + rival),
                   dr.select(from_pinhole, rival, emission_pdf * d_end),
                   dr.select(from_pinhole, 0.0, emission_pdf * d_vm), total)


def groups_nee(d_vcm, d_vc, d_end, first, w_light, camera_ratio, bsdf_rev_w, m_vcm=1.0,
               d_vm=0.0, m_vm=0.0):
    total = w_light + 1.0 + camera_ratio * (m_vcm * d_vcm + d_vc * bsdf_rev_w + m_vm)
    lt = camera_ratio * dr.select(first, d_end, d_end * bsdf_rev_w)
    return _shares(w_light + 1.0, lt, camera_ratio * (d_vm * bsdf_rev_w + m_vm), total)


def groups_light_image(d_vcm, d_vc, d_end, first, cam_pdf_a, bsdf_rev_w, light_ratio=1.0,
                       m_vcm=1.0, d_vm=0.0, m_vm=0.0):
    """``cam_pdf_a`` unscaled: the light image's rate divides it, as in its weight."""
    cam_pdf_a = cam_pdf_a / light_ratio
    chain = m_vcm * d_vcm + d_vc * bsdf_rev_w
    pt = cam_pdf_a * dr.select(first, chain, d_end * bsdf_rev_w)
    return _shares(pt, 1.0, cam_pdf_a * (d_vm * bsdf_rev_w + m_vm),
                   1.0 + cam_pdf_a * (chain + m_vm))


def groups_connect(light, light_first, cam_d_vcm, cam_d_vc, cam_d_end, cam_first,
                   cam_bsdf_pdf_a, cam_bsdf_rev_w, light_bsdf_pdf_a, light_bsdf_rev_w,
                   m_light_vcm=1.0, m_cam_vcm=1.0, kappa=1.0, cam_d_vm=0.0,
                   m_light_vm=0.0, m_cam_vm=0.0):
    """Relative to the connection's own density kappa p (``weight_connect``)."""
    light_chain = m_light_vcm * light.d_vcm + light.d_vc * light_bsdf_rev_w
    cam_chain = m_cam_vcm * cam_d_vcm + cam_d_vc * cam_bsdf_rev_w
    total = kappa + (cam_bsdf_pdf_a * (light_chain + m_light_vm)
                     + light_bsdf_pdf_a * (cam_chain + m_cam_vm))
    pt = cam_bsdf_pdf_a * dr.select(light_first, light_chain, light.d_end * light_bsdf_rev_w)
    lt = light_bsdf_pdf_a * dr.select(cam_first, cam_d_end, cam_d_end * cam_bsdf_rev_w)
    vm = (cam_bsdf_pdf_a * (light.d_vm * light_bsdf_rev_w + m_light_vm)
          + light_bsdf_pdf_a * (cam_d_vm * cam_bsdf_rev_w + m_cam_vm))
    return _shares(pt, lt, vm, total)


def groups_merge(light, light_first, light_rev_w, cam_d_vcm, cam_d_vc, cam_d_end, cam_d_vm,
                 cam_first, cam_rev_w, eta, m_light_vcm=1.0, m_cam_vcm=1.0):
    """Relative to the merge's own density eta p (``weight_merge``): its rivals are the
    chains on both sides over eta, their far ends path tracing (light side) and the
    light image (camera side) as in ``groups_connect``, and their d_vm terms merges."""
    light_chain = m_light_vcm * light.d_vcm + light.d_vc * light_rev_w
    cam_chain = m_cam_vcm * cam_d_vcm + cam_d_vc * cam_rev_w
    total = eta + light_chain + cam_chain
    pt = dr.select(light_first, light_chain, light.d_end * light_rev_w)
    lt = dr.select(cam_first, cam_d_end, cam_d_end * cam_rev_w)
    return _shares(pt, lt, eta + light.d_vm * light_rev_w + cam_d_vm * cam_rev_w, total)
