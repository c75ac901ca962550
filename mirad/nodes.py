"""The node hierarchy of the hierarchical core: volume clusters, face clusters, triangles.

From the top down:

* **volume clusters** (``VOLUME``): a bounding-volume hierarchy over the planar groups of
  the scene. They are link *sources* only (light leaves them towards receivers; nothing is
  gathered at a volume), and refinement opens them where a link's bound asks for it.
* **face clusters** (``FACE``): each planar group (adjacent or not, the triangles of one
  shape side that share a plane within a relative tolerance) is a binary tree of
  near-square pieces, split at the median of the longest extent (Willmott, Heckbert &
  Garland 1999 build theirs bottom-up by edge contraction; a median split gives the same
  kind of tree over a plane for a fraction of the cost). A face cluster is one planar
  patch: links attach to it on either end, and what it gathers is pushed to the triangles
  below. Its form-factor polygon is its bounding rectangle in the plane, scaled by
  ``fill = area / rectangle area`` (exact for rectangular walls, bounded by the fill
  otherwise: see refine.py).
* **triangles** (``TRIANGLE``): the input patches (node id = patch id) and, below them,
  their midpoint subdivisions (1 -> 4, or 1 -> 2 across the longest edge of a sliver),
  made on demand where the lighting inside a patch asks for it.

Every node keeps a fixed set of points: ``RECEIVER_POINTS`` receiver quadrature points with
weights (the 7-point degree-5 Dunavant rule on triangles; area-stratified points on the
triangles of a cluster) and ``SOURCE_POINTS`` stratified points that shadow rays aim at.
Points of tessellated spheres and cylinders lie on the true surface (rays hit it).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from .arrays import group_mean, group_sum
from .cluster import SPLIT_BINS, build_tree, split_keys

TRIANGLE, FACE, VOLUME = 0, 1, 2
#: Receiver quadrature points per node (Dunavant's degree-5 rule on triangles).
RECEIVER_POINTS = 7
#: Shadow-ray target points per node.
SOURCE_POINTS = 16
#: Longest-edge^2 / area above which a triangle splits in two across its longest edge.
SLIVER_RATIO = 8.0
#: A point's two coordinates on a triangle (``transfer.pack_place``) are kept as 16-bit integers
#: over [0, 1]: a leaf ten splits below its triangle is 1/1024 of it across, 64 steps.
PLACE_SCALE = 65535.0
#: Two triangles share a plane when their normals' components agree to this (~0.06 degrees)
#: and their centroids' heights along their mean normal to this fraction of the scene
#: diagonal, up to chaining (``planar_groups``).
PLANE_NORMAL_TOL = 1e-3
PLANE_OFFSET_TOL = 1e-5

#: Dunavant's 7-point rule of degree 5: barycentric coordinates (7, 3) and weights (7,).
_A1, _B1 = 0.059715871789770, 0.470142064105115
_A2, _B2 = 0.797426985353087, 0.101286507323456
DUNAVANT7_BARY = np.array([[1 / 3, 1 / 3, 1 / 3],
                           [_A1, _B1, _B1], [_B1, _A1, _B1], [_B1, _B1, _A1],
                           [_A2, _B2, _B2], [_B2, _A2, _B2], [_B2, _B2, _A2]])
DUNAVANT7_WEIGHT = np.array([0.225] + [0.132394152788506] * 3 + [0.125939180544827] * 3)


@dataclass
class Nodes:
    """Struct of arrays over all nodes (N); arrays grow when triangles split.

    Attributes
    ----------
    kind : (N,) int8              TRIANGLE, FACE or VOLUME
    parent : (N,) int32           -1 for the root
    children : (N, 4) int32       child ids, -1 padded (clusters 2, triangles 4 or 2, leaves none)
    patch : (N,) int32            patch of a triangle node (sub-triangles: their patch), -1 for clusters
    lo, hi : (N,) int32           clusters: range in ``order`` of the patches they hold;
                                  triangles: the patch's own position
    area : (N,) float             m^2
    normal : (N, 3) float         unit normal (zero for volume clusters)
    poly : (N, 4, 3) float        form-factor polygon, metres (triangles repeat their last corner)
    fill : (N,) float             area / polygon area (1 for triangles; 0 for volume clusters)
    center : (N, 3) float         bounding-sphere centre, metres
    radius : (N,) float           bounding-sphere radius, metres
    rho_max : (N,) float          largest reflectance (any channel) of the patches below
    emits : (N,) bool             holds an emitting patch
    depth : (N,) int16            triangles: subdivision depth below their patch
    recv_pts, recv_nrm : (N, K, 3) float32   receiver points and their normals
    recv_w : (N, K) float32       their quadrature weights (sum 1)
    src_pts, src_nrm : (N, S, 3) float32     stratified points on the node (buried-share test)
    curve : (N, 7) float          triangles: their patch's true-surface centre (3), axis (3) and
                                  radius (1; 0 for flat patches, see ``project``); clusters 0
    """

    kind: np.ndarray
    parent: np.ndarray
    children: np.ndarray
    patch: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    area: np.ndarray
    normal: np.ndarray
    poly: np.ndarray
    fill: np.ndarray
    center: np.ndarray
    radius: np.ndarray
    rho_max: np.ndarray
    emits: np.ndarray
    depth: np.ndarray
    recv_pts: np.ndarray
    recv_nrm: np.ndarray
    recv_w: np.ndarray
    src_pts: np.ndarray
    src_nrm: np.ndarray
    curve: np.ndarray

    def __len__(self) -> int:
        return len(self.kind)

    @property
    def is_leaf(self) -> np.ndarray:
        """(N,) bool: triangles without children (volume and face clusters always have some)."""
        return self.children[:, 0] < 0

    @property
    def leaves(self) -> np.ndarray:
        return np.flatnonzero(self.is_leaf)

    @property
    def nbytes(self) -> int:
        return sum(getattr(self, f.name).nbytes for f in fields(self))

    def append(self, other: "Nodes") -> None:
        for f in fields(self):
            setattr(self, f.name, np.concatenate([getattr(self, f.name), getattr(other, f.name)]))

    def copy(self) -> "Nodes":
        """A copy whose arrays the copy's owner may change (splits append to them)."""
        return Nodes(**{f.name: getattr(self, f.name).copy() for f in fields(self)})

    def children_of(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every child of nodes ids (M,): (its parent's position in ids (C,), its node id (C,)),
        in the order of ids and then of the children's slots."""
        kids = self.children[ids]
        own, slot = np.nonzero(kids >= 0)
        return own, kids[own, slot].astype(np.int64)

    def splittable(self, min_area: float) -> np.ndarray:
        """(N,) bool: clusters, and triangles larger than ``min_area`` (m^2)."""
        return (self.kind != TRIANGLE) | (self.area > min_area)


# ------------------------------------------------------------------------------------------
# Building the tree over the scene's patches
# ------------------------------------------------------------------------------------------

@dataclass
class Surface:
    """What the hierarchy needs of the scene's patches (P of them).

    verts : (P, 3, 3) float   corners (back sides wound the other way), metres
    normal : (P, 3) float     unit normals
    group_key : (P,) int      shape * 2 + side: planar groups never mix shapes or sides
    rho_max : (P,) float      largest reflectance over channels
    emits : (P,) bool
    curve : ((P, 3), (P, 3), (P,)) true-surface centre, axis and radius (0: flat)
    diagonal : float          scene diagonal, metres
    seed : int
    """

    verts: np.ndarray
    normal: np.ndarray
    group_key: np.ndarray
    rho_max: np.ndarray
    emits: np.ndarray
    curve: tuple
    diagonal: float
    seed: int

    def same_as(self, other: "Surface") -> bool:
        """Whether a tree built over ``other`` is the one this surface would get."""
        arrays = [(self.verts, other.verts), (self.normal, other.normal), (self.group_key, other.group_key),
                  (self.rho_max, other.rho_max), (self.emits, other.emits)]
        arrays += list(zip(self.curve, other.curve))
        return self.diagonal == other.diagonal and self.seed == other.seed and \
            all(np.array_equal(a, b) for a, b in arrays)


def build_nodes(surf: Surface) -> tuple[Nodes, np.ndarray, int]:
    """The hierarchy over the patches: (nodes, order (P,) patches in tree order, root id).

    Node ids: patches 0 .. P-1 (id = patch), then face clusters, then volume clusters.
    """
    p = len(surf.verts)
    area = _tri_area(surf.verts)
    group = planar_groups(surf)
    n_groups = int(group.max()) + 1
    # --- volume tree over the planar groups ----------------------------------------------
    g_area = group_sum(group, area, n_groups)
    g_cent = group_mean(group, surf.verts.mean(axis=1), n_groups, weights=area)
    vtree = build_tree(g_cent, g_area, SPLIT_BINS) if n_groups > 1 else None
    g_rank = np.empty(n_groups, np.int64)
    g_rank[vtree.order if vtree is not None else np.arange(n_groups)] = np.arange(n_groups)
    # --- patches sorted by group in the volume tree's order, then face trees per group ----
    order = np.argsort(g_rank[group], kind="stable")
    counts = np.bincount(group, minlength=n_groups)[np.argsort(g_rank)]
    seg_lo = np.concatenate([[0], np.cumsum(counts)[:-1]])
    seg_hi = seg_lo + counts
    cent = surf.verts.mean(axis=1)
    f_lo, f_hi, f_parent, f_children, order = _segmented_median_tree(cent, order, seg_lo, seg_hi, p)
    n_face = len(f_lo)
    # the root of each group: its first face cluster, or its single patch
    g_root = np.where(counts >= 2, 0, order[seg_lo]).astype(np.int64)
    face_roots = np.flatnonzero(f_parent == -1)
    g_root[counts >= 2] = p + face_roots[np.argsort(f_lo[face_roots])]
    # groups in volume order: g_root is indexed by rank already (seg order)
    n_vol = 0 if vtree is None else len(vtree)
    n = p + n_face + n_vol
    parent = np.full(n, -1, np.int64)
    children = np.full((n, 4), -1, np.int64)
    lo = np.full(n, -1, np.int64)
    hi = np.full(n, -1, np.int64)
    kind = np.full(n, TRIANGLE, np.int8)
    pos = np.empty(p, np.int64)
    pos[order] = np.arange(p)
    lo[:p], hi[:p] = pos, pos + 1
    kind[p:p + n_face] = FACE
    lo[p:p + n_face], hi[p:p + n_face] = f_lo, f_hi
    children[p:p + n_face, :2] = f_children
    has = f_children >= 0
    parent[f_children[has]] = np.repeat(p + np.arange(n_face), 2)[has.ravel()]
    parent[p:p + n_face] = np.where(f_parent >= 0, p + f_parent, -1)
    if vtree is not None:
        # vtree's leaves are group indices (< n_groups) -> the groups' roots (by rank)
        kind[p + n_face:] = VOLUME
        vc = vtree.children.copy()
        leaf = vc < n_groups
        vc[leaf] = g_root[g_rank[vc[leaf]]]
        vc[~leaf] = p + n_face + (vc[~leaf] - n_groups)
        children[p + n_face:, :2] = vc
        parent[vc.ravel()] = np.repeat(p + n_face + np.arange(n_vol), 2)
        parent[p + n_face + np.arange(n_vol)] = np.where(vtree.parent >= 0, p + n_face + vtree.parent - n_groups, -1)
        cum_g = np.concatenate([[0], np.cumsum(counts)])
        lo[p + n_face:] = cum_g[vtree.lo]
        hi[p + n_face:] = cum_g[vtree.hi]
        root = p + n_face
    else:
        root = int(g_root[0])
    nodes = _describe(surf, kind, parent, children, lo, hi, order, area)
    return nodes, order, int(root)


def planar_groups(surf: Surface) -> np.ndarray:
    """(P,) group index: patches of one shape side whose planes agree within tolerance.

    Normals are grouped component by component, then the patches of a normal group by
    their centroids' heights along the group's mean normal, each by chaining sorted values
    (a gap wider than the tolerance starts a new group: ``_chains``). Values equal up to
    rounding, or scattered within the tolerance (a jittered floor), never straddle a bin
    edge, and heights are differences along one normal, so the groups are the same for
    the scene scaled or moved. Curved patches (true-surface radius > 0) each form their
    own group.
    """
    n = surf.normal
    p = len(n)
    curved = surf.curve[2] > 0
    label = np.where(curved, np.arange(p) + 1, 0).astype(np.int64)
    label = np.unique(np.stack([surf.group_key.astype(np.int64), label], 1), axis=0, return_inverse=True)[1].ravel()
    for c in range(3):
        label = _chains(label, n[:, c], PLANE_NORMAL_TOL)
    # heights of the centroids along each normal group's mean normal (area-weighted)
    area = _tri_area(surf.verts)
    count = int(label.max()) + 1 if p else 0
    mean = group_sum(label, n, count, weights=area)
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-300)
    height = np.einsum("pc,pc->p", mean[label], surf.verts.mean(axis=1))
    label = _chains(label, height, PLANE_OFFSET_TOL * surf.diagonal)
    return label.astype(np.int64)


#: A chain of values wider than this many tolerances is split on a grid of the tolerance
#: from its lowest value instead (a continuum, such as a finely tessellated curve, is not one plane).
CHAIN_SPREAD = 16


def _chains(label: np.ndarray, x: np.ndarray, tol: float) -> np.ndarray:
    """Refine groups ``label`` (P,) by the values x (P,): inside each group, sorted values
    whose gaps are at most ``tol`` share a chain; a chain wider than ``CHAIN_SPREAD`` tol is
    cut on a grid of ``tol`` from its lowest value. Returns labels 0 .. G-1, numbered by
    (group, value): the same for values moved or rounded by much less than ``tol``."""
    if not len(x):
        return label
    order = np.lexsort((np.arange(len(x)), x, label))
    xs, ls = x[order], label[order]
    new = np.ones(len(x), bool)
    new[1:] = (ls[1:] != ls[:-1]) | (np.diff(xs) > tol)
    chain = np.cumsum(new) - 1
    starts = np.flatnonzero(new)
    lo = xs[starts]
    hi = np.maximum.reduceat(xs, starts)
    wide = (hi - lo) > CHAIN_SPREAD * tol
    sub = np.where(wide[chain], np.floor((xs - lo[chain]) / tol), 0.0)
    new[1:] |= sub[1:] != sub[:-1]
    out = np.empty(len(x), np.int64)
    out[order] = np.cumsum(new) - 1
    return out


def _segmented_median_tree(cent, order, seg_lo, seg_hi, p):
    """Binary median-split trees inside every segment [seg_lo, seg_hi) of ``order`` at once.

    Returns (lo, hi, parent, children (F, 2), order): F clusters (one less than the patches
    of each segment of two or more); children are patch ids (< p) or p + cluster index.
    """
    order = order.copy()
    lo_l, hi_l, par_l, ch = [], [], [], []
    seg = np.flatnonzero(seg_hi - seg_lo >= 2)
    s_lo, s_hi = seg_lo[seg], seg_hi[seg]
    s_node = np.arange(len(seg))
    lo_l.extend(s_lo); hi_l.extend(s_hi); par_l.extend([-1] * len(seg))
    while len(s_lo):
        counts = s_hi - s_lo
        seg_of = np.repeat(np.arange(len(s_lo)), counts)
        idx = np.repeat(s_lo - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts) + np.arange(counts.sum())
        c = cent[order[idx]]
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        key = split_keys(c, starts, seg_of, SPLIT_BINS)
        perm = np.lexsort((np.arange(len(idx)), key, seg_of))
        order[idx] = order[idx[perm]]
        mid = (s_lo + s_hi) // 2
        nxt_lo, nxt_hi, nxt_node = [], [], []
        for slot, (a, b) in enumerate(((s_lo, mid), (mid, s_hi))):
            single = (b - a) == 1
            ch.append(np.stack([s_node[single], np.full(single.sum(), slot), order[a[single]]], 1))
            many = ~single
            new = len(lo_l) + np.arange(many.sum())
            lo_l.extend(a[many]); hi_l.extend(b[many]); par_l.extend(s_node[many])
            ch.append(np.stack([s_node[many], np.full(many.sum(), slot), p + new], 1))
            nxt_lo.append(a[many]); nxt_hi.append(b[many]); nxt_node.append(new)
        s_lo, s_hi, s_node = (np.concatenate(x) for x in (nxt_lo, nxt_hi, nxt_node))
    f = len(lo_l)
    children = np.full((f, 2), -1, np.int64)
    if ch:
        c = np.concatenate(ch).astype(np.int64)
        children[c[:, 0], c[:, 1]] = c[:, 2]
    return (np.array(lo_l, np.int64), np.array(hi_l, np.int64), np.array(par_l, np.int64), children, order)


def _tri_area(v: np.ndarray) -> np.ndarray:
    return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)


