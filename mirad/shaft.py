"""Visibility classification of links: proven fully visible, proven fully blocked, or partial.

A link whose visibility is proven needs no shadow rays and carries no visibility error;
the children of a classified link inherit its class (their shaft lies inside the
parent's), so each shaft is tested once, near the top of the hierarchy.

Fully visible (shaft culling)
    Every shadow ray of a link runs between the receiver and the source triangle, each
    lifted off its surface by the ray offset, so it lies inside the convex hull of their
    six corners. If no scene triangle other than the two ends enters that hull, nothing
    can block any ray. The hull is described by its face planes (the planes through three
    of the six corners that have all six on one side); a bounding-volume hierarchy over
    the scene's triangles is traversed for all links of a wave at once, pruning boxes that
    lie outside a face plane or outside the hull's box, and testing the triangles reached
    against the same planes and against their own plane. Touching (within ``TOUCH`` of the
    scene diagonal, below the ray offset) does not count as entering. The test is
    conservative: it can fail to prove a visible link (it then gets rays), never the
    reverse. Scenes with curved shapes (rays hit the true sphere or cylinder, not its
    tessellation) are not culled.

Fully blocked
    If the nine segments between the two ends' (lifted) corners all hit the same scene
    triangle, and the receiver's corners lie strictly on one side of its plane and the
    source's strictly on the other, every segment between the two triangles crosses that
    occluder (central projection maps a triangle onto the triangle of its corners' images,
    and the occluder is convex). Tested with Mitsuba ``ray_intersect``, only for links
    whose sampled rays were all blocked.
"""

from __future__ import annotations

import itertools

import numpy as np

from . import _runtime  # noqa: F401

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

from .arrays import to_float  # noqa: E402

#: Link classes stored in ``Links.vclass``.
PARTIAL, VISIBLE, BLOCKED = 0, 1, 2
#: A triangle within this fraction of the scene diagonal of the hull counts as touching.
TOUCH = 1e-6
#: Links tested per chunk and hierarchy nodes visited per link before giving up (partial).
_CHUNK = 4096
_MAX_NODES = 96
#: Scenes with at most this many triangles test every triangle (no hierarchy traversal).
_BRUTE_FORCE = 256
#: Face planes kept per hull (a hull of 6 points has at most 8 triangular faces).
_FACES = 10
_TRIPLES = np.array(list(itertools.combinations(range(6), 3)))


def lift(verts: np.ndarray, normal: np.ndarray, offset: float) -> np.ndarray:
    """(M, 3, 3) triangles moved by ``offset`` along their (M, 3) normals (ray origins' plane)."""
    return verts + normal[:, None, :] * offset


