"""Fused Dr.Jit waves: sample points, form-factor kernel, shadow rays, per-link reduction.

One call evaluates every link of a refinement wave. Element corners stay in
Dr.Jit arrays; each lane (link, sample k) gathers its receiver and source
corners, draws a stratified jittered point on each (hash-based random numbers,
so results depend only on the seed and the element ids), evaluates Lambert's
point-to-triangle form factor to the source, traces one shadow ray with
``mi.Scene.ray_test`` and the link's sums are reduced with ``dr.block_sum``.
Only per-link results come back to numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ._runtime import exact_arithmetic  # (and the LLVM set-up before mitsuba)
from .arrays import MAX_LANES, RAY_OFFSET, shadow_ray_length, to_float, to_uint, to_vector3
from .formfactor import point_to_triangle_dr

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

# RAY_OFFSET (fraction of the scene diagonal rays are lifted off surfaces) and MAX_LANES
# (lanes per Dr.Jit launch) have their one home in arrays.py


@dataclass
class Geometry:
    """Element geometry resident in Dr.Jit (float32), one entry per element.

    v0, v1, v2, normal : mi.Vector3f; curve_center, curve_axis : mi.Vector3f; curve_radius : mi.Float
    (curve_radius > 0: sample points are projected onto the true sphere/cylinder).
    """

    v0: object
    v1: object
    v2: object
    normal: object
    curve_center: object
    curve_axis: object
    curve_radius: object
    offset: float
    size: int

    @classmethod
    def upload(cls, verts, normal, curve_center, curve_axis, curve_radius, diagonal) -> "Geometry":
        return cls(to_vector3(verts[:, 0]), to_vector3(verts[:, 1]), to_vector3(verts[:, 2]), to_vector3(normal),
                   to_vector3(curve_center), to_vector3(curve_axis), to_float(curve_radius),
                   float(RAY_OFFSET * diagonal), len(verts))

    def gather(self, idx):
        """Corners, normal and curve data of elements idx (mi.UInt32)."""
        g = lambda arr: dr.gather(type(arr), arr, idx)  # noqa: E731
        return (g(self.v0), g(self.v1), g(self.v2), g(self.normal),
                g(self.curve_center), g(self.curve_axis), g(self.curve_radius))


# ------------------------------------------------------------------------------------------
# Random numbers and sampling
# ------------------------------------------------------------------------------------------

def hash_u32(x):
    """Integer hash (lowbias32) of a mi.UInt32 array."""
    x = x ^ (x >> 16)
    x = x * 0x7FEB352D
    x = x ^ (x >> 15)
    x = x * 0x846CA68B
    return x ^ (x >> 16)


def opaque_u32(value: int):
    """mi.UInt32 of a Python int (mod 2^32) that enters a kernel as a parameter, not as a
    literal: a seed, or a batch's offset. (As a literal each new value compiled its kernels
    anew: 30-100 ms each, eight of them a solve of the 36-triangle box for each new seed.)"""
    return dr.opaque(mi.UInt32, int(value) & 0xFFFFFFFF)


def to_unit(x):
    """mi.UInt32 hash -> mi.Float in [0, 1)."""
    return mi.Float(x >> 8) * (1.0 / (1 << 24))


def stratified(k, n: int, key):
    """Jittered point of stratum k (of n) in [0,1)^2: (u, v) mi.Float."""
    gx = int(math.ceil(math.sqrt(n)))
    gy = int(math.ceil(n / gx))
    ju = to_unit(hash_u32(key ^ 0x68E31DA4))
    jv = to_unit(hash_u32(key ^ 0xB5297A4D))
    u = (mi.Float(k % gx) + ju) * (1.0 / gx)
    v = (mi.Float(k // gx) + jv) * (1.0 / gy)
    return u, v


def _radical_inverse_2(k):
    """Van der Corput radical inverse in base 2 of a mi.UInt32, as mi.Float in [0, 1)."""
    k = ((k & 0x55555555) << 1) | ((k >> 1) & 0x55555555)
    k = ((k & 0x33333333) << 2) | ((k >> 2) & 0x33333333)
    k = ((k & 0x0F0F0F0F) << 4) | ((k >> 4) & 0x0F0F0F0F)
    k = ((k & 0x00FF00FF) << 8) | ((k >> 8) & 0x00FF00FF)
    k = (k << 16) | (k >> 16)
    return mi.Float(k >> 8) * (1.0 / (1 << 24))


def shifted_hammersley(k, n: int, key):
    """Point k of an n-point Hammersley set in [0,1)^2, shifted by a random offset per key.

    All points sharing a key (one element) get the same Cranley-Patterson shift, so the
    set keeps its low discrepancy: smooth integrands converge much faster than with
    jittered strata, and the estimate stays unbiased.
    """
    su = to_unit(hash_u32(key ^ 0x68E31DA4))
    sv = to_unit(hash_u32(key ^ 0xB5297A4D))
    u = (mi.Float(k) + 0.5) * (1.0 / n) + su
    v = _radical_inverse_2(k) + sv
    return u - dr.floor(u), v - dr.floor(v)


def triangle_point(v0, v1, v2, u, v):
    """Uniform point on a triangle from (u, v) in [0,1)^2 (square-root warp)."""
    su = dr.sqrt(u)
    return v0 * (1 - su) + v1 * (su * (1 - v)) + v2 * (su * v)


def project_to_surface(p, n, center, axis, radius):
    """Move points of tessellated spheres/cylinders onto the true surface; returns (p, n)."""
    d = p - center
    radial = d - axis * dr.dot(d, axis)
    rlen = dr.norm(radial)
    curved = (radius > 0) & (rlen > 0)
    direction = radial / dr.select(rlen > 0, rlen, 1.0)
    flip = dr.select(dr.dot(direction, n) < 0, -1.0, 1.0)  # back-side patches face inwards
    p_true = p + direction * (radius - rlen)
    return dr.select(curved, p_true, p), dr.select(curved, direction * flip, n)


def count_true(mask) -> int:
    """Number of set lanes of a mi.Bool."""
    return int(dr.count(mask)[0]) if dr.width(mask) else 0


def _coprime_step(n: int) -> int:
    for q in (5, 7, 11, 13, 3, 17, 19, 23):
        if math.gcd(q, n) == 1 and q < n:
            return q
    return 1


# ------------------------------------------------------------------------------------------
# The link wave
# ------------------------------------------------------------------------------------------

@dataclass
class LinkWave:
    """Per-link results of one wave (numpy, float32): see hierarchy.Links for the fields."""

    ff: np.ndarray
    ff_max: np.ndarray
    vis: np.ndarray
    ff_std: np.ndarray
    ff_range: np.ndarray
    ff_lo: np.ndarray
    rays: int

    FIELDS = ("ff", "ff_max", "vis", "ff_std", "ff_range", "ff_lo")


def evaluate_links(mi_scene, geo: Geometry, recv: np.ndarray, src: np.ndarray, *,
                   samples: int, seed: int, clusters=None, vclass: np.ndarray | None = None) -> LinkWave:
    """Form factor, visibility and kernel statistics of links recv <- src.

    Parameters
    ----------
    recv, src : (M,) int element ids
    samples : receiver points (and shadow rays) per link
    clusters : cluster.ClusterGeometry or None (sources with ids in its range are clusters)
    vclass : (M,) int8 or None, visibility classes (shaft.py): links proven visible or
        blocked trace no rays (v = 1 or 0 exactly)
    """
    if vclass is None:
        vclass = np.zeros(len(recv), np.int8)
    element = lambda r, s, c: _link_kernel(mi_scene, geo, r, s, c, samples, seed)  # noqa: E731
    if clusters is not None:
        is_cluster = (src >= clusters.first) & (src < clusters.first + clusters.count)
        if is_cluster.any():
            parts = [np.flatnonzero(~is_cluster), np.flatnonzero(is_cluster)]
            waves = [_in_launches(element, recv[parts[0]], src[parts[0]], vclass[parts[0]], samples),
                     _in_launches(lambda r, s, c: _cluster_kernel(mi_scene, geo, clusters, r, s, samples, seed),
                                  recv[parts[1]], src[parts[1]], vclass[parts[1]], samples)]
            out = [np.zeros(len(recv), np.float32) for _ in LinkWave.FIELDS]
            for part, wave in zip(parts, waves):
                for o, name in zip(out, LinkWave.FIELDS):
                    o[part] = getattr(wave, name)
            return LinkWave(*out, waves[0].rays + waves[1].rays)
    return _in_launches(element, recv, src, vclass, samples)


def _in_launches(kernel, recv, src, vclass, samples: int) -> LinkWave:
    """Run kernel(recv, src, vclass) -> (ff, ff_max, vis, ff_std, ff_range, ff_lo, rays) in
    launches of at most MAX_LANES lanes and gather the per-link results."""
    m = len(recv)
    out = [np.zeros(m, np.float64) for _ in LinkWave.FIELDS]
    rays = 0
    per_launch = max(1, MAX_LANES // samples)
    # (without fast math wherever it is called: a worker's wave is bitwise the in-process one)
    with exact_arithmetic():
        for start in range(0, m, per_launch):
            stop = min(m, start + per_launch)
            res = kernel(recv[start:stop], src[start:stop], vclass[start:stop])
            for o, r in zip(out, res[:-1]):
                o[start:stop] = r
            rays += res[-1]
    return LinkWave(*(o.astype(np.float32) for o in out), rays)


def _link_kernel(mi_scene, geo: Geometry, recv, src, vclass, n: int, seed: int):
    m = len(recv)
    recv_dr, src_dr, class_dr = to_uint(recv), to_uint(src), to_uint(vclass)
    lane = dr.arange(mi.UInt32, m * n)
    link = lane // n
    k = lane % n
    r = dr.gather(mi.UInt32, recv_dr, link)
    s = dr.gather(mi.UInt32, src_dr, link)
    cls = dr.gather(mi.UInt32, class_dr, link)

    # --- stratified jittered sample points on receiver and source -----------------------
    pair_key = hash_u32(hash_u32(r ^ hash_u32(opaque_u32(seed) + 0x9E3779B9)) + s)
    lane_key = hash_u32(pair_key + k * 0x632BE5AB)
    rv0, rv1, rv2, rn, rc, ra, rr = geo.gather(r)
    sv0, sv1, sv2, sn, sc, sa, sr = geo.gather(s)
    # receiver points depend on the receiver only (not the source), so all links of a
    # receiver share them and its row sum is a mean of point row sums, each <= 1
    recv_key = hash_u32(r ^ hash_u32(opaque_u32(seed) + 0x7F4A7C15))
    ur, vr = shifted_hammersley(k, n, recv_key)
    k_src = (k * _coprime_step(n) + 3) % n
    us, vs = stratified(k_src, n, hash_u32(lane_key ^ 0x1B873593))
    x = triangle_point(rv0, rv1, rv2, ur, vr)
    y = triangle_point(sv0, sv1, sv2, us, vs)

    # --- unoccluded kernel: Lambert's form factor from x to the whole source triangle ---
    # (a point in, or within rounding of, the source's plane sees nothing of it: Lambert's
    # formula is meaningless there, and coplanar pairs exchange exactly nothing)
    in_plane = 0.1 * geo.offset
    front = dr.dot(sn, x - sv0) > in_plane
    g = dr.select(front, point_to_triangle_dr(x, rn, sv0, sv1, sv2), 0.0)
    # the first three lanes also probe the receiver's (slightly inset) corners: random
    # samples rarely land there, yet corners next to other surfaces are where a coarse
    # link's constant value is most wrong
    corner = dr.select(k == 0, rv0 * 0.9 + (rv1 + rv2) * 0.05,
                       dr.select(k == 1, rv1 * 0.9 + (rv0 + rv2) * 0.05, rv2 * 0.9 + (rv0 + rv1) * 0.05))
    corner = dr.select(k < 3, corner, x)
    g_corner = dr.select(dr.dot(sn, corner - sv0) > in_plane, point_to_triangle_dr(corner, rn, sv0, sv1, sv2), 0.0)

    # --- one shadow ray per lane, only where the kernel is non-zero and the link's --------
    # visibility is not already proven (shaft.py: 1 visible, 2 blocked)
    xs, xn = project_to_surface(x, rn, rc, ra, rr)
    ys, yn = project_to_surface(y, sn, sc, sa, sr)
    o = xs + xn * geo.offset
    target = ys + yn * geo.offset
    d = target - o
    dist = dr.norm(d)
    active = (g > 0) & (dist > 0) & (dr.dot(d, rn) > 0) & (dr.dot(d, sn) < 0)
    ray = mi.Ray3f(o, d / dr.select(dist > 0, dist, 1.0))
    ray.maxt = shadow_ray_length(dist, geo.offset)
    traced = active & (cls == 0)
    blocked = mi_scene.ray_test(ray, traced) | (cls == 2)
    v = dr.select(active & ~blocked, 1.0, 0.0)
    gv = g * v

    # --- per-link reduction --------------------------------------------------------------
    # F = mean_k G(x_k) * V_K, with V_K the kernel-weighted visible fraction of the sample
    # pairs: sum K(x_k, y_k) v_k / sum K(x_k, y_k). Weighting the rays by the point-to-point
    # kernel keeps grazing (nearly irrelevant) blocked rays from darkening the link.
    kernel = dr.select(active, dr.dot(d, rn) * -dr.dot(d, sn) / dr.square(dr.square(dist)), 0.0)
    lanes = [g, kernel, kernel * v, gv, gv * gv, dr.maximum(g, g_corner), dr.minimum(g, g_corner),
             dr.select(traced, 1.0, 0.0)]
    # One kernel computes every per-lane quantity; the block reductions then read stored
    # arrays. (Reducing unevaluated expressions would re-run the whole wave, shadow rays
    # included, once per reduction.)
    dr.eval(*lanes)
    g_sum, k_sum, kv_sum, gv_sum, sq_sum = (dr.block_sum(x, n) for x in lanes[:5])
    ff_max = dr.block_reduce(dr.ReduceOp.Max, g, n)
    g_hi = dr.block_reduce(dr.ReduceOp.Max, lanes[5], n)
    g_lo = dr.block_reduce(dr.ReduceOp.Min, lanes[6], n)
    n_traced = dr.sum(lanes[7])
    dr.eval(g_sum, k_sum, kv_sum, gv_sum, sq_sum, ff_max, g_hi, g_lo, n_traced)
    inv_n = 1.0 / n
    ks = k_sum.numpy().astype(np.float64)
    # a link without a single valid sample pair (all across a plane) carries nothing
    vis_np = np.where(ks > 0, kv_sum.numpy() / np.where(ks > 0, ks, 1.0), 0.0)
    ff_np = g_sum.numpy().astype(np.float64) * inv_n * vis_np
    gvm = gv_sum.numpy().astype(np.float64) * inv_n
    var = np.maximum(sq_sum.numpy().astype(np.float64) * inv_n - gvm * gvm, 0.0)
    ff_range = (g_hi.numpy() - g_lo.numpy()).astype(np.float64)
    return (ff_np, ff_max.numpy(), vis_np, np.sqrt(var), ff_range, g_lo.numpy(),
            int(round(float(n_traced[0]))))


def cluster_link_entries(mi_scene, geo: Geometry, clusters, recv, src, *, samples: int,
                         seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Matrix entries of cluster links: (rows = receivers, columns = sampled patches, weights).

    Each link recv <- cluster spreads its form factor over the patches its samples drew,
    weight g v / n each (the same samples as ``evaluate_links`` with the same seed), so the
    transfer uses the radiosity of the patches it actually sees rather than the cluster's
    mean: a downward-facing light inside a cluster adds nothing to the ceiling.
    """
    rows, cols, vals = [], [], []
    per_launch = max(1, MAX_LANES // samples)
    for start in range(0, len(recv), per_launch):
        stop = min(len(recv), start + per_launch)
        patch, weight = _cluster_kernel(mi_scene, geo, clusters, recv[start:stop], src[start:stop],
                                        samples, seed, lanes_out=True)
        keep = weight > 0
        rows.append(np.repeat(recv[start:stop], samples)[keep])
        cols.append(patch[keep])
        vals.append(weight[keep])
    if not rows:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    return np.concatenate(rows), np.concatenate(cols).astype(np.int64), np.concatenate(vals).astype(np.float64)


def _cluster_kernel(mi_scene, geo: Geometry, clusters, recv, src, n: int, seed: int, lanes_out: bool = False):
    """Links receiver element <- cluster: Monte Carlo over point pairs (see cluster.py)."""
    m = len(recv)
    recv_dr, cl_dr = to_uint(recv), to_uint(src - clusters.first)
    lane = dr.arange(mi.UInt32, m * n)
    link = lane // n
    k = lane % n
    r = dr.gather(mi.UInt32, recv_dr, link)
    c = dr.gather(mi.UInt32, cl_dr, link)

    # --- receiver points exactly as for element sources; source points by area ----------
    rv0, rv1, rv2, rn, rc, ra, rr = geo.gather(r)
    recv_key = hash_u32(r ^ hash_u32(opaque_u32(seed) + 0x7F4A7C15))
    ur, vr = shifted_hammersley(k, n, recv_key)
    x = triangle_point(rv0, rv1, rv2, ur, vr)
    lane_key = hash_u32(hash_u32(recv_key + c * 0x9E3779B9) + k * 0x632BE5AB)
    us, vs = stratified((k * _coprime_step(n) + 3) % n, n, hash_u32(lane_key ^ 0x1B873593))
    patch = clusters.sample_patch(c, to_unit(hash_u32(lane_key ^ 0x2C1B3C6D)))
    sv0, sv1, sv2, sn, sc, sa, sr = geo.gather(patch)
    y = triangle_point(sv0, sv1, sv2, us, vs)
    a_patch = dr.norm(dr.cross(sv1 - sv0, sv2 - sv0)) * 0.5
    a_cluster = dr.gather(mi.Float, clusters.area, c)

    # --- per pair: disc estimate of the drawn patch / its selection probability ----------
    xs, xn = project_to_surface(x, rn, rc, ra, rr)
    ys, yn = project_to_surface(y, sn, sc, sa, sr)
    o = xs + xn * geo.offset
    d = ys + yn * geo.offset - o
    dist2 = dr.squared_norm(d)
    dist = dr.sqrt(dist2)
    cos_x = dr.dot(d, rn) / dr.select(dist > 0, dist, 1.0)
    cos_y = -dr.dot(d, sn) / dr.select(dist > 0, dist, 1.0)
    # Lambert's form factor to the drawn patch over the probability of drawing it (its area
    # share): unbiased for the cluster's form factor, and bounded however close the patch is
    front = dr.dot(sn, x - sv0) > 0.1 * geo.offset
    f_patch = dr.select(front, point_to_triangle_dr(x, rn, sv0, sv1, sv2), 0.0)
    active = (dist > 0) & (cos_x > 0) & (cos_y > 0) & (f_patch > 0)
    g = dr.select(active, f_patch * a_cluster / dr.maximum(a_patch, 1e-30), 0.0)
    ray = mi.Ray3f(o, d / dr.select(dist > 0, dist, 1.0))
    ray.maxt = shadow_ray_length(dist, geo.offset)
    blocked = mi_scene.ray_test(ray, active)
    v = dr.select(active & ~blocked, 1.0, 0.0)
    gv = g * v
    if lanes_out:
        dr.eval(patch, gv)
        return patch.numpy(), gv.numpy() * (1.0 / n)
    lanes = [g, gv, gv * gv, dr.select(active, 1.0, 0.0)]
    dr.eval(*lanes)
    g_sum, gv_sum, sq_sum = (dr.block_sum(x_, n) for x_ in lanes[:3])
    g_max = dr.block_reduce(dr.ReduceOp.Max, g, n)
    g_min = dr.block_reduce(dr.ReduceOp.Min, g, n)
    traced = dr.sum(lanes[3])
    dr.eval(g_sum, gv_sum, sq_sum, g_max, g_min, traced)
    inv_n = 1.0 / n
    gs = g_sum.numpy().astype(np.float64)
    gvs = gv_sum.numpy().astype(np.float64)
    ff = gvs * inv_n
    vis = np.where(gs > 0, gvs / np.where(gs > 0, gs, 1.0), 1.0)
    var = np.maximum(sq_sum.numpy().astype(np.float64) * inv_n - ff * ff, 0.0)
    ff_range = (g_max.numpy() - g_min.numpy()).astype(np.float64)
    return ff, g_max.numpy(), vis, np.sqrt(var), ff_range, g_min.numpy(), int(round(float(traced[0])))


# ------------------------------------------------------------------------------------------
# Point gathers: irradiance at arbitrary points from the solution's leaves
# ------------------------------------------------------------------------------------------

def gather_at_points(mi_scene, points: np.ndarray, normals: np.ndarray, geo: Geometry,
                     radiosity: np.ndarray, *, rays: int, seed: int, progress=None, with_error: bool = False):
    """Irradiance (P, C), W/m^2, at points (P, 3) with normals (P, 3) from every leaf.

    H(x) = sum_l B_l * F(dA_x -> leaf l) * v(x, l), with Lambert's analytic form factor
    (clipped to x's tangent half-space) and v the visible fraction of ``rays`` stratified
    shadow rays from x to leaf l, as the link kernel weighs it: over the rays to points of
    the leaf in front of x (the part the clipped form factor counts), each weighted by its
    point-to-point kernel. A leaf straddling x's tangent plane (a ceiling light seen from a
    box's side) so keeps its visible part once: its rays into the surface under x are
    blocked, and counting them again darkened such leaves by the share behind the horizon.
    A leaf whose rays all point behind x's plane gives nothing. A point in, or within
    rounding of, a leaf's plane sees nothing of it (float32 rounding used to put a probe on
    a tilted face in front of its own leaf, where Lambert's formula gives 1).
    ``geo`` holds the leaves only; ``radiosity`` is (L, C). ``progress``, if given, is called
    with the number of points finished after every launch (it does not change the result).

    With ``with_error``, returns (H, standard error of H (P, C), W/m^2): the visibility noise
    sqrt(sum_l (B_l F_l)^2 v_l (1 - v_l) / (rays - 1)), the binomial variance of each leaf's
    visible fraction estimated without bias from its ``rays`` rays (an upper bound for the
    stratified rays traced); zero where no leaf is partly visible, and zero when ``rays`` is 1
    (one ray cannot tell its own noise). H is bitwise the same either way.
    """
    n_pts, n_leaf = len(points), geo.size
    channels = radiosity.shape[1]
    b_dr = [to_float(radiosity[:, c]) for c in range(channels)]
    pts_per_launch = max(1, MAX_LANES // max(1, n_leaf * rays))
    out = np.zeros((n_pts, channels))
    err = np.zeros((n_pts, channels)) if with_error else None
    in_plane = 0.1 * geo.offset
    for start in range(0, n_pts, pts_per_launch):
        stop = min(n_pts, start + pts_per_launch)
        m = stop - start
        p_dr, n_dr = to_vector3(points[start:stop]), to_vector3(normals[start:stop])
        lane = dr.arange(mi.UInt32, m * n_leaf * rays)
        k = lane % rays
        pair = lane // rays
        leaf = pair % n_leaf
        pidx = pair // n_leaf
        x = dr.gather(mi.Vector3f, p_dr, pidx)
        nx = dr.gather(mi.Vector3f, n_dr, pidx)
        sv0, sv1, sv2, sn, sc, sa, sr = geo.gather(leaf)
        key = hash_u32(hash_u32(pidx + opaque_u32(start) + hash_u32(opaque_u32(seed))) + leaf * 0x632BE5AB + k)
        # (as in the link kernel: within rounding of a leaf's plane, nothing of it is seen)
        front = dr.dot(sn, x - sv0) > in_plane
        g = dr.select(front, point_to_triangle_dr(x, nx, sv0, sv1, sv2), 0.0)
        us, vs = stratified(k, rays, key)
        y = triangle_point(sv0, sv1, sv2, us, vs)
        ys, yn = project_to_surface(y, sn, sc, sa, sr)
        o = x + nx * geo.offset
        d = ys + yn * geo.offset - o
        dist = dr.norm(d)
        # only rays to the leaf's points in front of x (and reaching the leaf's front) sample
        # the part of it the clipped form factor counts
        active = (g > 0) & (dist > 0) & (dr.dot(d, nx) > 0) & (dr.dot(d, sn) < 0)
        ray = mi.Ray3f(o, d / dr.select(dist > 0, dist, 1.0))
        ray.maxt = shadow_ray_length(dist, geo.offset)
        blocked = mi_scene.ray_test(ray, active)
        seen = active & ~blocked
        kernel = dr.select(active, dr.dot(d, nx) * -dr.dot(d, sn) / dr.square(dr.square(dist)), 0.0)
        lanes = [kernel, dr.select(seen, kernel, 0.0)]
        dr.eval(*lanes)           # one launch of the rays, then block sums over stored arrays
        k_sum, kv_sum = dr.block_sum(lanes[0], rays), dr.block_sum(lanes[1], rays)
        # per (point, leaf) pair: the kernel-weighted visible fraction and the (clipped) form factor
        v = dr.select(k_sum > 0, kv_sum / dr.select(k_sum > 0, k_sum, 1.0), 0.0)
        first = dr.arange(mi.UInt32, m * n_leaf) * rays
        g_pair = dr.gather(mi.Float, g, first)
        gv = g_pair * v
        leaf_pair = dr.arange(mi.UInt32, m * n_leaf) % n_leaf
        dr.eval(gv)
        for c in range(channels):
            h = dr.block_sum(gv * dr.gather(mi.Float, b_dr[c], leaf_pair), n_leaf)
            out[start:stop, c] = h.numpy()
        if with_error and rays > 1:
            spread = g_pair * g_pair * v * (1.0 - v) * (1.0 / (rays - 1))
            dr.eval(spread)
            for c in range(channels):
                b = dr.gather(mi.Float, b_dr[c], leaf_pair)
                var = dr.block_sum(spread * b * b, n_leaf)
                err[start:stop, c] = np.sqrt(np.maximum(np.asarray(var.numpy(), np.float64), 0.0))
        if progress is not None:
            progress(m)
    return (out, err) if with_error else out