def _hash01(x: np.ndarray) -> np.ndarray:
    """Deterministic uniform numbers in [0, 1) from non-negative integers (lowbias32)."""
    x = np.asarray(x, np.uint64) & np.uint64(0xFFFFFFFF)
    x ^= x >> np.uint64(16)
    x = (x * np.uint64(0x7FEB352D)) & np.uint64(0xFFFFFFFF)
    x ^= x >> np.uint64(15)
    x = (x * np.uint64(0x846CA68B)) & np.uint64(0xFFFFFFFF)
    x ^= x >> np.uint64(16)
    return (x >> np.uint64(8)).astype(np.float64) / float(1 << 24)


def _radical_inverse(k: np.ndarray) -> np.ndarray:
    out = np.zeros(len(k))
    f = 0.5
    k = k.copy()
    while np.any(k):
        out += f * (k & 1)
        k >>= 1
        f *= 0.5
    return out


def _hammersley(count: int, keys: np.ndarray, salt: int) -> tuple[np.ndarray, np.ndarray]:
    """(M, count) u and v: a Hammersley set shifted per key (Cranley-Patterson)."""
    k = np.arange(count)
    su = _hash01(keys * 2654435761 + salt)[:, None]
    sv = _hash01(keys * 2246822519 + salt + 1)[:, None]
    u = ((k + 0.5) / count)[None] + su
    v = _radical_inverse(k)[None] + sv
    return u - np.floor(u), v - np.floor(v)