def hull_planes(points: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Face planes of the convex hulls of (M, 6, 3) point sets.

    Returns (normals (M, F, 3), offsets (M, F), valid (M, F)): outward unit normals n and
    offsets h with n.x <= h + tol for every point x of the set.
    """
    a, b, c = (points[:, _TRIPLES[:, i]] for i in range(3))               # (M, 20, 3)
    n = np.cross(b - a, c - a)
    length = np.linalg.norm(n, axis=2)
    n = n / np.where(length > 0, length, 1.0)[..., None]
    h = np.einsum("mfc,mfc->mf", n, a)
    d = np.einsum("mfc,mkc->mfk", n, points) - h[..., None]                # (M, 20, 6)
    below, above = d.max(axis=2) <= tol, d.min(axis=2) >= -tol
    valid = (length > 0) & (below | above) & ~(below & above)
    flip = np.where(below, 1.0, -1.0)
    n, h = n * flip[..., None], h * flip
    # keep the first _FACES valid planes (dropping one only makes the test more conservative)
    order = np.argsort(~valid, axis=1, kind="stable")[:, :_FACES]
    take = lambda x: np.take_along_axis(x, order if x.ndim == 2 else order[..., None], axis=1)  # noqa: E731
    return take(n), take(h), take(valid)


class ShaftCuller:
    """Proves links fully visible against the scene's triangles (see module docstring).

    tri_verts : (T, 3, 3) every ray-blocking triangle of the scene; diagonal : scene size (m).
    """

    def __init__(self, tri_verts: np.ndarray, diagonal: float):
        from .cluster import build_tree, cluster_boxes

        self.tri = np.ascontiguousarray(tri_verts, dtype=np.float64)
        self.tol = TOUCH * diagonal
        t = len(self.tri)
        self.patches = t
        tri_lo, tri_hi = self.tri.min(axis=1), self.tri.max(axis=1)
        if t >= 2:
            area = 0.5 * np.linalg.norm(np.cross(self.tri[:, 1] - self.tri[:, 0],
                                                 self.tri[:, 2] - self.tri[:, 0]), axis=1)
            tree = build_tree(self.tri.mean(axis=1), area)
            c_lo, c_hi = cluster_boxes(tree, self.tri)
            self.children = tree.children
        else:
            c_lo = c_hi = np.zeros((0, 3))
            self.children = np.zeros((0, 2), np.int64)
        self.box_lo = np.concatenate([tri_lo, c_lo])      # node ids: triangles, then clusters
        self.box_hi = np.concatenate([tri_hi, c_hi])
        self.root = t if t >= 2 else 0
        self.tri_n = np.cross(self.tri[:, 1] - self.tri[:, 0], self.tri[:, 2] - self.tri[:, 0])
        length = np.linalg.norm(self.tri_n, axis=1)
        self.tri_n /= np.where(length > 0, length, 1.0)[:, None]
        self.tri_h = np.einsum("tc,tc->t", self.tri_n, self.tri[:, 0])

    def visible(self, recv_lifted: np.ndarray, src_lifted: np.ndarray, recv_tri: np.ndarray,
                src_tri: np.ndarray) -> np.ndarray:
        """(M,) bool: proven that no triangle but recv_tri and src_tri enters each link's shaft.

        recv_lifted, src_lifted : (M, 3, 3) link ends lifted by the ray offset;
        recv_tri, src_tri : (M,) scene triangle of each end (never counted as occluders).
        """
        out = np.zeros(len(recv_lifted), bool)
        for start in range(0, len(out), _CHUNK):
            s = slice(start, start + _CHUNK)
            out[s] = self._visible_chunk(np.concatenate([recv_lifted[s], src_lifted[s]], axis=1),
                                         recv_tri[s], src_tri[s])
        return out

    def _visible_chunk(self, points, recv_tri, src_tri) -> np.ndarray:
        m = len(points)
        tol = self.tol
        n, h, valid = hull_planes(points, tol)
        hull_lo, hull_hi = points.min(axis=1), points.max(axis=1)
        occluded = np.zeros(m, bool)
        if self.patches <= _BRUTE_FORCE:
            # few triangles: test every (link, triangle) pair whose boxes overlap
            apart = ((self.box_lo[None, : self.patches] > hull_hi[:, None] - tol)
                     | (self.box_hi[None, : self.patches] < hull_lo[:, None] + tol)).any(axis=2)
            link, tri = np.nonzero(~apart)
            enters = self._enters(link, tri, points, n, h, valid, recv_tri, src_tri)
            occluded[link[enters]] = True
            return ~occluded
        visits = np.zeros(m, np.int64)
        link = np.arange(m)
        node = np.full(m, self.root, np.int64)
        while len(link):
            # --- prune nodes whose box lies outside the hull's box or one of its faces -------
            lo, hi = self.box_lo[node], self.box_hi[node]
            apart = ((lo > hull_hi[link] - tol) | (hi < hull_lo[link] + tol)).any(axis=1)
            centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
            nl = n[link]
            nearest = (np.einsum("pfc,pc->pf", nl, centre) - np.einsum("pfc,pc->pf", np.abs(nl), half)
                       - h[link])
            apart |= ((nearest >= -tol) & valid[link]).any(axis=1)
            keep = ~apart & ~occluded[link]
            link, node = link[keep], node[keep]
            # --- triangles reached -------------------------------------------------------------
            tri = node < self.patches
            if tri.any():
                tl, tn = link[tri], node[tri]
                occluded[tl[self._enters(tl, tn, points, n, h, valid, recv_tri, src_tri)]] = True
            # --- clusters reached: descend; links past their visit budget stay partial --------
            inner = ~tri & ~occluded[link]
            link, node = link[inner], node[inner]
            visits += np.bincount(link, minlength=m)
            over = visits > _MAX_NODES
            occluded |= over
            keep = ~over[link]
            link = np.repeat(link[keep], 2)
            node = self.children[node[keep] - self.patches].ravel()
        return ~occluded

    def _enters(self, link, tri, points, n, h, valid, recv_tri, src_tri) -> np.ndarray:
        """(K,) bool per (link, triangle) pair: the triangle may enter the link's hull.

        Separated when all its corners lie outside (or on) one hull face, or all hull points
        lie on one side of (or on) its plane; the link's own two triangles never count.
        """
        tol = self.tol
        own = (tri == recv_tri[link]) | (tri == src_tri[link])
        d = np.einsum("pfc,pkc->pfk", n[link], self.tri[tri]) - h[link][..., None]
        outside = ((d.min(axis=2) >= -tol) & valid[link]).any(axis=1)
        side = np.einsum("pc,pkc->pk", self.tri_n[tri], points[link]) - self.tri_h[tri][:, None]
        outside |= (side.max(axis=1) <= tol) | (side.min(axis=1) >= -tol)
        return ~own & ~outside


def prove_blocked(mi_scene, recv_lifted: np.ndarray, src_lifted: np.ndarray, tol: float) -> np.ndarray:
    """(M,) bool: proven that one planar, convex piece of a scene mesh blocks every segment
    between the two ends.

    The nine corner-to-corner segments must all hit triangles of one mesh lying in one
    plane, with the receiver strictly on one side and the source strictly on the other;
    the triangles hit must form a convex polygon (their areas add up to the area of
    their convex hull), which then contains every crossing point (see module docstring).
    recv_lifted, src_lifted : (M, 3, 3) link ends lifted by the ray offset; tol : metres.
    """
    m = len(recv_lifted)
    if m == 0:
        return np.zeros(0, bool)
    i, j = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
    o = recv_lifted[:, i.ravel()].reshape(-1, 3)                           # (9M, 3)
    t = src_lifted[:, j.ravel()].reshape(-1, 3)
    d = t - o
    dist = np.linalg.norm(d, axis=1)
    ray = mi.Ray3f(mi.Point3f(*(to_float(o[:, k]) for k in range(3))),
                   mi.Vector3f(*(to_float(d[:, k] / np.maximum(dist, 1e-300)) for k in range(3))))
    ray.maxt = to_float(dist * (1 - 1e-4))
    si = mi_scene.ray_intersect(ray)
    shape = dr.reinterpret_array(mi.UInt32, si.shape)
    dr.eval(si.t, si.prim_index, shape, si.n, si.p)
    hit = np.isfinite(si.t.numpy()).reshape(m, 9)
    shape_id = shape.numpy().astype(np.int64).reshape(m, 9)
    prim = si.prim_index.numpy().astype(np.int64).reshape(m, 9)
    normal = si.n.numpy().T.astype(np.float64).reshape(m, 9, 3)
    point = si.p.numpy().T.astype(np.float64).reshape(m, 9, 3)
    n0, p0 = normal[:, 0], point[:, 0]
    coplanar = ((np.abs(np.einsum("mkc,mc->mk", point - p0[:, None], n0)) <= 10 * tol).all(axis=1)
                & (np.abs(np.einsum("mkc,mc->mk", normal, n0)) > 1 - 1e-5).all(axis=1))
    side_r = np.einsum("mkc,mc->mk", recv_lifted - p0[:, None], n0)
    side_s = np.einsum("mkc,mc->mk", src_lifted - p0[:, None], n0)
    apart = (((side_r > tol).all(axis=1) & (side_s < -tol).all(axis=1))
             | ((side_r < -tol).all(axis=1) & (side_s > tol).all(axis=1)))
    ok = hit.all(axis=1) & (shape_id == shape_id[:, :1]).all(axis=1) & coplanar & apart
    several = ok & (prim != prim[:, :1]).any(axis=1)
    if several.any():
        ok[several] = _convex_union(mi_scene, shape_id[several, 0], prim[several], n0[several])
    return ok


def _convex_union(mi_scene, shape_id: np.ndarray, prim: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """(K,) bool: the distinct triangles prim (K, 9) of mesh shape_id (K,) form a convex polygon."""
    from scipy.spatial import ConvexHull

    meshes = {}
    for s in mi_scene.shapes():
        if s.is_mesh():
            key = int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s)).numpy()[0])
            meshes[key] = (np.array(s.vertex_positions_buffer().numpy(), np.float64).reshape(-1, 3),
                           np.array(s.faces_buffer().numpy(), np.int64).reshape(-1, 3))
    out = np.zeros(len(shape_id), bool)
    for k in range(len(shape_id)):        # only links whose rays all hit one plane: few
        if int(shape_id[k]) not in meshes:
            continue
        verts, faces = meshes[int(shape_id[k])]
        tri = verts[faces[np.unique(prim[k])]]                              # (U, 3, 3)
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
        axis_u = np.cross(normal[k], [1.0, 0, 0] if abs(normal[k][0]) < 0.9 else [0, 1.0, 0])
        axis_u /= np.linalg.norm(axis_u)
        axis_v = np.cross(normal[k], axis_u)
        flat = tri.reshape(-1, 3) @ np.stack([axis_u, axis_v], 1)
        out[k] = abs(ConvexHull(flat).volume - area) <= 1e-4 * area
    return out
