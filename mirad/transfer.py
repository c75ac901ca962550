"""Link transfers of the hierarchical core as one fused Dr.Jit wave per call.

A link r <- s is evaluated at the receiver's fixed quadrature points x_i (nodes.py):

* planar sources (triangles, face clusters): the exact unoccluded point-to-polygon form
  factor G_i = F(dA_{x_i} -> polygon of s) * fill_s (Lambert's formula, clipped to x_i's
  tangent half-space; exact for triangles and rectangular clusters);
* volume clusters: a Monte Carlo estimate over the rays' target points, each the exact
  form factor of the triangle the point is on over the probability of drawing that triangle
  (A_triangle / A_s): unbiased, and bounded by A_s / A_triangle where a point-to-point
  kernel is not.

Visibility is only sampled: R shadow rays from each x_i to the link's own stratified points
on the source (``source_point``, ``mi.Scene.ray_test``); v_i is the kernel-weighted fraction of them that arrive. A link's
transfer is F = sum_i w_i G_i v_i. The wave returns per-point arrays (M, K) to numpy,
where refine.py turns them into errors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np

from ._runtime import exact_arithmetic  # (and the LLVM set-up before mitsuba)
from .nodes import (FACE, PLACE_SCALE, PLANE_NORMAL_TOL, RECEIVER_POINTS, SOURCE_POINTS, TRIANGLE, VOLUME, Nodes,
                    cluster_children, flat_nodes)
from .arrays import MAX_LANES, shadow_ray_length, to_bool, to_float, to_uint, to_vector3
from .visibility import hash_u32, opaque_u32, shifted_hammersley, to_unit, triangle_point

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

_TINY = 1e-30
#: Rays over a point's hemisphere that must all meet the back of a one-sided surface, beside
#: its ray along the normal, for the point to count as buried (``_buried``): cosine-weighted
#: and stratified, the most grazing at asin(sqrt(1 / (2 K))) (14.5 degrees for K = 8), so a
#: point whose hemisphere is open in less than about 1 / (2 K) of its cosine-weighted
#: measure, and which so gets less than that share of the light around it, is taken as enclosed.
BURIED_DIRECTIONS = 8


@dataclass
class NodeArrays:
    """The node arrays a wave reads, all resident in Dr.Jit (float32): a PyTree that a frozen
    wave (``_wave``) takes whole, its widths free to change between calls."""

    poly: tuple          # four mi.Vector3f (N,)
    normal: object       # mi.Vector3f (N,)
    fill: object         # mi.Float (N,)
    area: object         # mi.Float (N,)
    kind: object         # mi.UInt32 (N,)
    recv_pts: object     # mi.Vector3f (N * K,)
    recv_nrm: object
    child: tuple         # two mi.UInt32 (N,): a cluster's children (a triangle: itself)
    curve: tuple         # centre, axis (mi.Vector3f) and radius (mi.Float) of a triangle's true surface
    sphere: tuple        # bounding-sphere centre (mi.Vector3f) and radius (mi.Float)
    flat: object         # mi.Bool (N,): a triangle or face cluster all of whose points lie in its plane

    def arrays(self) -> "NodeArrays":
        """The Dr.Jit arrays alone (what a frozen wave may take: no Python values in it)."""
        return NodeArrays(**{f.name: getattr(self, f.name) for f in fields(NodeArrays)})


@dataclass
class NodeBuffers(NodeArrays):
    """Node arrays resident in Dr.Jit, uploaded once per change of the node count, with their
    count and which nodes are volume clusters (numpy)."""

    size: int = 0
    volume: np.ndarray | None = None   # (N,) bool: volume clusters (which waves draw below one, ``evaluate``)

    @classmethod
    def upload(cls, nodes: Nodes) -> "NodeBuffers":
        def points(a):          # (N, ...) -> every point's (x, y, z), node-major
            return to_vector3(np.asarray(a).reshape(-1, 3))

        child = cluster_children(nodes.kind, nodes.children)
        curve = np.asarray(nodes.curve)
        return cls(poly=tuple(points(nodes.poly[:, k]) for k in range(4)), normal=points(nodes.normal),
                   fill=to_float(nodes.fill), area=to_float(nodes.area), kind=to_uint(nodes.kind),
                   recv_pts=points(nodes.recv_pts), recv_nrm=points(nodes.recv_nrm),
                   child=(to_uint(child[:, 0]), to_uint(child[:, 1])),
                   curve=(points(curve[:, :3]), points(curve[:, 3:6]), to_float(curve[:, 6])),
                   sphere=(points(nodes.center), to_float(nodes.radius)), flat=to_bool(flat_nodes(nodes)),
                   size=len(nodes), volume=np.asarray(nodes.kind) == VOLUME)


@dataclass
class PointTransfers:
    """Per receiver point results of a wave (numpy): arrays (M, K)."""

    g: np.ndarray        # unoccluded form factor at the point
    gv: np.ndarray       # times the link's visibility fraction
    gv_point: np.ndarray  # times the point's own visibility fraction (for the spread)
    gv_square: np.ndarray  # volume-cluster sources: mean over the point's rays of the squared
    #                        sampled transfer (its sampling variance); 0 for planar sources
    rays: int            # shadow rays traced
    #: with ``evaluate(..., samples=True)``: the arriving samples of volume-cluster sources
    #: (link (S,), point (S,), triangle node (S,), sampled transfer (S,), place on the triangle
    #: (S,); ``_arriving``): a link's transfer is sum_i w_i gv_i with gv_i the mean of point
    #: i's R samples, so its samples over R split it by the triangle each came from
    #: (``source_point``). And those of face clusters some of whose rays were blocked: each its
    #: point's exact form factor times its ray's kernel, shares of the link's transfer that are
    #: not normed to it
    samples: tuple | None = None


def _edge_term(a, b, n):
    c = dr.cross(a, b)
    cn = dr.norm(c)
    return dr.atan2(cn, dr.dot(a, b)) * dr.dot(n, c) / dr.maximum(cn, _TINY)


def point_to_polygon_dr(x, n, corners):
    """Unoccluded form factor dA(x, n) -> convex polygon ``corners`` (list of mi.Vector3f,
    a repeated corner allowed), clipped to n.(y - x) >= 0; mi.Float in [0, 1]."""
    r = [c - x for c in corners]
    d = [dr.dot(n, ri) for ri in r]
    inside = [di >= 0 for di in d]
    width = dr.width(d[0])
    total = dr.zeros(mi.Float, width)
    exit_pt = dr.zeros(mi.Vector3f, width)
    entry_pt = dr.zeros(mi.Vector3f, width)
    crossing = dr.zeros(mi.Bool, width)
    k = len(r)
    for i in range(k):
        j = (i + 1) % k
        denom = d[i] - d[j]
        t = dr.select(dr.abs(denom) > 0, d[i] / dr.select(denom == 0, 1.0, denom), 0.0)
        p = dr.fma(r[j] - r[i], t, r[i])
        start = dr.select(inside[i], r[i], p)
        end = dr.select(inside[j], r[j], p)
        total += dr.select(inside[i] | inside[j], _edge_term(start, end, n), 0.0)
        leaving = inside[i] & ~inside[j]
        exit_pt = dr.select(leaving, p, exit_pt)
        entry_pt = dr.select(~inside[i] & inside[j], p, entry_pt)
        crossing |= leaving
    total += dr.select(crossing, _edge_term(exit_pt, entry_pt, n), 0.0)
    return dr.minimum(dr.abs(total) * (0.5 / dr.pi), 1.0)


def evaluate(mi_scene, buf: NodeBuffers, recv: np.ndarray, src: np.ndarray, *, rays_per_point: int,
             seed: int, offset: float, periodic=None, samples: bool = False, spread: bool = False) -> PointTransfers:
    """Transfers of links recv <- src (M,) at the receivers' K points, R = rays_per_point
    shadow rays each; ``offset`` lifts ray ends off surfaces (metres). ``periodic``: a
    ``periodic.PeriodicBox`` (the link then sums the source's nearest lattice images, with
    wrapped shadow rays; ``periodic.image_visibility``), or None. With ``samples``, also the
    volume clusters' arriving samples and the partly hidden face clusters' shares
    (``PointTransfers.samples``). With ``spread``, each of a link's K R rays aims at a point of
    its own on the source (``ray_target``)."""
    m = len(recv)
    k = RECEIVER_POINTS
    g, gv, gp, g2 = (np.zeros((m, k), np.float32) for _ in range(4))
    rays = 0
    frozen = FREEZE_WAVES and periodic is None
    per_launch = max(1, (FROZEN_LANES if frozen else MAX_LANES) // (k * rays_per_point))
    found = []
    # (the links from volume clusters last, in launches of their own where they fill one: only
    # theirs weigh the face clusters they descend to, ``source_point``; a link's lanes depend on
    # the link, not on where it is in the wave)
    volume = buf.volume[src]
    order = np.argsort(volume, kind="stable") if volume.any() and not volume.all() else None
    if order is not None:
        recv, src, volume = recv[order], src[order], volume[order]
    arrays = buf.arrays()
    seed_dr = opaque_u32(seed)
    # (without fast math wherever it is called: a worker's wave is bitwise the in-process one)
    with exact_arithmetic():
        for a in range(0, m, per_launch):
            b = min(m, a + per_launch)
            weigh = WEIGH_FACES_IN_VOLUMES and bool(volume[a:b].any())
            point_lane = dr.arange(mi.UInt32, (b - a) * k)
            ray_lane = point_lane if rays_per_point == 1 else dr.arange(mi.UInt32, (b - a) * k * rays_per_point)
            # (nor a single link: its per-link sums are of width 1, which a recording takes for a
            # scalar, and a replay over more links would then broadcast the first link's)
            out = _wave(mi_scene, arrays, to_uint(recv[a:b]), to_uint(src[a:b]), ray_lane, point_lane, seed_dr,
                        rays_per_point, offset, periodic, weigh, spread, samples, frozen and b - a > 1)
            g[a:b], gv[a:b], gp[a:b], g2[a:b] = (np.asarray(x.numpy(), np.float32).reshape(b - a, k) for x in out[:4])
            rays += int(round(float(out[4][0])))
            if samples:
                found.append(_arriving(*out[5:], k, rays_per_point, a))
    arrived = join_samples(found) if samples else None
    if order is not None:
        # (each row back to its pair's place: row i of the wave is pair order[i])
        back = np.empty_like(order)
        back[order] = np.arange(len(order))
        g, gv, gp, g2 = (np.take(per_point, back, axis=0) for per_point in (g, gv, gp, g2))
        if samples:
            arrived = (order[arrived[0]],) + arrived[1:]
    return PointTransfers(g, gv, gp, g2, rays, arrived)


def _arriving(value, tri, place, k: int, r_count: int, first: int):
    """The lanes whose volume-cluster sample ``value`` (mi.Float, evaluated, with the triangle
    node ``tri`` it is on and its ``place`` there) arrived, as numpy: (link (S,) int64, counted
    from ``first``; point (S,) uint8; triangle node (S,) int32; sampled transfer (S,) float32;
    place (S,) uint32, ``pack_place``)."""
    lane = dr.compress(value > 0)
    tri, place = dr.gather(mi.UInt32, tri, lane), dr.gather(mi.UInt32, place, lane)
    value = dr.gather(mi.Float, value, lane)
    dr.eval(lane, tri, value, place)
    lane = np.asarray(lane.numpy(), np.int64)
    # (compact: a large canopy's gather keeps millions of them)
    return (lane // (k * r_count) + first, ((lane // r_count) % k).astype(np.uint8), np.asarray(tri.numpy(), np.int32),
            np.asarray(value.numpy(), np.float32), np.asarray(place.numpy(), np.uint32))


def join_samples(found: list) -> tuple:
    """Parts of the arriving samples (``_arriving``'s, ``PointTransfers.samples``) concatenated,
    column by column (empty arrays for none)."""
    if not found:
        return (np.zeros(0, np.int64), np.zeros(0, np.uint8), np.zeros(0, np.int32), np.zeros(0, np.float32),
                np.zeros(0, np.uint32))
    return tuple(np.concatenate(c) for c in zip(*found))


def reverse_form_factor(buf: NodeBuffers, recv: np.ndarray, src: np.ndarray, offset: float) -> np.ndarray:
    """(M, K) exact unoccluded form factors from the K points of sources src (M,) (their
    receiver points, ``nodes.recv_pts``) to the polygons of receivers recv (M,) (scaled by
    the receiver's fill): the transfer integrated over the source's side, where a source
    much smaller than its receiver is resolved by its own points. Planar sources only."""
    m, k = len(recv), RECEIVER_POINTS
    if m == 0:
        return np.zeros((0, k))
    # (recorded and replayed as the waves are, but for a single link, whose width-1 inputs a
    # recording may take for scalars)
    values = _frozen_reverse if FREEZE_WAVES and m > 1 else _reverse_values
    value = values(buf.arrays(), to_uint(recv), to_uint(src), dr.arange(mi.UInt32, m * k), offset)
    dr.eval(value)
    return np.asarray(value.numpy(), np.float64).reshape(m, k)


def _reverse_values(buf: NodeArrays, recv, src, lane, offset: float):
    """``reverse_form_factor``'s values (mi.Float, M K) of links recv <- src (mi.UInt32 (M,)),
    ``lane`` an arange over their M K points."""
    k = RECEIVER_POINTS
    r = dr.gather(mi.UInt32, recv, lane // k)
    s = dr.gather(mi.UInt32, src, lane // k)
    y = dr.gather(mi.Vector3f, buf.recv_pts, s * k + lane % k)
    ny = dr.gather(mi.Vector3f, buf.recv_nrm, s * k + lane % k)
    corners = [dr.gather(mi.Vector3f, c, r) for c in buf.poly]
    return _point_form_factor(buf, y, ny, corners, dr.gather(mi.Vector3f, buf.normal, r), True, r, offset)


def _point_form_factor(buf: NodeArrays, x, nx, corners, ns, planar, s, offset: float):
    """Exact unoccluded form factor from points x (normals nx) to planar sources s (their
    polygon ``corners`` and normal ``ns``), scaled by the source's fill; 0 for volume
    clusters and for points in (or within rounding of) the source's plane or behind it."""
    front = dr.dot(ns, x - corners[0]) > 0.1 * offset
    return dr.select(planar & front, point_to_polygon_dr(x, nx, corners) * dr.gather(mi.Float, buf.fill, s), 0.0)


class Lanes(NamedTuple):
    """A wave's lanes, one per shadow ray (``_lanes``), in Dr.Jit."""

    g_exact: object      # mi.Float: a planar source's exact unoccluded form factor at the ray's point
    kernel: object       # mi.Float: the point-to-point kernel cos cos / r^2 to the ray's target
    g_volume: object     # mi.Float: a volume cluster's sampled transfer (``volume_sample``), else 0
    traced: object       # mi.Bool: a ray was traced
    v: object            # mi.Float: 1 where it arrived
    tri: object          # mi.UInt32: the triangle node the target is on
    g_weighted: object   # mi.Float: g_volume times its point's kernel over its triangle's mean kernel
    g_share: object      # mi.Float: a face cluster's g_exact times the ray's kernel (its share, before norming), else 0
    place: object        # mi.UInt32: where on that triangle the target is (``source_point``)


class Aimed(NamedTuple):
    """A wave's lanes with their shadow rays aimed, not yet traced (``_aim``), in Dr.Jit."""

    g_exact: object      # as Lanes'
    kernel: object
    g_volume: object
    traced: object       # mi.Bool: a ray is traced
    tri: object
    origin: object       # mi.Vector3f: the ray's origin, lifted off the receiver
    direction: object    # mi.Vector3f: unit direction
    length: object       # mi.Float: how far it goes (short of the lifted target)
    g_weighted: object   # as Lanes'
    g_share: object      # as Lanes'
    place: object        # as Lanes'


def _lanes(mi_scene, buf: NodeArrays, recv_dr, src_dr, lane, point_lane, r_count: int, seed, offset: float,
           periodic=None, weigh_faces: bool = False, spread: bool = False) -> Lanes:
    """One lane per shadow ray of links recv_dr <- src_dr (mi.UInt32 (M,)), R = r_count rays at
    each of the receivers' K points: ``lane`` = (link K + point) R + ray, 0 .. M K R - 1 (the
    lanes passed in, so that a frozen wave's sizes follow its inputs), ``point_lane`` = 0 ..
    M K - 1; ``seed`` a mi.UInt32. ``weigh_faces``: as ``source_point``'s; ``spread``: as
    ``ray_target``'s. The rays are aimed (``_aim``) and traced (``_shoot``); a periodic
    scene's are traced as they are aimed (``periodic.image_visibility``)."""
    aimed = _aim(mi_scene, buf, recv_dr, src_dr, lane, point_lane, r_count, seed, offset, periodic,
                 weigh_faces=weigh_faces, spread=spread)
    return aimed if isinstance(aimed, Lanes) else _shoot(mi_scene, aimed)


def _aim(mi_scene, buf: NodeArrays, recv_dr, src_dr, lane, point_lane, r_count: int, seed, offset: float,
         periodic=None, weigh_faces: bool = False, spread: bool = False) -> Aimed | Lanes:
    """``_lanes`` up to the shadow rays: their aim (``mi_scene`` is only used where ``periodic``
    is given, whose wrapped rays are then traced too: Lanes)."""
    k = RECEIVER_POINTS
    per_link = k * r_count
    link = lane // per_link
    i = (lane // r_count) % k
    j = lane % r_count
    r = dr.gather(mi.UInt32, recv_dr, link)
    s = dr.gather(mi.UInt32, src_dr, link)

    # --- receiver point and the source's geometry ----------------------------------------
    x = dr.gather(mi.Vector3f, buf.recv_pts, r * k + i)
    nx = dr.gather(mi.Vector3f, buf.recv_nrm, r * k + i)
    corners = [dr.gather(mi.Vector3f, c, s) for c in buf.poly]
    ns = dr.gather(mi.Vector3f, buf.normal, s)
    kind = dr.gather(mi.UInt32, buf.kind, s)
    planar = kind != VOLUME
    area_s = dr.gather(mi.Float, buf.area, s)
    form_factor = _point_form_factor
    if periodic is not None:     # the sum over the source's lattice images (periodic.py)
        from .periodic import image_form_factor
        form_factor = image_form_factor(periodic, _point_form_factor)
    if r_count == 1:
        g_exact = form_factor(buf, x, nx, corners, ns, planar, s, offset)
    else:
        # the form factor depends on the point, not the ray: once per point (M K lanes),
        # then shared by the point's R rays
        p_lane = point_lane
        p_r = dr.gather(mi.UInt32, recv_dr, p_lane // k)
        p_s = dr.gather(mi.UInt32, src_dr, p_lane // k)
        p_x = dr.gather(mi.Vector3f, buf.recv_pts, p_r * k + p_lane % k)
        p_n = dr.gather(mi.Vector3f, buf.recv_nrm, p_r * k + p_lane % k)
        p_corners = [dr.gather(mi.Vector3f, c, p_s) for c in buf.poly]
        p_planar = dr.gather(mi.UInt32, buf.kind, p_s) != VOLUME
        g_point = form_factor(buf, p_x, p_n, p_corners, dr.gather(mi.Vector3f, buf.normal, p_s), p_planar,
                              p_s, offset)
        dr.eval(g_point)
        g_exact = dr.gather(mi.Float, g_point, lane // r_count)

    # --- shadow ray to one of the source's stratified points -------------------------------
    key = hash_u32(hash_u32(r ^ hash_u32(seed + 0x9E3779B9)) + s * 0x632BE5AB)
    pattern = pattern_size(r_count, spread)
    t = ray_target(i, j, r_count, key, spread)
    # (a volume cluster's triangle is drawn by what it may send to the point, ``source_point``;
    # a periodic source's images are drawn by area)
    y, ny, tri, drawn, place = source_point(buf, s, t, pattern, key, *((x, nx) if periodic is None else ()),
                                            weigh_faces=weigh_faces)
    # a volume cluster: the exact form factor of the triangle the point is on, over the
    # probability of drawing it: unbiased, and bounded by the cluster's area over the
    # triangle's times what the draw favoured it by, where a point-to-point kernel is not (a
    # bounded kernel A cos cos / (pi r^2 + A / S) took too little light from nearby triangles)
    tri_corners = [dr.gather(mi.Vector3f, c, tri) for c in buf.poly]
    per_area = area_s / dr.maximum(dr.gather(mi.Float, buf.area, tri), _TINY) * drawn
    if periodic is not None:     # one of the source's images per ray, wrapped visibility
        from .periodic import image_visibility
        kernel, g_volume, traced, v = image_visibility(mi_scene, periodic, x, nx, y, ny, planar, g_exact,
                                                       tri_corners, per_area, offset,
                                                       hash_u32(key ^ (i * 0x68E31DA4 + j * 0x2C1B3C6D)), volume_sample)
        return Lanes(g_exact, kernel, g_volume, traced, v, tri, g_volume, _face_share(kind, g_exact, kernel), place)
    o = x + nx * offset
    d = (y + ny * offset) - o
    dist2 = dr.squared_norm(d)
    dist = dr.sqrt(dist2)
    cos_x = dr.dot(d, nx) / dr.maximum(dist, _TINY)
    cos_y = -dr.dot(d, ny) / dr.maximum(dist, _TINY)
    valid = (cos_x > 0) & (cos_y > 0) & (dist > 0)
    kernel = dr.select(valid, cos_x * cos_y / dr.maximum(dist2, _TINY), 0.0)
    g_volume = volume_sample(x, nx, ny, tri_corners, per_area, planar, offset)
    g_weighted = g_volume
    if KERNEL_WEIGHTED_VOLUMES:
        # (the sample times its point's kernel over its triangle's mean kernel, pi F_tri / A_tri:
        # the point kernel's own estimate A_s cos cos / (pi r^2) over the draw's probability. Its
        # ray is weighed so as the planar sources' rays are, ``_sums``)
        g_weighted = dr.select(g_volume > 0, kernel * (area_s * drawn / dr.pi), 0.0)
    traced = valid & ((g_exact > 0) | ~planar)
    return Aimed(g_exact, kernel, g_volume, traced, tri, o, d / dr.maximum(dist, _TINY),
                 shadow_ray_length(dist, offset), g_weighted, _face_share(kind, g_exact, kernel), place)


def _face_share(kind, g_exact, kernel):
    """mi.Float per lane: a face cluster's share of its link's transfer before norming, its
    point's exact form factor times its ray's kernel (``Lanes.g_share``); 0 for other sources."""
    return dr.select(kind == FACE, g_exact * kernel, 0.0)


def _shoot(mi_scene, aimed: Aimed) -> Lanes:
    """The lanes of a wave whose shadow rays are aimed (``_aim``), once those are traced."""
    ray = mi.Ray3f(aimed.origin, aimed.direction)
    ray.maxt = aimed.length
    v = dr.select(aimed.traced, dr.select(mi_scene.ray_test(ray, aimed.traced), 0.0, 1.0), 0.0)
    return Lanes(aimed.g_exact, aimed.kernel, aimed.g_volume, aimed.traced, v, aimed.tri, aimed.g_weighted,
                 aimed.g_share, aimed.place)


def volume_sample(x, nx, ny, tri_corners, per_area, planar, offset: float):
    """mi.Float: a volume-cluster source's transfer sample at points x (normals nx): the exact
    form factor of the sampled triangle (corners ``tri_corners``, normal ny) times the
    cluster's area over the triangle's (``per_area``); 0 for planar sources and for
    triangles facing away (or in x's plane)."""
    front = dr.dot(ny, x - tri_corners[0]) > 0.1 * offset
    return dr.select(~planar & front, point_to_polygon_dr(x, nx, tri_corners) * per_area, 0.0)


def _wave(mi_scene, buf: NodeArrays, recv_dr, src_dr, lane, point_lane, seed, r_count: int, offset: float,
          periodic, weigh_faces: bool, spread: bool, samples: bool, frozen: bool) -> tuple:
    """One launch of ``evaluate``: the lanes of links recv_dr <- src_dr (``_lanes``) summed per
    receiver point (``_sums``), in Dr.Jit: (g, gv, gv_point, gv_square) mi.Float (M K,), the
    rays traced (mi.Float (1,)) and, with ``samples``, the volume-cluster samples' transfer (and
    the partly hidden face clusters' shares) and triangle node per lane (for ``_arriving``).
    ``frozen`` (FREEZE_WAVES, not periodic): the rays' aim and the sums replay recorded kernels
    (``_frozen_aim``, ``_frozen_sums``); only the rays are traced as they come (a frozen function
    takes the scene's every array as an input)."""
    if frozen:
        aimed = _frozen_aim(None, buf, recv_dr, src_dr, lane, point_lane, r_count, seed, offset,
                            weigh_faces=weigh_faces, spread=spread)
        # (a frozen function traverses plain tuples, not named ones)
        return _frozen_sums(r_count, point_lane, tuple(_shoot(mi_scene, Aimed(*aimed))), samples)
    lanes = _lanes(mi_scene, buf, recv_dr, src_dr, lane, point_lane, r_count, seed, offset, periodic,
                   weigh_faces=weigh_faces, spread=spread)
    return _sampled_sums(r_count, point_lane, lanes, samples)


def _volume_norm(g_volume, g_weighted, per_link: int):
    """mi.Float per link: its volume samples' summed transfer over their summed kernel-weighted
    transfer (1 where none has weight)."""
    plain, weighted = dr.block_sum(g_volume, per_link), dr.block_sum(g_weighted, per_link)
    return dr.select(weighted > 0, plain / dr.select(weighted > 0, weighted, 1.0), 1.0)


def _sampled_sums(r_count: int, point_lane, lanes: Lanes, samples: bool) -> tuple:
    """``_sums``, and with ``samples`` the volume-cluster samples' transfer (and the partly hidden
    face clusters' shares, ``PointTransfers.samples``) and triangle node
    per lane (evaluated with the sums: kept unevaluated, their rays would be traced again)."""
    per_link = RECEIVER_POINTS * r_count
    norm = _volume_norm(lanes.g_volume, lanes.g_weighted, per_link)
    if samples:
        lane_link = dr.arange(mi.UInt32, dr.width(lanes.v)) // per_link
        lane_norm = dr.gather(mi.Float, norm, lane_link)
        # (a face cluster's lane where its ray arrived: its share of the link's transfer, which the
        # caller norms over the link; only where some of the link's rays were blocked)
        hidden = dr.block_sum(lanes.g_share * lanes.v, per_link) < dr.block_sum(lanes.g_share, per_link)
        face = dr.select(dr.gather(mi.Bool, hidden, lane_link), lanes.g_share * lanes.v, 0.0)
        sampled = (lanes.g_weighted * lanes.v * lane_norm + face, lanes.tri, lanes.place)
    else:
        sampled = ()
    return _sums(r_count, point_lane, lanes, norm, *sampled) + sampled


#: Whether ``evaluate`` replays its waves' recorded kernels (``dr.freeze``) rather than tracing
#: them anew on every call: tracing a wave (its Python, then Dr.Jit's assembly of the kernel)
#: took 1-3 ms a launch, half a small scene's solve. A wave is recorded once per kind of call
#: (rays per point, ray offset, the flags) and replayed for any number of links; periodic
#: scenes' waves are traced as before.
FREEZE_WAVES = True
#: Whether a volume cluster's samples weigh their rays' visibility by their point's kernel over
#: their triangle's mean kernel (``_aim``, ``_sums``), as the planar sources' rays are weighed.
KERNEL_WEIGHTED_VOLUMES = True
#: Most lanes in one frozen wave: its aimed rays are kept between its two halves (about 50 B
#: a lane), so its launches are smaller than MAX_LANES (a fine Cornell box's peak memory rose
#: by 230 MB with waves of MAX_LANES).
FROZEN_LANES = 1 << 20
#: Recordings kept of each frozen half (least recently used dropped): one per kind of call.
FROZEN_WAVES_KEPT = 64


def _freeze(function):
    # (no warning after many recordings: each scene's ray offset is a kind of call of its own, so
    # a process that solves many scenes records many; a test checks that a warm solve records none.
    # warn_after=0 does not turn it off: Dr.Jit then warns at every recording after the first)
    return dr.freeze(function, limit=FROZEN_WAVES_KEPT, warn_after=1 << 30)


_frozen_aim = _freeze(lambda *args, **kwargs: tuple(_aim(*args, **kwargs)))
_frozen_sums = _freeze(lambda r_count, point_lane, lanes, samples: _sampled_sums(r_count, point_lane, Lanes(*lanes),
                                                                                samples))
# (and the reverse form factors of a refinement pass's near links)
_frozen_reverse = _freeze(_reverse_values)


def wave_recordings() -> int:
    """How many times this process recorded a frozen wave's halves or a reverse form factor's
    launch (``FREEZE_WAVES``): once per kind of call; a solve of a scene solved before with the
    same settings adds none."""
    return sum(f.n_recordings for f in (_frozen_aim, _frozen_sums, _frozen_reverse))


def _sums(r_count: int, point_lane, lanes: Lanes, volume_norm, *also) -> tuple:
    """The wave's per-ray lanes (``_lanes``) summed per receiver point and combined there, in
    Dr.Jit: (g, gv, gv_point, gv_square) mi.Float (M K,) and the rays traced (mi.Float (1,)),
    evaluated. ``volume_norm``: per link, its volume samples' summed transfer over their summed
    kernel-weighted one (``_volume_norm``); ``also``: further per-lane values evaluated in the same
    kernel."""
    k = RECEIVER_POINTS
    kernel, g_volume, v = lanes.kernel, lanes.g_volume, lanes.v
    summed = [lanes.g_exact, kernel, kernel * v, g_volume, lanes.g_weighted * v, g_volume * g_volume * v,
              dr.select(lanes.traced, 1.0, 0.0)]
    dr.eval(*summed, *also)
    g_e, k_s, kv_s, g_vol, g_vol_v, g_vol_sq = (dr.block_sum(a, r_count) for a in summed[:6])
    n_traced = dr.sum(summed[6])
    # (a volume cluster's samples weighed by their kernels, normed over the whole link so that
    # their weights mean 1 (``volume_norm``, per link): the link's kernel-weighted visibility, as
    # the planar sources' ratio)
    g_vol_v = g_vol_v * dr.gather(mi.Float, volume_norm, point_lane // k)
    # visibility: the kernel-weighted fraction of the rays that arrive, over the whole link
    # for the transfer and at each point for its spread; a point none of whose rays could be
    # aimed (grazing) takes the link's
    # (a ratio of sums over every ray of the link: over one point's few rays the ratio is
    # biased towards the area-weighted fraction)
    ks_l, kv_l = dr.block_sum(k_s, k), dr.block_sum(kv_s, k)
    vis_link = dr.gather(mi.Float, dr.select(ks_l > 0, kv_l / dr.select(ks_l > 0, ks_l, 1.0), 1.0), point_lane // k)
    vis_point = dr.select(k_s > 0, kv_s / dr.select(k_s > 0, k_s, 1.0), vis_link)
    g_e = g_e / r_count
    out = (g_e + g_vol / r_count, g_e * vis_link + g_vol_v / r_count, g_e * vis_point + g_vol_v / r_count,
           g_vol_sq / r_count, n_traced)
    dr.eval(*out)
    return out


def pattern_size(rays_per_point: int, spread: bool = False) -> int:
    """Points in the set a link's rays aim at: SOURCE_POINTS, or one per ray of a point; with
    ``spread``, one per ray of the link (K R)."""
    if spread:
        return RECEIVER_POINTS * int(rays_per_point)
    return max(SOURCE_POINTS, int(rays_per_point))


def ray_target(i, j, rays_per_point: int, key=0, spread: bool = False):
    """Which of a link's ``pattern_size`` target points ray j of its receiver point i aims at
    (i, j, key: ints, numpy or Dr.Jit arrays; ``key`` the link's hash, which only shifts the
    set): the points' rays spread over the targets with an odd step, so that a point's R rays
    are R different targets (``refine.shared_target_weight`` counts how the points share them).

    The points share the targets, so that what each point sees is a quadrature of the source
    that varies smoothly over the receiver, as a field fitted over it needs. Its mean over the
    points is then hardly better than one point's: sixteen rays a point at the sixteen targets
    gave a shadowed pair's transfer 2.8 times the variance of 112 independent rays on the fine
    Cornell box. With ``spread`` (a pair that takes the points' mean, not a field) every ray has
    a target of its own, the points' rays interleaved over the K R targets (point i at i, i + K,
    ...), so that each point's rays cover the source as a stratified set: 0.5 times that variance."""
    if spread:
        return (key + i + RECEIVER_POINTS * j) % pattern_size(rays_per_point, spread)
    pattern = pattern_size(rays_per_point)
    step = 2 * (rays_per_point // 2) + 1 if rays_per_point < pattern else 1
    return (key + i * 7 + j * step) % pattern


#: A volume cluster's draw weighs the face clusters below it by what each part may send to the
#: point (``_reach``), as it does its volume levels, rather than by area (``source_point``).
WEIGH_FACES_IN_VOLUMES = True


def source_point(buf: NodeArrays, s, t, pattern: int, key, x=None, nx=None, weigh_faces: bool = False):
    """Point t (of ``pattern``) on source nodes s, its normal (mi.Vector3f each), the
    triangle node it is on (mi.UInt32), the ratio (mi.Float) of the probability of
    drawing that triangle by area to the probability it was drawn with, and where on the
    triangle the point is (mi.UInt32, ``pack_place``), for the link whose hash is ``key``.

    Each link draws its own stratified set: a Hammersley set shifted per link (every
    receiver point of a link aims at the same ``pattern`` points, so a ray to each of
    them is a quadrature of the source that varies smoothly over the receiver). A fixed set
    per node would be one quadrature shared by all of the node's links: where part of a
    large source is hidden, its error would be the same on every receiver, a bias that no
    number of receivers averages out. On a cluster, u picks one of its triangles with
    probability in proportion to area, descending the tree (along the tree's order, so
    the set stays stratified over the cluster); a hash of (link, t) places the point on it.

    Given receiver points x (normals nx), a volume cluster's levels split u by what each
    child may send to x instead (``_reach``: 0 only where nothing of the child reaches x). The
    draw stays unbiased (the transfer is divided by the probability it was drawn with) and
    follows the kernel over the cluster's nearer and facing parts, where drawing by area spent
    most samples on parts that send little: a leaf under a canopy gathers from clusters of
    leaves around it, a few of which bring most of the light. The face clusters below a volume
    cluster are weighed so too, where ``weigh_faces`` (``WEIGH_FACES_IN_VOLUMES`` for the waves
    that hold volume-cluster links): by area, a plate 1 m over a ground of 32 large triangles drew
    the one below it, a sixth of its light, one time in 32, and its transfer's deviation over
    seeds was 22 % at four rays a point (8 % weighed). A face cluster that is the link's own
    source is drawn by area, a stratified quadrature of it."""
    u, v = shifted_hammersley(t, pattern, key)
    node = mi.UInt32(s)
    on_triangle = dr.gather(mi.UInt32, buf.kind, node) == TRIANGLE

    def kind(node):
        return dr.gather(mi.UInt32, buf.kind, node)

    def descend(node, left, drawn, weigh: bool, where=True):
        c0 = dr.gather(mi.UInt32, buf.child[0], node)
        c1 = dr.gather(mi.UInt32, buf.child[1], node)
        a0 = dr.gather(mi.Float, buf.area, c0)
        share = a0 / dr.maximum(a0 + dr.gather(mi.Float, buf.area, c1), _TINY)
        by_area = share
        if weigh:
            r0, r1 = _reach(buf, c0, x, nx), _reach(buf, c1, x, nx)
            share = dr.select(where & (r0 + r1 > 0), r0 / dr.maximum(r0 + r1, _TINY), share)
        first = left < share
        nxt = dr.select(first, left / dr.maximum(share, _TINY), (left - share) / dr.maximum(1.0 - share, _TINY))
        if weigh:
            drawn = drawn * dr.select(share == by_area, 1.0,
                                      dr.select(first, by_area / dr.maximum(share, _TINY),
                                                (1.0 - by_area) / dr.maximum(1.0 - share, _TINY)))
        return dr.select(first, c0, c1), dr.clip(nxt, 0.0, 1.0 - 2 ** -24), drawn

    # (the volume clusters' levels first, weighed where x is given, then the face clusters':
    # weighed below a volume cluster, by area on a face-cluster source; the weights are computed
    # only where a level may use them)
    weigh_faces = weigh_faces and x is not None
    below_volume = kind(node) == VOLUME
    state = (node, mi.Float(u), dr.full(mi.Float, 1.0, dr.width(node)))
    state = dr.while_loop(state=state, cond=lambda node, left, drawn: kind(node) == VOLUME,
                          body=lambda node, left, drawn: descend(node, left, drawn, x is not None))
    node, _, drawn = dr.while_loop(state=state, cond=lambda node, left, drawn: kind(node) != TRIANGLE,
                                   body=lambda node, left, drawn: descend(node, left, drawn, weigh_faces, below_volume))
    w = to_unit(hash_u32(key ^ hash_u32(t + 0x2545F491)))
    along = dr.select(on_triangle, u, w)
    y = triangle_point(*(dr.gather(mi.Vector3f, c, node) for c in buf.poly[:3]), along, v)
    place = pack_place(dr.sqrt(along), v)
    n = dr.gather(mi.Vector3f, buf.normal, node)
    # points of tessellated spheres and cylinders on the true surface (nodes.project)
    radius = dr.gather(mi.Float, buf.curve[2], node)
    center = dr.gather(mi.Vector3f, buf.curve[0], node)
    axis = dr.gather(mi.Vector3f, buf.curve[1], node)
    d = y - center
    radial = d - axis * dr.dot(d, axis)
    rlen = dr.norm(radial)
    curved = (radius > 0) & (rlen > 0)
    direction = radial / dr.maximum(rlen, _TINY)
    y = dr.select(curved, y + direction * (radius - rlen), y)
    n = dr.select(curved, dr.select(dr.dot(direction, n) < 0, -direction, direction), n)
    return y, n, node, drawn, place


def pack_place(su, v):
    """mi.UInt32: a point on a triangle (corners p0, p1, p2) at (1 - su) p0 + su (1 - v) p1 +
    su v p2 (``visibility.triangle_point``, su = sqrt(u)), su and v in [0, 1] as 16 bits each
    (``nodes.leaf_holding`` finds the leaf below the triangle that holds it)."""
    def bits(x):
        return mi.UInt32(dr.clip(x, 0.0, 1.0) * PLACE_SCALE + 0.5)
    return (bits(su) << 16) | bits(v)


def _reach(buf: NodeArrays, c, x, nx):
    """mi.Float: what nodes c may send to points x (normals nx), as ``source_point`` weighs a
    volume cluster's children, after the kernel A cos_x cos_c / r^2 over the child's bounding
    sphere (centre at d from x, radius R): its area over max(|d|^2, R^2), times upper bounds of
    the cosines over the sphere, (n_x . d + R) / (|d| - R) at x and, for a flat node (normal
    n_c, x at height h over its plane), (h + b) / (|d| - R) at the node (b the plane's
    tolerance, ``nodes.PLANE_NORMAL_TOL`` R), each clipped to [0, 1] (1 within the sphere).
    A bound is 0 only where no part of the child can send x anything: the sphere wholly behind
    x's tangent plane, or x behind the node's plane; x within b of the plane (on the receiver's
    own planar group, which shares a cluster with it) weighs the node at 1/1000. Bounds, not
    the cosines at the centre: a point 1 cm over a large floor gets much of its light from the
    floor just below it, which the centre's grazing cosine put at a hundredth (a chair leg's
    foot then drew the floor's few samples with large weights, and its transfer was noisy)."""
    d = dr.gather(mi.Vector3f, buf.sphere[0], c) - x
    radius = dr.gather(mi.Float, buf.sphere[1], c)
    dist2 = dr.squared_norm(d)
    gap = dr.sqrt(dist2) - radius
    inv = dr.select(gap > 0, 1.0 / dr.maximum(gap, _TINY), dr.inf)
    cosine = dr.clip((dr.dot(nx, d) + radius) * inv, 0.0, 1.0)
    height = -dr.dot(dr.gather(mi.Vector3f, buf.normal, c), d)
    # (a planar group's triangles leave its plane by up to PLANE_NORMAL_TOL of its size: x in the
    # plane, as on the receiver's own group, gets next to nothing from it, drawn next to never)
    bump = PLANE_NORMAL_TOL * radius
    facing = dr.select(height > 0.1 * bump, dr.clip((height + bump) * inv, 0.0, 1.0),
                       dr.select(height > -bump, 1e-3, 0.0))
    cosine *= dr.select(dr.gather(mi.Bool, buf.flat, c), facing, 1.0)
    return dr.gather(mi.Float, buf.area, c) * cosine / dr.maximum(dr.maximum(dist2, radius * radius), _TINY)


def buried_fraction(mi_scene, points: np.ndarray, normals: np.ndarray, offset: float, table) -> np.ndarray:
    """(N,) fraction of each node's points (N, S, 3), with normals (N, S, 3), that lie
    inside closed geometry: a ray from the point along its normal first meets the back of a
    one-sided surface (``table``: ``one_sided_table``; the floor under a box standing on it), and
    so does every ray of a set spread over its hemisphere (``_buried``).

    That part of a surface is seen from nowhere; its radiosity is zero, so the light a
    node sends is its power over the area that is not buried (``core.solve``)."""
    n, s = points.shape[:2]
    out = np.zeros(n)
    per_launch = max(1, MAX_LANES // max(s, 1))
    for a in range(0, n, per_launch):
        b = min(n, a + per_launch)
        inside = _buried(mi_scene, to_vector3(points[a:b].reshape(-1, 3)), to_vector3(normals[a:b].reshape(-1, 3)),
                         offset, table)
        out[a:b] = np.asarray(dr.block_sum(dr.select(inside, 1.0, 0.0), s).numpy(), np.float64) / s
    return out


def blocked(mi_scene, start: np.ndarray, end: np.ndarray, normal: np.ndarray, offset: float) -> np.ndarray:
    """(M,) bool: whether a surface lies between points start and end (M, 3) of a surface with
    normals ``normal`` (M, 3), both ends lifted ``offset`` (m) off it."""
    m = len(start)
    out = np.zeros(m, bool)
    with exact_arithmetic():
        for a in range(0, m, MAX_LANES):
            b = min(m, a + MAX_LANES)
            lift = to_vector3(normal[a:b]) * offset
            o = to_vector3(start[a:b]) + lift
            d = to_vector3(end[a:b]) + lift - o
            dist = dr.norm(d)
            ray = mi.Ray3f(o, d / dr.maximum(dist, _TINY))
            ray.maxt = shadow_ray_length(dist, offset)
            out[a:b] = np.asarray(mi_scene.ray_test(ray, dist > 0).numpy(), bool)
    return out


def buried_share(mi_scene, buf: NodeBuffers, ids: np.ndarray, count: int, seed: int, offset: float,
                 table) -> np.ndarray:
    """(M,) ``buried_fraction`` of triangle nodes ids from ``count`` stratified points on
    each (a Hammersley set shifted per node, on the true surface of curved patches), made
    and counted in the wave: only the shares come back. It measures the nodes that
    ``buried_fraction`` found partly buried, whose enclosure the rays around their points
    confirmed: how much of each lies under the enclosing surface, from the points' rays
    along the normal alone."""
    m = len(ids)
    out = np.zeros(m)
    per_launch = max(1, MAX_LANES // max(count, 1))
    for a in range(0, m, per_launch):
        b = min(m, a + per_launch)
        lane = dr.arange(mi.UInt32, (b - a) * count)
        node = dr.gather(mi.UInt32, to_uint(ids[a:b]), lane // count)
        key = hash_u32(node ^ hash_u32(opaque_u32(seed) + 0x5BD1E995))
        y, n, _, _, _ = source_point(buf, node, lane % count, count, key)
        inside = _buried(mi_scene, y, n, offset, table, enclosed=False)
        out[a:b] = np.asarray(dr.block_sum(dr.select(inside, 1.0, 0.0), count).numpy(), np.float64) / count
    return out


def leaves_blocked(mi_scene, buf: NodeBuffers, centroid: np.ndarray, normal: np.ndarray, recv: np.ndarray,
                   src: np.ndarray, seed: int, offset: float, rays=1, from_points: bool = False) -> np.ndarray:
    """(M,) bool: whether any of ``rays`` (an int, or (M,) per node) shadow rays from the
    centroid (M, 3) of each node recv (M,), with normals ``normal`` (M, 3), to the stratified
    points of source nodes src (M,) (``source_point``; which ones and where on it from a hash of
    the pair and seed, a node's rays spread over the SOURCE_POINTS points) is blocked. A point on
    the source behind the receiver, or the receiver behind the source, counts as not blocked (the
    ray says nothing of a shadow). One wave for all nodes, up to MAX_LANES rays at a time.
    ``from_points``: the rays start at each node's receiver points (``buf.recv_pts``, K a node)
    instead of its centroid, ray t of a node at its point (h + t) mod K (h from the pair's hash),
    so that k rays see k places of the node, not its centre k times. (Read from the resident
    buffer: passed as an (M, K, 3) array, the furnished room's checks at tolerance 0.02 held
    0.8 GB more and took its gather 50 -> 66 s.)"""
    m = len(src)
    count = np.broadcast_to(np.asarray(rays, np.int64), (m,))
    out = np.zeros(m, bool)
    ends = np.cumsum(count)
    a = 0
    with exact_arithmetic():
        while a < m:
            # (whole nodes per wave: as many as MAX_LANES rays hold, at least one)
            b = max(a + 1, int(np.searchsorted(ends, (ends[a - 1] if a else 0) + MAX_LANES, side="right")))
            c = count[a:b]
            pair_of = np.repeat(np.arange(b - a), c)
            t_of = np.arange(len(pair_of)) - np.repeat(np.cumsum(c) - c, c)
            step_of = np.maximum(SOURCE_POINTS // np.maximum(c, 1), 1)[pair_of]
            pair = to_uint(pair_of)
            s = dr.gather(mi.UInt32, to_uint(src[a:b]), pair)
            r = dr.gather(mi.UInt32, to_uint(recv[a:b]), pair)
            key = hash_u32(hash_u32(r ^ hash_u32(opaque_u32(seed) + 0x2545F491)) + s * 0x632BE5AB)
            y, ny, _, _, _ = source_point(buf, s, (key + to_uint(t_of * step_of)) % SOURCE_POINTS, SOURCE_POINTS, key)
            if from_points:
                x = dr.gather(mi.Vector3f, buf.recv_pts, r * RECEIVER_POINTS + (key + to_uint(t_of)) % RECEIVER_POINTS)
            else:
                x = dr.gather(mi.Vector3f, to_vector3(centroid[a:b]), pair)
            nx = dr.gather(mi.Vector3f, to_vector3(normal[a:b]), pair)
            o = x + nx * offset
            d = (y + ny * offset) - o
            dist = dr.norm(d)
            aimed = (dr.dot(d, nx) > 0) & (dr.dot(d, ny) < 0) & (dist > 0)
            ray = mi.Ray3f(o, d / dr.maximum(dist, _TINY))
            ray.maxt = shadow_ray_length(dist, offset)
            hit = np.asarray(mi_scene.ray_test(ray, aimed).numpy(), bool)
            out[a:b] = np.bincount(pair_of, weights=hit, minlength=b - a) > 0
            a = b
    return out


#: Rays from each source with which ``escaping_share`` measures the share of its light that
#: leaves the scene.
ESCAPE_RAYS = 64


def escaping_share(mi_scene, buf: NodeBuffers, src: np.ndarray, seed: int, offset: float) -> tuple[np.ndarray, int]:
    """(S,) the share of the light of planar source nodes src (S,) that leaves the scene,
    and the rays traced: of ESCAPE_RAYS cosine-distributed rays from stratified points of
    each (``source_point``), those that meet nothing. (A periodic scene's rays are not
    wrapped: what leaves its pattern box sideways counts as leaving, the larger share.)"""
    m = len(src)
    out = np.zeros(m)
    per = max(1, MAX_LANES // ESCAPE_RAYS)
    with exact_arithmetic():
        for a in range(0, m, per):
            b = min(m, a + per)
            lane = dr.arange(mi.UInt32, (b - a) * ESCAPE_RAYS)
            pair, t = lane // ESCAPE_RAYS, lane % ESCAPE_RAYS
            s = dr.gather(mi.UInt32, to_uint(src[a:b]), pair)
            key = hash_u32(s * 0x9E3779B9 + opaque_u32(seed))
            y, ny, _, _, _ = source_point(buf, s, t, ESCAPE_RAYS, key)
            # (the directions' set in another order than the points': each point its own)
            u, v = shifted_hammersley((t * 37 + 11) % ESCAPE_RAYS, ESCAPE_RAYS, hash_u32(key ^ 0x5BD1E995))
            d = mi.Frame3f(ny).to_world(mi.warp.square_to_cosine_hemisphere(mi.Point2f(u, v)))
            hit = np.asarray(mi_scene.ray_test(mi.Ray3f(y + ny * offset, d)).numpy(), bool)
            out[a:b] = 1.0 - hit.reshape(b - a, ESCAPE_RAYS).mean(axis=1)
    return out, m * ESCAPE_RAYS


def one_sided_table(mi_scene) -> mi.Bool:
    """mi.Bool indexed by a shape's registry id (``dr.reinterpret_array`` of its pointer): whether
    its BSDF scatters on its front side only. (A table read per hit, not a call of each hit's
    BSDF: the call's trace took half of ``_meets_back``'s, about 0.7 ms a launch.) Made once a
    scene: it calls every shape's BSDF (``core`` keeps it on the scene)."""
    shapes = mi_scene.shapes_dr()
    ids = dr.reinterpret_array(mi.UInt32, shapes)
    table = dr.zeros(mi.Bool, int(dr.max(ids)[0]) + 1 if dr.width(ids) else 1)
    dr.scatter(table, (shapes.bsdf().flags() & int(mi.BSDFFlags.BackSide)) == 0, ids)
    return table


def _meets_back(mi_scene, p, w, d, offset: float, table):
    """mi.Bool: rays from points p (normals d, lifted ``offset`` along them) in directions w
    whose first hit is the back of a one-sided surface (``table``: ``one_sided_table``)."""
    ray = mi.Ray3f(p + d * offset, w)
    si = mi_scene.ray_intersect(ray)
    shape = dr.reinterpret_array(mi.UInt32, si.shape)
    one_sided = dr.gather(mi.Bool, table, shape, si.is_valid() & (shape < dr.width(table)))
    # (the side Mitsuba lights is its shading normal's: under a mirroring transform the
    # geometric normal si.n points the other way)
    return si.is_valid() & (dr.dot(si.sh_frame.n, w) > 0) & one_sided


def _buried(mi_scene, p, d, offset: float, table, *, enclosed: bool = True):
    """mi.Bool: points p (normals d) inside closed geometry: their ray along the normal first
    meets the back of a one-sided surface (the floor under a box standing on it) and, with
    ``enclosed``, so does each of BURIED_DIRECTIONS rays spread over their hemisphere (the
    normal's ray alone read the ceiling above a one-sided lamp hung below it as enclosed, and
    gave it no light). Only the points whose normal's ray meets a back trace the others."""
    inside = _meets_back(mi_scene, p, d, d, offset, table)
    if not enclosed:
        return inside
    candidates = dr.compress(inside)
    count = dr.width(candidates)
    if count == 0:
        return inside
    # (one ray per lane, BURIED_DIRECTIONS lanes a candidate)
    lane = dr.arange(mi.UInt32, count * BURIED_DIRECTIONS)
    point = dr.gather(mi.UInt32, candidates, lane // BURIED_DIRECTIONS)
    k = mi.Float(lane % BURIED_DIRECTIONS)
    u = (k + 0.5) / BURIED_DIRECTIONS
    turn = k * 0.6180339887498949
    phi = 2.0 * math.pi * (turn - dr.floor(turn))
    sin_t = dr.sqrt(u)
    local = mi.Vector3f(sin_t * dr.cos(phi), sin_t * dr.sin(phi), dr.sqrt(1.0 - u))
    pc, dc = dr.gather(type(p), p, point), dr.gather(type(d), d, point)
    backs = dr.block_sum(dr.select(_meets_back(mi_scene, pc, mi.Frame3f(dc).to_world(local), dc, offset, table),
                                   1.0, 0.0), BURIED_DIRECTIONS)
    out = dr.zeros(mi.Bool, dr.width(inside))
    dr.scatter(out, backs == BURIED_DIRECTIONS, candidates)
    return out