def _warp(v0, v1, v2, u, v):
    """Uniform points on triangles (..., 3) from u, v in [0, 1) (square-root warp)."""
    su = np.sqrt(u)[..., None]
    return v0 * (1 - su) + v1 * (su * (1 - v[..., None])) + v2 * (su * v[..., None])


def project(points: np.ndarray, normals: np.ndarray, center, axis, radius) -> tuple[np.ndarray, np.ndarray]:
    """Move points (M, K, 3) of tessellated spheres/cylinders onto the true surface.

    ``center``, ``axis`` (M, 3) and ``radius`` (M,) per row (radius 0: flat, unchanged);
    normals follow the true surface, keeping their side.
    """
    curved = radius > 0
    if not curved.any():
        return points, normals
    d = points - center[:, None]
    radial = d - axis[:, None] * np.einsum("mkc,mc->mk", d, axis)[..., None]
    rlen = np.linalg.norm(radial, axis=2, keepdims=True)
    ok = curved[:, None, None] & (rlen > 0)
    direction = radial / np.where(rlen > 0, rlen, 1.0)
    flip = np.where(np.einsum("mkc,mkc->mk", direction, normals)[..., None] < 0, -1.0, 1.0)
    p = np.where(ok, points + direction * (radius[:, None, None] - rlen), points)
    n = np.where(ok, direction * flip, normals)
    return p, n


