"""Clusters of input patches: a bounding-volume hierarchy used as link *sources*.

Without clustering every pair of facing input patches starts linked, O(P^2) links
before any refinement: 47 M for a 10k-triangle model. With it, every patch starts
with one link to the root cluster and refinement opens clusters (binary BVH nodes)
where a link's error asks for it, so a receiver ends up linked to a cut of the
tree: fine near it, coarse far away.

Clusters are element nodes appended after the patches (ids P .. P+C-1): each
patch's parent is its lowest cluster, so the existing push/pull matrices give a
cluster the area-weighted mean radiosity of the leaves below it. Clusters are only
ever sources; receivers stay surface elements (links sit on receiver leaves).

A link p <- cluster q is evaluated by Monte Carlo: receiver points as for any link,
a patch of the cluster drawn by area per sample (binary search in a cumulative-area
table in BVH order), Lambert's form factor from the point to that patch divided by
the probability of drawing it (``F_patch * A_q / A_patch``, unbiased and bounded),
and one shadow ray to a point of the patch. The sampled variance drives the oracle
to open the cluster; the solver spreads the link over the patches its samples drew
(``visibility.cluster_link_entries``), so each carries its own radiosity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import _runtime  # noqa: F401

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

from .arrays import to_float, to_uint  # noqa: E402


@dataclass
class ClusterTree:
    """Binary BVH over P patches.

    order : (P,) int        patches in tree order; every cluster covers order[lo:hi]
    lo, hi : (C,) int       each cluster's range in ``order``
    children : (C, 2) int   element ids of the two children (patch ids < P, or P + cluster)
    parent_of_patch : (P,) int   element id of each patch's lowest cluster
    parent : (C,) int       element id of each cluster's parent (-1 for the root)
    area : (C,) float       m^2
    level : (C,) int        depth in the tree (root 0)
    """

    order: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    children: np.ndarray
    parent_of_patch: np.ndarray
    parent: np.ndarray
    area: np.ndarray
    level: np.ndarray

    def __len__(self) -> int:
        return len(self.lo)


#: Split positions along a segment's longest extent are compared on a grid of this many steps
#: over that extent (``build_tree(bins=...)``, the hierarchical core's trees).
SPLIT_BINS = 1024


def split_keys(c: np.ndarray, starts: np.ndarray, seg_of: np.ndarray, bins: int | None = None) -> np.ndarray:
    """Sort keys of points c (Q, 3) grouped in segments (``starts`` of each, ``seg_of`` (Q,)):
    their coordinate along their segment's longest extent.

    With ``bins``, extents and coordinates are compared on a grid of ``bins`` steps over the
    segment's largest extent, from the segment's lower corner: positions equal up to rounding
    (a grid's rows after float32 rounding of scaled or moved vertices) tie, and ties keep the
    order the points came in, so that the same geometry in other units or at another place
    gives the same tree. Without, the raw longest axis and coordinate (ties broken by rounding).
    """
    box_lo = np.minimum.reduceat(c, starts, axis=0)
    box_hi = np.maximum.reduceat(c, starts, axis=0)
    ext = box_hi - box_lo
    if bins is None:
        axis = np.argmax(ext, axis=1)
        return c[np.arange(len(c)), axis[seg_of]]
    top = ext.max(axis=1)
    top = np.where(top > 0, top, 1.0)
    axis = np.argmax(np.round(ext / top[:, None] * bins), axis=1)          # first of (nearly) equal extents
    a = axis[seg_of]
    return np.round((c[np.arange(len(c)), a] - box_lo[seg_of, a]) / top[seg_of] * bins)


def build_tree(centroid: np.ndarray, area: np.ndarray, bins: int | None = None) -> ClusterTree:
    """BVH over patches (centroids (P, 3), areas (P,)): median split on the longest axis.

    Built one level at a time over all segments at once (numpy); P - 1 clusters for P >= 2.
    ``bins``: compare positions on a grid relative to each segment (``split_keys``).
    """
    p = len(centroid)
    order = np.arange(p)
    seg_lo, seg_hi, seg_node = np.array([0]), np.array([p]), np.array([0])
    lo, hi, parent, level = [0], [p], [-1], [0]
    depth = 0
    children = []          # (node, slot, element id)
    parent_of_patch = np.full(p, -1, np.int64)
    while len(seg_lo):
        depth += 1
        # --- sort each segment along the longest axis of its centroids' box -------------
        seg_of = np.repeat(np.arange(len(seg_lo)), seg_hi - seg_lo)
        idx = _ranges(seg_lo, seg_hi)
        c = centroid[order[idx]]
        starts = np.concatenate([[0], np.cumsum(seg_hi - seg_lo)[:-1]])
        key = split_keys(c, starts, seg_of, bins)
        perm = np.lexsort((np.arange(len(idx)), key, seg_of))
        order[idx] = order[idx[perm]]
        # --- split at the middle; children of size 1 are patches, larger ones clusters ----
        mid = (seg_lo + seg_hi) // 2
        next_lo, next_hi, next_node = [], [], []
        for slot, (a, b) in enumerate(((seg_lo, mid), (mid, seg_hi))):
            single = (b - a) == 1
            patch = order[a[single]]
            children.extend(zip(seg_node[single], np.full(single.sum(), slot), patch))
            parent_of_patch[patch] = p + seg_node[single]
            many = ~single
            new_nodes = len(lo) + np.arange(many.sum())
            lo.extend(a[many]); hi.extend(b[many]); parent.extend(seg_node[many])
            level.extend([depth] * int(many.sum()))
            children.extend(zip(seg_node[many], np.full(many.sum(), slot), p + new_nodes))
            next_lo.append(a[many]); next_hi.append(b[many]); next_node.append(new_nodes)
        seg_lo, seg_hi, seg_node = (np.concatenate(x) for x in (next_lo, next_hi, next_node))
    n = len(lo)
    child_table = np.zeros((n, 2), np.int64)
    ch = np.array(children, dtype=np.int64).reshape(-1, 3)
    child_table[ch[:, 0], ch[:, 1]] = ch[:, 2]
    lo, hi = np.array(lo), np.array(hi)
    cum = np.concatenate([[0.0], np.cumsum(area[order])])
    parent = np.array(parent)
    return ClusterTree(order, lo, hi, child_table, parent_of_patch,
                       np.where(parent >= 0, p + parent, -1), cum[hi] - cum[lo], np.array(level))


def cluster_boxes(tree: ClusterTree, patch_verts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bounding boxes (lower (C, 3), upper (C, 3)) of the clusters.

    Children boxes are merged bottom-up, one tree level at a time.
    """
    p = len(patch_verts)
    box_lo = np.concatenate([patch_verts.min(axis=1), np.zeros((len(tree), 3))])
    box_hi = np.concatenate([patch_verts.max(axis=1), np.zeros((len(tree), 3))])
    for lev in range(int(tree.level.max()), -1, -1):
        nodes = np.flatnonzero(tree.level == lev)
        a, b = tree.children[nodes, 0], tree.children[nodes, 1]
        box_lo[p + nodes] = np.minimum(box_lo[a], box_lo[b])
        box_hi[p + nodes] = np.maximum(box_hi[a], box_hi[b])
    return box_lo[p:], box_hi[p:]


def box_corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(M, 8, 3) corners of boxes (M, 3)."""
    pick = np.array([[(i >> a) & 1 for a in range(3)] for i in range(8)], bool)
    return np.where(pick[None], hi[:, None, :], lo[:, None, :])


def sphere_form_factor_bound(recv_centre, recv_radius, src_centre, src_radius) -> np.ndarray:
    """(M,) upper bound of the form factor from any point of a receiver to a source cluster.

    Everything inside a sphere of radius R whose centre is at least D away subtends at most
    the sphere's form factor R^2 / D^2 (1 when the spheres overlap).
    """
    dist = np.linalg.norm(recv_centre - src_centre, axis=1) - recv_radius
    ratio = np.where(dist > src_radius, src_radius / np.maximum(dist, 1e-300), 1.0)
    return np.minimum(ratio * ratio, 1.0)


def _ranges(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Concatenation of arange(lo[i], hi[i]) for all i (vectorised)."""
    counts = hi - lo
    return np.repeat(lo - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts) + np.arange(counts.sum())


@dataclass
class ClusterGeometry:
    """The tree resident in Dr.Jit for the link kernel: cumulative patch areas in tree order."""

    first: int            # element id of the root cluster (= number of patches P)
    order: object         # mi.UInt32 (P,)
    cum: object           # mi.Float (P + 1,)
    lo: object            # mi.UInt32 (C,)
    hi: object            # mi.UInt32 (C,)
    area: object          # mi.Float (C,)
    patches: int
    count: int            # number of clusters C

    @classmethod
    def upload(cls, tree: ClusterTree, patch_area: np.ndarray) -> "ClusterGeometry":
        cum = np.concatenate([[0.0], np.cumsum(patch_area[tree.order])])
        return cls(len(patch_area), to_uint(tree.order), to_float(cum),
                   to_uint(tree.lo), to_uint(tree.hi),
                   to_float(tree.area), len(patch_area), len(tree))

    def sample_patch(self, cluster, u):
        """Patch (element id) drawn by area inside cluster (index from 0) with u in [0, 1)."""
        lo = dr.gather(mi.UInt32, self.lo, cluster)
        hi = dr.gather(mi.UInt32, self.hi, cluster)
        c_lo = dr.gather(mi.Float, self.cum, lo)
        c_hi = dr.gather(mi.Float, self.cum, hi)
        target = c_lo + u * (c_hi - c_lo)
        j = dr.binary_search(0, self.patches - 1,
                             lambda i: dr.gather(mi.Float, self.cum, i + 1) <= target)
        j = dr.clip(j, lo, hi - 1)
        return dr.gather(mi.UInt32, self.order, j)
