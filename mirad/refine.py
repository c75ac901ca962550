"""The Refine stage of the hierarchical core: link arrays, their errors, and what to split.

Every link r <- s carries its transfer F (form factor with visibility) and two errors in
form-factor units, both from the receiver points of its wave (transfer.py):

* ``err_ff``: the error of F as the receiver's *mean*. On a face cluster, the standard
  error of its K area-stratified point transfers G_i v_i (the variation of the light over
  the cluster is not an error: the final gather in core.py gives every input triangle below
  it its own share); on a triangle, the quadrature error of the unoccluded part: the
  difference between the degree-5 rule and an embedded degree-2 rule on its outer six
  points, about C (h/d)^3 for a receiver of radius h at distance d, scaled by (h/d)^3 to
  the degree-5 rule's C (h/d)^6 (capped at 1). A face-cluster source's rectangle stands
  in for its triangles scaled by its fill ratio: F (1 - fill) more.
  Where the source is smaller than the receiver and nearer to it than the receiver's radius
  (``unresolved``), the light peaks on a spot the K points may all miss, and then their
  spread misses it too: there ``err_ff`` is at least the difference from the same
  unoccluded transfer summed over the source's own points (``reciprocal_error``, exact
  point-to-polygon form factors to the receiver, times A_s / A_r), and the final gather
  does not interpolate such a link over the receiver. The same transfer from the source's
  side measures what a receiver misses that straddles the source's plane with every point
  behind it (``unseen_in_front``): its part in front may see the source.
* ``vis_std``: the standard error of the visibility sampling, F_unocc sqrt(V (1 - V) / n)
  over the link's n rays (zero when all rays agree), or a volume cluster's sampled
  transfer's (``volume_transfer_std``). Zero on face clusters: there a volume cluster's
  sampling error is an error of the mean (``err_ff`` is at least it), since the final gather
  evaluates the link again on the leaves below with rays of its own.

As power (W): irradiance errors over the receiver's area A_r, with the source's brightest
channel (``power_errors``; ERRORS_OF = "irradiance": what the receiver absorbs and what it
reflects are both outputs, so a dark or black receiver's light counts as much as a white
one's; with "radiosity" each term is also weighted by the receiver's reflectance rho_r):

    receiver term  A_r B_s (p err_ff + sqrt(2/pi) vis_std)
    source term    A_r F dev_s min(1, 2 R_s / d)

where p is 1 on triangles and, on face clusters, rho_r times the gain with which an error
in the cluster's mean reaches the output (``SourceState.propagation``: the cluster's own
triangles are gathered again, so the error travels only in the light the cluster sends,
amplified by interreflection; the face clusters' sampling errors add in quadrature over
receivers, see ``face_mean_errors``), and dev_s is the mean |B_leaf - B_s|
over the source's leaves plus how far each leaf's own radiosity varies over it from its
point, spot and sun light (``core.own_deviation``, ``core.OWN_SOURCE_DEVIATION``: a leaf's
shadow on the leaf below it, which its own underside faces most), so a sunlit source splits
where its shadows matter (the link carries the source's mean; the kernel's relative change
across the source, at most its size over its distance, turns that into a transfer error). A volume-cluster source has no exact
transfer: its term is A_r B_max,s F_bound (the bounding sphere's form factor and
the brightest leaf below, Smits-Arvo-Greenberg), so it opens wherever it matters; a
cluster holding an emitter always opens for receivers within its bounding sphere's
diameter (there the sphere bounds nothing useful) and is bounded like the others farther
away.

Refinement (``choose``) splits a link whose error exceeds eps: the source when it is a
volume cluster or its term dominates; otherwise the larger end that can split; a link on a
triangle whose error is mostly visibility noise first gets four times the rays (up to
``MAX_RAYS_PER_POINT``), which costs no new nodes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from .arrays import row_norm, row_slices, row_sum, take_rows
from .cluster import sphere_form_factor_bound
from .nodes import DUNAVANT7_BARY, FACE, RECEIVER_POINTS, TRIANGLE, VOLUME, Nodes
from .transfer import PointTransfers, pattern_size, ray_target

#: What the tolerance bounds: the error of the "irradiance" H (so of absorbed and reflected
#: light alike) or of the reflected radiosity B - E only ("radiosity").
ERRORS_OF = "irradiance"
#: Most shadow rays per receiver point (a link traces at most K times this many).
MAX_RAYS_PER_POINT = 16
#: A degree-2 rule on the six outer points of Dunavant's 7-point rule (nodes.DUNAVANT7_BARY):
#: weights that integrate 1 and the symmetric second moment (1/6) exactly.
def _embedded_weights() -> np.ndarray:
    m1, m2 = ((DUNAVANT7_BARY[k] ** 2).sum() for k in (1, 4))   # a^2 + 2 b^2 of each orbit
    w2 = (1 / 6 - m1 / 3) / (m2 - m1)
    return np.array([0.0] + [1 / 3 - w2] * 3 + [w2] * 3)


EMBEDDED_WEIGHTS = _embedded_weights()
#: Expected |N(0, s)| / s: turns a standard error into an expected absolute error.
EXPECTED_ABS = float(np.sqrt(2.0 / np.pi))
#: Relative difference under which two link or leaf errors count as the same error (float32
#: rounding of the transfers they come from is about 6e-8).
SAME_ERROR = 1e-6


@dataclass
class Links:
    """Links receiver <- source as parallel arrays (M rows).

    recv, src : (M,) int32     node ids
    ff : (M,) float32          transfer (form factor with visibility), receiver-area mean
    ff_unocc : (M,) float32    unoccluded form factor
    err_ff : (M,) float32      representation / quadrature error of ff (see module docstring)
    vis_std : (M,) float32     standard error of ff from visibility sampling
    spread : (M,) float32      mean absolute deviation of the point transfers over the receiver
    rays : (M,) int16          shadow rays per receiver point used
    change : (M,) float32      the kernel's relative change across the source (``kernel_change``),
                               kept with the link: the source term reads it every pass
    grad : (M, 3) float32      the transfer's gradient over the receiver, in its plane (1/m: the
                               weighted plane through its points' transfers, each with its own
                               visibility; 0 on volume clusters), set by ``core.evaluate_links``
    """

    recv: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    src: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    ff: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    ff_unocc: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    err_ff: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    vis_std: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    spread: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    rays: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int16))
    change: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    grad: np.ndarray | None = None

    _FIELDS = ("recv", "src", "ff", "ff_unocc", "err_ff", "vis_std", "spread", "rays", "change", "grad")

    def __post_init__(self):
        if self.grad is None:
            self.grad = np.zeros((len(self.recv), 3), np.float32)

    def __len__(self) -> int:
        return len(self.recv)

    @property
    def nbytes(self) -> int:
        return sum(getattr(self, f).nbytes for f in self._FIELDS)

    def select(self, mask) -> "Links":
        return Links(**{f: getattr(self, f)[mask] for f in self._FIELDS})

    def extend(self, other: "Links") -> "Links":
        return Links(**{f: np.concatenate([getattr(self, f), getattr(other, f)]) for f in self._FIELDS})

    def matrix(self, n: int) -> sp.csr_matrix:
        """(N, N) sparse transfer matrix: H_recv = F @ B_src (duplicates summed)."""
        return sp.csr_matrix((self.ff.astype(np.float64), (self.recv, self.src)), shape=(n, n))


def link_values(nodes: Nodes, recv: np.ndarray, src: np.ndarray, pt: PointTransfers, rays: np.ndarray) -> Links:
    """Links from the per-point results of a wave (see module docstring)."""
    w = take_rows(nodes.recv_w, recv).astype(np.float64)
    g = pt.g.astype(np.float64)
    gv = pt.gv.astype(np.float64)
    ff = row_sum(w * gv)
    ff_unocc = row_sum(w * g)
    vis = visible_fraction(ff, ff_unocc)
    face_recv = nodes.kind[recv] == FACE
    # triangles: the 7-point degree-5 rule against the degree-2 rule on its six outer points
    # (EMBEDDED_WEIGHTS). Their difference is about the degree-2 rule's error C (h/d)^3 for a
    # receiver of radius h at distance d from the source; the degree-5 rule's is about
    # C (h/d)^6, hence the (h/d)^3 factor (capped at 1). d is the distance to the nearest
    # part of the source (its bounding sphere), not to its centre: a triangle in the corner
    # of a large wall is next to the light it gets, where the kernel is steepest
    d = distance_to_source(nodes, recv, src)
    h = nodes.radius[recv]
    order_gain = np.minimum(1.0, (h / np.maximum(d, 1e-12 * np.maximum(h, 1e-300))) ** 3)
    low = row_sum(g * EMBEDDED_WEIGHTS[None])
    quad = np.abs(ff_unocc - low) * order_gain * vis
    dev = pt.gv_point.astype(np.float64) - ff[:, None]
    spread = row_sum(w * np.abs(dev))
    # a face cluster's mean from its K area-stratified points: their standard error (the
    # variation of the light over the cluster is not an error: the final gather resolves it
    # on the input triangles; only the cluster's mean enters the solution)
    # (the points are stratified along the cluster's patches in their spatial order: the
    # successive-difference estimator of a systematic sample's variance, which is the i.i.d.
    # one for rough integrands and small where the light is smooth)
    step = np.diff(pt.gv_point.astype(np.float64), axis=1)
    k = RECEIVER_POINTS
    stratified = np.sqrt((step * step).sum(axis=1) / (2.0 * (k - 1)) / k)
    err = np.where(face_recv, stratified, quad)
    # a face-cluster source is its bounding rectangle scaled by its fill: off by about
    # F (1 - fill) from afar, but from closer than its size the rectangle's overhang (into
    # its neighbours' area) may be the nearest, brightest part: the whole F is in doubt
    src_face = nodes.kind[src] == FACE
    overhang = (nodes.fill[src] < 1.0 - 1e-6) & (d <= 2.0 * nodes.radius[src])
    err = err + np.where(src_face, np.where(overhang, ff, ff * (1.0 - nodes.fill[src])), 0.0)
    n_rays = RECEIVER_POINTS * rays.astype(np.float64)
    seen = noise_visibility(ff, ff_unocc, n_rays)
    partial = (seen > 1e-6) & (seen < 1 - 1e-6) & (nodes.kind[src] != VOLUME) & ~face_recv
    vis_std = np.where(partial, ff_unocc * np.sqrt(np.clip(seen * (1 - seen), 0, 0.25) / n_rays), 0.0)
    vol = nodes.kind[src] == VOLUME
    if vol.any():
        vis_std[vol] = volume_transfer_std(take_rows(w, vol), take_rows(gv, vol),
                                           take_rows(pt.gv_square, vol).astype(np.float64), ff_unocc[vol], rays[vol],
                                           recv[vol])
        if VOLUME_NOISE_OF_FACE_MEANS:
            # (the points' stratified estimate alone, inside a cluster's sphere, read a third of
            # the seeds' spread where the samples' own error read it)
            on_face = vol & face_recv
            err[on_face] = np.maximum(err[on_face], vis_std[on_face])
            vis_std[on_face] = 0.0
    return Links(recv.astype(np.int32), src.astype(np.int32), ff.astype(np.float32), ff_unocc.astype(np.float32),
                 err.astype(np.float32), vis_std.astype(np.float32), spread.astype(np.float32),
                 rays.astype(np.int16), kernel_change(nodes, recv, src).astype(np.float32))


#: Whether a volume cluster's sampling error on a face-cluster receiver counts as the error of
#: the receiver's mean (``err_ff``, reaching the output only through the light the cluster
#: reflects, ``face_mean_errors``) rather than as visibility noise on the output: the final
#: gather evaluates every link on a face cluster again on the leaves below, with rays of its own.
VOLUME_NOISE_OF_FACE_MEANS = True


#: How near to a volume-cluster source (the gap from its bounding sphere to the receiver's
#: centre, in the sphere's radii) its transfer is bounded by the spheres' form factor rather than
#: judged by its samples' error (``power_errors``): 0, only where the sphere holds the receiver's
#: centre. It was 2 (the sphere's diameter) until 2026-11-29, a rule made before the samples were
#: weighted by the kernel (``transfer.KERNEL_WEIGHTED_VOLUMES``): a canopy's passes then opened
#: every cluster near each leaf (the 1,000-leaf canopy at 0.9: 14 passes, 147,629 links, 2.44 s
#: for 2.04 % per leaf; now 55,501 links, 1.10 s for 2.35 %, and 2 % per leaf in about 1.5 s for
#: 2.4 s). A cluster holding an emitter still opens for every receiver within its diameter.
NEAR_CLUSTER_GAP = 0.0


def holds_receiver(nodes: Nodes, recv: np.ndarray, src: np.ndarray) -> np.ndarray:
    """(M,) bool: links recv <- src whose source is a volume cluster within NEAR_CLUSTER_GAP of its
    radii of the receiver's centre (its sphere holds the centre, for a gap of 0): those
    ``power_errors`` bounds by the spheres' form factor."""
    return (nodes.kind[src] == VOLUME) & (distance_to_source(nodes, recv, src) <= NEAR_CLUSTER_GAP * nodes.radius[src])