def _describe(surf, kind, parent, children, lo, hi, order, patch_area) -> Nodes:
    """Geometry, bounds and points of a freshly built tree (patches and clusters)."""
    p = len(surf.verts)
    n = len(kind)
    cum = np.concatenate([[0.0], np.cumsum(patch_area[order])])
    area = np.where(kind == TRIANGLE, 0.0, cum[np.maximum(hi, 0)] - cum[np.maximum(lo, 0)])
    area[:p] = patch_area
    is_cl = np.arange(n) >= p
    # corners of every patch below each cluster, by cumulative sums over ``order``
    cl = np.flatnonzero(is_cl)
    box_lo = _bottom_up(np.concatenate([surf.verts.min(axis=1), np.zeros((n - p, 3))]), children, cl, np.minimum)[cl]
    box_hi = _bottom_up(np.concatenate([surf.verts.max(axis=1), np.zeros((n - p, 3))]), children, cl, np.maximum)[cl]
    normal = np.zeros((n, 3))
    normal[:p] = surf.normal
    face = np.flatnonzero(kind == FACE)
    normal[face] = surf.normal[order[lo[face]]]
    poly = np.zeros((n, 4, 3))
    poly[:p, :3] = surf.verts
    poly[:p, 3] = surf.verts[:, 2]
    fill = np.zeros(n)
    fill[:p] = 1.0
    center = np.zeros((n, 3))
    radius = np.zeros(n)
    center[:p] = surf.verts.mean(axis=1)
    radius[:p] = np.linalg.norm(surf.verts - center[:p, None], axis=2).max(axis=1)
    center[is_cl] = 0.5 * (box_lo + box_hi)
    radius[is_cl] = 0.5 * np.linalg.norm(box_hi - box_lo, axis=1)
    if len(face):
        poly[face], fill[face] = _face_rectangles(surf, order, lo[face], hi[face], normal[face], area[face])
    rho = np.zeros(n)
    emits = np.zeros(n, bool)
    rho[:p], emits[:p] = surf.rho_max, surf.emits
    rho = _bottom_up(rho[:, None], children, cl, np.maximum)[:, 0]
    emits = _bottom_up(emits[:, None], children, cl, np.logical_or)[:, 0]
    patch = np.where(kind == TRIANGLE, np.arange(n), -1)
    nodes = Nodes(kind=kind.astype(np.int8), parent=parent.astype(np.int32), children=children.astype(np.int32),
                  patch=patch.astype(np.int32), lo=lo.astype(np.int32), hi=hi.astype(np.int32), area=area,
                  normal=normal, poly=poly, fill=fill, center=center, radius=radius, rho_max=rho, emits=emits,
                  depth=np.zeros(n, np.int16),
                  recv_pts=np.zeros((n, RECEIVER_POINTS, 3), np.float32),
                  recv_nrm=np.zeros((n, RECEIVER_POINTS, 3), np.float32),
                  recv_w=np.zeros((n, RECEIVER_POINTS), np.float32),
                  src_pts=np.zeros((n, SOURCE_POINTS, 3), np.float32),
                  src_nrm=np.zeros((n, SOURCE_POINTS, 3), np.float32),
                  curve=np.zeros((n, 7)))
    nodes.curve[:p] = np.concatenate([surf.curve[0], surf.curve[1], np.asarray(surf.curve[2])[:, None]], axis=1)
    _triangle_points(nodes, np.arange(p), surf.verts, surf.normal, list(surf.curve), surf.seed)
    if len(cl):
        _cluster_points(nodes, cl, surf, order, cum, patch_area)
    return nodes


def _bottom_up(values: np.ndarray, children: np.ndarray, clusters: np.ndarray, op) -> np.ndarray:
    """Fill rows ``clusters`` of values (N, D) with op over their two children, bottom-up
    (one vectorised step per tree level); other rows must be filled already."""
    done = np.ones(len(values), bool)
    done[clusters] = False
    while not done.all():
        todo = np.flatnonzero(~done)
        c = children[todo, :2]
        ready = todo[done[c[:, 0]] & done[c[:, 1]]]
        c = children[ready, :2]
        values[ready] = op(values[c[:, 0]], values[c[:, 1]])
        done[ready] = True
    return values


def _face_rectangles(surf, order, lo, hi, normal, area):
    """Bounding rectangles in the plane of face clusters: (F, 4, 3) corners (counter-clockwise
    about the normal) and fill = area / rectangle area.

    The rectangle is the smallest of the three aligned with an edge of the cluster's first
    triangle (a grid of triangles is covered exactly)."""
    first = surf.verts[order[lo]]
    counts = hi - lo
    owner = np.repeat(np.arange(len(lo)), counts)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    idx = np.repeat(lo - start, counts) + np.arange(counts.sum())
    corners = surf.verts[order[idx]]                        # (Q, 3, 3): every (cluster, patch) pair
    best = None
    for k in range(3):
        e = first[:, (k + 1) % 3] - first[:, k]
        e = e - normal * np.einsum("fc,fc->f", e, normal)[:, None]
        a1 = e / np.maximum(np.linalg.norm(e, axis=1, keepdims=True), 1e-300)
        a2 = np.cross(normal, a1)
        u = np.einsum("qkc,qc->qk", corners, a1[owner])
        v = np.einsum("qkc,qc->qk", corners, a2[owner])
        # (each cluster's pairs are one run of ``owner``: reduced per run)
        box = [np.minimum.reduceat(u.min(axis=1), start), np.maximum.reduceat(u.max(axis=1), start),
               np.minimum.reduceat(v.min(axis=1), start), np.maximum.reduceat(v.max(axis=1), start)]
        rect_area = (box[1] - box[0]) * (box[3] - box[2])
        if best is None:
            best = (rect_area, a1, a2, box)
        else:
            better = rect_area < best[0] * (1 - 1e-9)
            best = (np.where(better, rect_area, best[0]), np.where(better[:, None], a1, best[1]),
                    np.where(better[:, None], a2, best[2]), [np.where(better, b, c) for b, c in zip(box, best[3])])
    rect_area, a1, a2, (umin, umax, vmin, vmax) = best
    base = normal * np.einsum("fc,fc->f", first[:, 0], normal)[:, None]
    col = lambda x: x[:, None]  # noqa: E731
    rect = np.stack([base + a1 * col(umin) + a2 * col(vmin), base + a1 * col(umax) + a2 * col(vmin),
                     base + a1 * col(umax) + a2 * col(vmax), base + a1 * col(umin) + a2 * col(vmax)], 1)
    fill = np.clip(area / np.maximum(rect_area, 1e-300), 0.0, 1.0)
    return rect, fill