def holding_chains_opened(nodes: Nodes, recv: np.ndarray, src: np.ndarray, per_light: np.ndarray,
                          brightest: np.ndarray, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """Links recv <- src (M,), the children of split links, with each volume-cluster source that
    ``holds_receiver`` and whose bound is over eps replaced by links from its children, down the
    chain: (the input link each comes from (M',), its source (M',)). ``per_light`` (M,): the
    split link's receiver term per W/m^2 of its brightest leaf (0 where its own source did not
    hold the receiver); ``brightest`` (N,): each cluster's brightest leaf below, W/m^2.

    A receiver inside nested clusters keeps its bound when one of them opens: the child that
    holds it takes the spheres' form factor, 1 inside, shared as before among the receiver's
    cluster links, times its own brightest leaf. Refinement would so open the chain a level a
    pass wherever that stays over eps (a 1,000-leaf canopy's leaves each sit inside some ten
    nested clusters: 14 passes); opened here, those levels cost no waves and no passes."""
    out_i, out_s = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    item, src = np.arange(len(recv)), np.asarray(src, np.int64)
    recv = np.asarray(recv, np.int64)
    while len(item):
        holds = holds_receiver(nodes, recv[item], src)
        # (volume clusters only: the triangles just split are beyond ``brightest``)
        held = np.flatnonzero(holds)
        holds[held] = per_light[item[held]] * brightest[src[held]] > eps
        out_i.append(item[~holds])
        out_s.append(src[~holds])
        own, kid = nodes.children_of(src[holds])
        item, src = item[holds][own], kid
    order = np.argsort(np.concatenate(out_i), kind="stable")
    return np.concatenate(out_i)[order], np.concatenate(out_s)[order]


#: Whether a transfer all of whose shadow rays were blocked counts the noise of its visibility
#: (``noise_visibility``) instead of being taken as certainly hidden.
BLOCKED_NOT_CERTAIN = True


def noise_visibility(ff: np.ndarray, ff_unocc: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """(M,) the visibility a transfer's noise is counted with, from its form factor ff (M,) and
    unoccluded one ff_unocc (M,) over ``rays`` (M,) shadow rays: ``visible_fraction``, but where
    every ray was blocked (0) the rule of succession's 1 / (n + 2), the mean visibility that n
    blocked rays leave under a uniform prior.

    A transfer whose rays all met an occluder is not certainly hidden: the kernel weighs the
    rays, and from near a large source the one or two targets nearest the receiver decide it.
    Taken as certain, its error was 0 and nothing evaluated it again: a chair seat's underside
    0.41 m over the floor read the floor's form factor as 0 where it is 0.80 (7 rays, all
    aimed near the chair's legs), and on the furnished room at tolerance 0.15 723 such links
    held 4.5 W of the 143 W the links carry (64 rays a point), 3 %. (Rays that all arrive are
    checked again at the leaves, ``core.check_rays``.)"""
    vis = np.asarray(visible_fraction(ff, ff_unocc), np.float64)
    if not BLOCKED_NOT_CERTAIN:
        return vis
    return np.where(vis <= 0.0, 1.0 / (np.asarray(rays, np.float64) + 2.0), vis)


def visible_fraction(ff: np.ndarray, ff_unocc: np.ndarray) -> np.ndarray:
    """(M,) a transfer's visibility: its form factor over the unoccluded one (1 where the
    unoccluded one is 0)."""
    return np.where(ff_unocc > 0, ff / np.where(ff_unocc > 0, ff_unocc, 1.0), 1.0)


def unresolved(nodes: Nodes, recv: np.ndarray, src: np.ndarray) -> np.ndarray:
    """(M,) bool: links whose source is smaller than their receiver and nearer to the
    receiver's surface than the receiver's radius: the light it brings peaks on a spot about
    as wide as that distance, which the receiver's K points need not resolve (all of them
    may miss it, and then so does their spread).

    The distance runs from the source's bounding sphere to the receiver's disc (its bounding
    sphere's section in its plane): the height over the plane and the reach beyond the rim."""
    out = (nodes.kind[recv] != VOLUME) & (nodes.radius[src] < nodes.radius[recv])
    # (the distances only where the cheap tests leave a link: a gathered pair's receiver, a
    # leaf, is rarely the larger end)
    some = np.flatnonzero(out)
    recv, src = recv[some], src[some]
    rel = take_rows(nodes.center, src) - take_rows(nodes.center, recv)
    height = np.abs(np.einsum("mc,mc->m", rel, take_rows(nodes.normal, recv)))
    across = np.sqrt(np.maximum(np.einsum("mc,mc->m", rel, rel) - height ** 2, 0.0))
    beyond = np.maximum(across - nodes.radius[recv], 0.0)
    gap = np.maximum(np.hypot(height, beyond) - nodes.radius[src], 0.0)
    out[some] = gap < nodes.radius[recv]
    return out


def unseen_in_front(nodes: Nodes, recv: np.ndarray, src: np.ndarray, ff_unocc: np.ndarray) -> np.ndarray:
    """(M,) bool: links whose receiver straddles the (planar) source's plane and none of whose
    points saw the source: the receiver's part in front may still see it, which only the
    transfer taken from the source's side tells (``reciprocal_error``). (Points that do see it
    sample the part in front like any other variation, and a source straddling the receiver's
    plane is clipped exactly at each point.) The bounding spheres' form factor alone, 1
    wherever one sphere holds the other, is kept only where the source's points saw nothing
    of the receiver either: a ground under a canopy straddles every tilted leaf's plane, and
    with the bound its links to leaves its points did not see held 50 times the tolerance's
    budget, each the ground's area times the leaf's radiosity."""
    out = (nodes.kind[src] != VOLUME) & (nodes.kind[recv] == FACE) & (np.asarray(ff_unocc) <= 0)
    # (the plane test only for the links the cheap tests leave: a few in a hundred)
    some = np.flatnonzero(out)
    out[some] = _straddles(nodes, recv[some], src[some])
    return out


def reciprocal_error(nodes: Nodes, recv: np.ndarray, src: np.ndarray, ff: np.ndarray, ff_unocc: np.ndarray,
                     reverse: np.ndarray) -> np.ndarray:
    """(M,) form-factor units: how far the receiver-side means of links recv <- src (their
    receivers' K points: ``ff_unocc``, and ``ff`` with visibility) are from the same
    unoccluded transfer integrated over the source's side, A_s / A_r sum_k w_k F(y_k -> r)
    (``reverse`` (M, K): transfer.reverse_form_factor), times the links' visibility: where
    the receiver's points miss a near source's spot, the two disagree."""
    other = nodes.area[src] / np.maximum(nodes.area[recv], 1e-300) * \
        row_sum(take_rows(nodes.recv_w, src) * reverse)
    ff_unocc = np.asarray(ff_unocc, np.float64)
    vis = visible_fraction(ff, ff_unocc)
    return np.abs(ff_unocc - other) * vis


def volume_transfer_std(w: np.ndarray, mean: np.ndarray, square: np.ndarray, unoccluded: np.ndarray,
                        rays: np.ndarray, recv: np.ndarray | None = None, spread: bool = False) -> np.ndarray:
    """(M,) standard error of links' Monte Carlo transfers from volume clusters.

    w (M, K): the receiver points' weights; mean, square (M, K): the mean over each point's
    rays of the sampled transfer and of its square; unoccluded (M,): the transfer had every
    ray arrived; rays (M,) per point. The samples' variance is pooled over the points (their
    spread over the receiver counts as noise: conservative), times ``shared_target_weight`` (as
    if the points' rays to one target drew the same triangle: conservative too, since each point
    draws its own, ``transfer.source_point``). Where every ray was blocked (or none was) the
    samples' variance is 0 however few they were: a floor of the unoccluded transfer over the
    ray count stands for the one that might have turned over. ``recv`` (M,): the receiver
    nodes w is of, where known (``shared_target_weight`` then goes once per receiver). With
    ``spread`` (``transfer.ray_target``) every ray has its own target: sum_i w_i^2 / R."""
    f = row_sum(w * mean)
    pooled = np.maximum(row_sum(w * square) - f * f, 0.0)
    n = RECEIVER_POINTS * rays.astype(np.float64)
    weight = row_sum(w * w) / rays if spread else shared_target_weight(w, rays, recv)
    std = np.sqrt(pooled * weight)
    return np.maximum(std, unoccluded / n)


def shared_target_weight(w: np.ndarray, rays: np.ndarray, recv: np.ndarray | None = None) -> np.ndarray:
    """(M,) sum_t c_t^2: what turns one sample's variance into that of a link's transfer,
    with c_t = sum_i w_i n_it / R the weight of the link's target point t (of
    ``transfer.pattern_size(R)``) and n_it how many of point i's R rays aim at it
    (``transfer.ray_target``). The points' rays share the link's targets; were the samples
    independent this would be sum_i w_i^2 / R, which targets drawn by several points' rays
    exceed (four rays a point: 28 rays on 16 targets). ``recv`` (M,): the receiver nodes whose
    points' weights w are, or None: where given, each (receiver, rays) is computed once (a
    canopy's links share a few thousand receivers)."""
    if recv is not None and len(recv):
        key = np.asarray(recv, np.int64) * (int(rays.max()) + 1) + rays
        _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
        return shared_target_weight(w[first], rays[first])[inverse]
    out = np.zeros(len(w))
    k = w.shape[1]
    for r in np.unique(rays):
        r = int(r)
        target = ray_target(np.arange(k)[:, None], np.arange(r)[None, :], r)               # (K, R)
        uses = np.zeros((k, pattern_size(r)))
        np.add.at(uses, (np.repeat(np.arange(k), r), target.ravel()), 1.0)
        idx = np.flatnonzero(rays == r)
        c = w[idx] @ uses / r
        out[idx] = (c * c).sum(axis=1)
    return out


#: Node pairs per chunk of ``centre_distance``: its (M, 3) temporaries over a large scene's
#: tens of millions of gathered pairs held gigabytes at once.
DISTANCE_CHUNK = 1 << 20


def centre_distance(nodes: Nodes, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(M,) m: from the centre of each node a to that of b (M,)."""
    out = np.empty(len(a))
    for part in row_slices(len(a), DISTANCE_CHUNK):
        out[part] = row_norm(take_rows(nodes.center, a[part]) - take_rows(nodes.center, b[part]))
    return out


def kernel_change(nodes: Nodes, recv: np.ndarray, src: np.ndarray, dist: np.ndarray | None = None) -> np.ndarray:
    """(M,) the kernel's relative change across each source seen from its receiver, min(1,
    2 R_s / d) over the distance d between their centres (``dist`` (M,), ``centre_distance``'s,
    where the caller has it): what turns a source's radiosity deviation into a transfer error
    (the source term)."""
    dist = centre_distance(nodes, recv, src) if dist is None else dist
    return np.minimum(1.0, 2.0 * nodes.radius[src] / np.maximum(dist, 1e-300))


def distance_to_source(nodes: Nodes, recv: np.ndarray, src: np.ndarray, dist: np.ndarray | None = None) -> np.ndarray:
    """(M,) m: from each receiver's centre to the nearest point of its source's bounding
    sphere (0 inside it); ``dist`` (M,): ``centre_distance``'s, where the caller has it."""
    dist = centre_distance(nodes, recv, src) if dist is None else dist
    return np.maximum(dist - nodes.radius[src], 0.0)


def _straddles(nodes: Nodes, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(M,) bool: face cluster a has patches on both sides of (planar) b's plane.

    A face cluster lies inside its form-factor rectangle (nodes.Nodes.poly), so the signed
    heights of the rectangle's corners over b's plane bound those of its patches; touching
    the plane (a floor against a wall) is not straddling it."""
    h = np.einsum("mc,mkc->mk", take_rows(nodes.normal, b),
                  take_rows(nodes.poly, a) - take_rows(nodes.poly[:, 0], b)[:, None])
    tol = 1e-6 * np.maximum(nodes.radius[a], 1e-300)
    return (nodes.kind[a] == FACE) & (h.min(axis=1) < -tol) & (h.max(axis=1) > tol) & \
        (nodes.kind[b] != VOLUME) & \
        (np.abs(np.einsum("mc,mc->m", take_rows(nodes.normal, a), take_rows(nodes.normal, b))) < 1 - 1e-6)


@dataclass
class SourceState:
    """What the errors need of the current solution, per node (N,).

    b_max : brightest channel of the node's mean radiosity, W/m^2
    b_max_below : brightest leaf below (volume-cluster bounds), W/m^2
    dev : area-weighted mean |B_leaf - B_node| over the node's leaves (max channel), W/m^2

    b_max_below and dev are read at links' sources only, and set there only (0 elsewhere;
    b_max_below also at every volume cluster with ``core.OPEN_HOLDING_CHAINS``).
    """

    b_max: np.ndarray
    b_max_below: np.ndarray
    dev: np.ndarray
    propagation: float = 1.0
    mean_weight: np.ndarray | None = None
    #: (N,) what an error in each node's light weighs in the estimate (core.output_weight), or
    #: None: 1 everywhere
    output_weight: np.ndarray | None = None

    def grow(self, nodes: Nodes) -> "SourceState":
        """Children made since: their parent's values (deviation halved) until the next solve."""
        n_old = len(self.b_max)
        if len(nodes) == n_old:
            return self
        par = nodes.parent[n_old:]

        def grown(a):
            return None if a is None else np.concatenate([a, a[par]])

        return SourceState(grown(self.b_max), grown(self.b_max_below), np.concatenate([self.dev, 0.5 * self.dev[par]]),
                           self.propagation, grown(self.mean_weight), grown(self.output_weight))

    def weight(self, ids: np.ndarray) -> np.ndarray:
        """(M,) ``output_weight`` of nodes ids (ones without it)."""
        return np.ones(len(ids)) if self.output_weight is None else self.output_weight[ids]


def receiver_weight(nodes: Nodes, recv: np.ndarray) -> np.ndarray:
    """(M,) what an error in a receiver's irradiance weighs in the estimate: 1 when the
    tolerance is on irradiance (ERRORS_OF, the default: a dark surface's absorbed light and
    a black one's irradiance are outputs too), the receiver's largest reflectance when it is
    on reflected radiosity."""
    return np.ones(len(recv)) if ERRORS_OF == "irradiance" else nodes.rho_max[recv].astype(np.float64)


def face_mean_errors(nodes: Nodes, links: Links, state: SourceState, *, weighted: bool = True) -> np.ndarray:
    """(M,) W: the part of the receiver term that is the error of the receiver's mean
    (err_ff), as it reaches the output.

    A face cluster's own triangles get their light from the final gather (core.py), so an
    error in the cluster's mean reaches the output only once reflected elsewhere, and then
    with every further bounce: ``state.propagation`` (mean reflectance times the solution's
    interreflection gain). The cluster's mean is an unbiased stratified estimate, so the
    errors of different receivers are independent and add in quadrature: with ``weighted``,
    each link's share is scaled by ``state.mean_weight`` of its receiver (e_r / sqrt(sum
    e_r^2), set by core.estimate), so that the shares sum to the quadrature total."""
    r, s = links.recv, links.src
    e = nodes.area[r] * state.b_max[s] * links.err_ff
    face = nodes.kind[r] == FACE
    # (a face cluster's mean error is sent on as radiosity: rho_r times it, amplified)
    e = np.where(face, state.propagation * nodes.rho_max[r] * e, receiver_weight(nodes, r) * state.weight(r) * e)
    if weighted and state.mean_weight is not None:
        e = np.where(face, e * state.mean_weight[r], e)
    return e


def power_errors(nodes: Nodes, links: Links, state: SourceState) -> tuple[np.ndarray, np.ndarray]:
    """(receiver term, source term) of every link, W (see module docstring)."""
    r, s = links.recv, links.src
    # (a face cluster's mean error above is sent on as light whatever its shape; the terms
    # below are the receiver's own, weighted as its shape is in the estimate)
    scale = nodes.area[r] * receiver_weight(nodes, r) * state.weight(r)
    # a face cluster's own triangles get their light from the final gather (core.py): an
    # error in the cluster's mean reaches the output only once reflected again elsewhere
    receiver = scale * state.b_max[s] * EXPECTED_ABS * links.vis_std + face_mean_errors(nodes, links, state)
    source = scale * links.ff * state.dev[s] * links.change
    vol = np.flatnonzero(nodes.kind[s] == VOLUME)
    # a far cluster's transfer is a Monte Carlo estimate, its error the samples' (the
    # receiver term above) and its radiosity's variation (the source term); from inside its
    # sphere (NEAR_CLUSTER_GAP) the samples say little: bounded there
    gap = distance_to_source(nodes, r[vol], s[vol]) / np.maximum(nodes.radius[s[vol]], 1e-300)
    emitting = vol[(gap <= 2.0) & nodes.emits[s[vol]]]
    vol = vol[gap <= NEAR_CLUSTER_GAP]
    if len(vol):
        rv, sv = r[vol], s[vol]
        bound = sphere_form_factor_bound(nodes.center[rv], nodes.radius[rv], nodes.center[sv], nodes.radius[sv])
        # a receiver's form factors sum to at most 1, so the bounds of its cluster links, each
        # up to 1 near the cluster, are shared out: their sum stays within min(1, sum of the
        # bounds) (opening a cluster into two children near the receiver no longer doubles it)
        total = np.bincount(rv, weights=bound, minlength=len(nodes))[rv]
        share = np.where(total > 1.0, 1.0 / np.maximum(total, 1e-300), 1.0)
        receiver[vol] = scale[vol] * state.b_max_below[sv] * bound * share
        source[vol] = 0.0
    # a cluster holding an emitter opens for the receivers near it (within its bounding
    # sphere's diameter, where the sphere says little about the light: all of these), and
    # elsewhere is judged like any other cluster: a thousand small lamps then reach a far wall
    # as a few clusters, not a thousand links
    receiver[emitting] = np.inf
    source[emitting] = 0.0
    return receiver, source


@dataclass
class Decision:
    """What a refinement wave does with the links it looked at (masks over them)."""

    split_src: np.ndarray
    split_recv: np.ndarray
    more_rays: np.ndarray

    @property
    def any(self) -> bool:
        return bool(self.split_src.any() or self.split_recv.any() or self.more_rays.any())


def choose(nodes: Nodes, links: Links, receiver: np.ndarray, source: np.ndarray, eps: float,
           min_area: float) -> Decision:
    """Which links over eps split their source, their receiver, or trace more rays."""
    r, s = links.recv, links.src
    over = (receiver + source) > eps
    can = nodes.splittable(min_area)
    can_r, can_s = can[r] & (nodes.kind[r] != VOLUME), can[s]
    vol_src = nodes.kind[s] == VOLUME
    noisy = (nodes.kind[r] == TRIANGLE) & (EXPECTED_ABS * links.vis_std > links.err_ff) & \
        (links.rays < MAX_RAYS_PER_POINT)
    more_rays = over & ~vol_src & noisy
    rest = over & ~more_rays
    src_first = vol_src | ((source > receiver) & can_s)
    bigger_src = nodes.area[s] >= nodes.area[r]
    split_src = rest & can_s & (src_first | bigger_src | ~can_r)
    split_recv = rest & ~split_src & can_r
    # a link stuck on noise with neither end splittable still gets its rays
    stuck = over & ~(split_src | split_recv | more_rays) & (links.rays < MAX_RAYS_PER_POINT) & ~vol_src
    return Decision(split_src, split_recv, more_rays | stuck)


def refinement_threshold(errors: np.ndarray, budget: float) -> float:
    """The eps at which the links below it hold at most half the budget (W): refining the
    links above it brings the summed error towards the budget in one pass."""
    if not len(errors):
        return np.inf
    e = np.sort(errors[np.isfinite(errors)])
    below = np.cumsum(e)
    k = int(np.searchsorted(below, 0.5 * budget, side="right"))
    if k >= len(e):
        return float(e[-1]) if len(e) else np.inf
    # (errors that differ by float rounding alone fall on one side: many leaves share one
    # error floor (the sky over its samples where each sees all of it), and a threshold at that floor split
    # them by their last bits, an RGB solve one way and the same channels as bands another)
    return float(e[k - 1]) * (1.0 + SAME_ERROR) if k > 0 else float(e[0]) * 0.999