def _triangle_points(nodes: Nodes, ids: np.ndarray, verts: np.ndarray, normal: np.ndarray, curve, seed: int) -> None:
    """Receiver (Dunavant) and source (shifted Hammersley) points of triangle nodes ids."""
    v0, v1, v2 = verts[:, 0][:, None], verts[:, 1][:, None], verts[:, 2][:, None]
    b = DUNAVANT7_BARY
    pts = b[None, :, 0, None] * v0 + b[None, :, 1, None] * v1 + b[None, :, 2, None] * v2
    nrm = np.broadcast_to(normal[:, None], pts.shape)
    pts, nrm = project(pts, nrm, curve[0], curve[1], curve[2])
    nodes.recv_pts[ids] = pts
    nodes.recv_nrm[ids] = nrm
    nodes.recv_w[ids] = DUNAVANT7_WEIGHT[None]
    u, v = _hammersley(SOURCE_POINTS, ids.astype(np.int64) + (seed << 20), 0x51ED)
    sp = _warp(v0, v1, v2, u, v)
    sn = np.broadcast_to(normal[:, None], sp.shape)
    sp, sn = project(sp, sn, curve[0], curve[1], curve[2])
    nodes.src_pts[ids] = sp
    nodes.src_nrm[ids] = sn


def triangle_samples(nodes: Nodes, ids: np.ndarray, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` stratified points (shifted Hammersley) on triangle nodes ids and their
    normals, each (M, count, 3), on the true surface of curved patches (``project``)."""
    v = nodes.poly[ids, :3]
    u, w = _hammersley(count, ids.astype(np.int64) + (seed << 20), 0x0B0E)
    pts = _warp(v[:, 0][:, None], v[:, 1][:, None], v[:, 2][:, None], u, w)
    nrm = np.broadcast_to(nodes.normal[ids][:, None], pts.shape)
    c = nodes.curve[ids]
    return project(pts, nrm, c[:, :3], c[:, 3:6], c[:, 6])


def _cluster_points(nodes: Nodes, ids: np.ndarray, surf: Surface, order, cum, patch_area) -> None:
    """Area-stratified points on the patches of clusters ids (receivers and sources)."""
    for count, pts_name, nrm_name, w_name, salt in ((RECEIVER_POINTS, "recv_pts", "recv_nrm", "recv_w", 0x7A11),
                                                   (SOURCE_POINTS, "src_pts", "src_nrm", None, 0x3C6E)):
        u, v = _hammersley(count, ids.astype(np.int64) + (surf.seed << 20), salt)
        # in the order of their place along the cluster's patches (tree order: neighbours
        # in it are neighbours in space), so that successive points' differences measure
        # how smooth the light over the cluster is (refine.link_values)
        rank = np.argsort(u, axis=1)
        u, v = np.take_along_axis(u, rank, axis=1), np.take_along_axis(v, rank, axis=1)
        lo, hi = nodes.lo[ids].astype(np.int64), nodes.hi[ids].astype(np.int64)
        target = cum[lo][:, None] + u * (cum[hi] - cum[lo])[:, None]
        j = np.clip(np.searchsorted(cum, target, side="right") - 1, lo[:, None], hi[:, None] - 1)
        patch = order[j]
        r = np.clip((target - cum[j]) / np.maximum(patch_area[patch], 1e-300), 0.0, 1.0 - 1e-7)
        tv = surf.verts[patch]                             # (M, K, 3, 3)
        p = _warp(tv[..., 0, :], tv[..., 1, :], tv[..., 2, :], r, v)
        nrm = surf.normal[patch]
        c = [x[patch] for x in surf.curve]
        shape = p.shape
        pp, nn = project(p.reshape(-1, 1, 3), nrm.reshape(-1, 1, 3), c[0].reshape(-1, 3), c[1].reshape(-1, 3),
                         c[2].reshape(-1))
        getattr(nodes, pts_name)[ids] = pp.reshape(shape)
        getattr(nodes, nrm_name)[ids] = nn.reshape(shape)
        if w_name:
            getattr(nodes, w_name)[ids] = 1.0 / count


def flat_nodes(nodes) -> np.ndarray:
    """(N,) bool: triangles and face clusters all of whose points lie in their plane (none of
    their triangles has a true curved surface, ``curve``); volume clusters never."""
    kind = np.asarray(nodes.kind)
    curved = (kind == TRIANGLE) & (np.asarray(nodes.curve)[:, 6] > 0)
    parent = np.asarray(nodes.parent)
    node = np.flatnonzero(curved)
    while len(node):                       # (each curved triangle marks its ancestors)
        node = parent[node]
        node = np.unique(node[node >= 0])
        node = node[~curved[node]]
        curved[node] = True
    return (kind != VOLUME) & ~curved


def cluster_children(kind: np.ndarray, children: np.ndarray) -> np.ndarray:
    """(N, 2) uint32: the two children of each cluster, and each triangle's own id (a
    triangle's children, made by splits, do not matter to where its points lie)."""
    own = np.arange(len(kind), dtype=np.int64)[:, None]
    return np.where(np.asarray(kind)[:, None] != TRIANGLE, np.asarray(children)[:, :2], own).astype(np.uint32)


def split_triangles(nodes: Nodes, ids: np.ndarray, surf: Surface) -> np.ndarray:
    """Give children to triangle leaves ids (midpoint 1 -> 4, slivers 1 -> 2); returns the
    ids that were split. Children are appended to ``nodes``."""
    ids = np.unique(ids)
    ids = ids[(nodes.kind[ids] == TRIANGLE) & (nodes.children[ids, 0] < 0)]
    if not len(ids):
        return ids
    v = nodes.poly[ids, :3]
    len2 = _edge_lengths2(v)
    sliver = len2.max(axis=1) > SLIVER_RATIO * nodes.area[ids]
    q, b = ids[~sliver], ids[sliver]
    kids = [_midpoint_children(nodes.poly[q, :3]), _bisect_children(nodes.poly[b, :3], len2[sliver])]
    counts = np.concatenate([np.full(len(q), 4), np.full(len(b), 2)])
    parents = np.concatenate([q, b])
    new_verts = np.concatenate([kids[0].reshape(-1, 3, 3), kids[1].reshape(-1, 3, 3)])
    owner = np.repeat(parents, counts)
    start = len(nodes)
    m = len(new_verts)
    new_ids = start + np.arange(m)
    slot = np.arange(m) - np.repeat(np.cumsum(counts) - counts, counts)
    nodes.children[owner, slot] = new_ids
    patch = nodes.patch[owner]
    poly = np.concatenate([new_verts, new_verts[:, 2:3]], axis=1)
    center = new_verts.mean(axis=1)
    kid = Nodes(kind=np.full(m, TRIANGLE, np.int8), parent=owner.astype(np.int32),
                children=np.full((m, 4), -1, np.int32), patch=patch.astype(np.int32),
                lo=nodes.lo[owner], hi=nodes.hi[owner], area=_tri_area(new_verts), normal=nodes.normal[owner],
                poly=poly, fill=np.ones(m), center=center,
                radius=np.linalg.norm(new_verts - center[:, None], axis=2).max(axis=1),
                rho_max=nodes.rho_max[owner], emits=nodes.emits[owner], depth=(nodes.depth[owner] + 1).astype(np.int16),
                recv_pts=np.zeros((m, RECEIVER_POINTS, 3), np.float32),
                recv_nrm=np.zeros((m, RECEIVER_POINTS, 3), np.float32),
                recv_w=np.zeros((m, RECEIVER_POINTS), np.float32),
                src_pts=np.zeros((m, SOURCE_POINTS, 3), np.float32),
                src_nrm=np.zeros((m, SOURCE_POINTS, 3), np.float32), curve=nodes.curve[owner])
    nodes.append(kid)
    _triangle_points(nodes, new_ids, new_verts, nodes.normal[new_ids], [c[patch] for c in surf.curve], surf.seed)
    return parents


def _edge_lengths2(v: np.ndarray) -> np.ndarray:
    """(M, 3) squared lengths of the edges v0v1, v1v2, v2v0 of triangles v (M, 3, 3)."""
    edges = np.stack([v[:, 1] - v[:, 0], v[:, 2] - v[:, 1], v[:, 0] - v[:, 2]], 1)
    return np.einsum("nij,nij->ni", edges, edges)


def leaf_holding(nodes: Nodes, tri: np.ndarray, place: np.ndarray, limit: int | None = None) -> np.ndarray:
    """(S,) int64: the leaf below each triangle node tri (S,) that holds the point ``place``
    (S,) uint32 on it (``transfer.pack_place``), following the splits of ``split_triangles``
    down; with ``limit``, no lower than the nodes numbered under it (those made later stop at
    their parent)."""
    node = np.asarray(tri, np.int64).copy()
    limit = len(nodes) if limit is None else limit
    first = nodes.children[node, 0]
    todo = np.flatnonzero((first >= 0) & (first < limit))
    if not len(todo):
        return node
    su = (place[todo] >> 16).astype(np.float64) / PLACE_SCALE
    v = (place[todo] & 0xFFFF).astype(np.float64) / PLACE_SCALE
    bary = np.stack([1.0 - su, su * (1.0 - v), su * v], 1)     # on the node's corners 0, 1, 2
    at = node[todo]
    going = np.arange(len(todo))
    while len(going):
        n, b = at[going], bary[going]
        four = nodes.children[n, 3] >= 0
        # midpoint split: the corner child whose corner's coordinate is over a half, else the middle
        corner = np.where(b[:, 0] >= 0.5, 0, np.where(b[:, 1] >= 0.5, 1, np.where(b[:, 2] >= 0.5, 2, 3)))
        mid = np.where((np.arange(3)[None, :] == corner[:, None]), 2.0 * b - 1.0, 2.0 * b)
        mid[corner == 3] = 1.0 - 2.0 * b[corner == 3][:, [2, 0, 1]]
        slot = corner
        if not four.all():
            # bisected sliver (its longest edge a b halved at m; children (a, m, c), (m, b, c))
            k = np.argmax(_edge_lengths2(nodes.poly[n, :3]), axis=1)
            rot = (np.arange(3)[None, :] + k[:, None]) % 3
            la, lb, lc = np.take_along_axis(b, rot, axis=1).T
            left = la >= lb
            half = np.where(left[:, None], np.stack([la - lb, 2.0 * lb, lc], 1), np.stack([2.0 * la, lb - la, lc], 1))
            slot = np.where(four, corner, np.where(left, 0, 1))
            mid = np.where(four[:, None], mid, half)
        bary[going] = mid
        at[going] = nodes.children[n, slot]
        nxt = nodes.children[at[going], 0]
        going = going[(nxt >= 0) & (nxt < limit)]
    node[todo] = at
    return node


def _midpoint_children(v: np.ndarray) -> np.ndarray:
    m01, m12, m20 = (v[:, 0] + v[:, 1]) / 2, (v[:, 1] + v[:, 2]) / 2, (v[:, 2] + v[:, 0]) / 2
    return np.stack([np.stack([v[:, 0], m01, m20], 1), np.stack([m01, v[:, 1], m12], 1),
                     np.stack([m20, m12, v[:, 2]], 1), np.stack([m01, m12, m20], 1)], 1)


def _bisect_children(v: np.ndarray, len2: np.ndarray) -> np.ndarray:
    k = np.argmax(len2, axis=1)
    rot = (np.arange(3)[None, :] + k[:, None]) % 3
    r = np.take_along_axis(v, rot[:, :, None], axis=1)
    a, b, c = r[:, 0], r[:, 1], r[:, 2]
    m = (a + b) / 2
    return np.stack([np.stack([a, m, c], 1), np.stack([m, b, c], 1)], 1)
