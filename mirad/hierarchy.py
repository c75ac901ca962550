"""Element hierarchy (struct of arrays) and the link arrays between elements.

Roots are the scene's patches (input triangles, plus back sides of two-sided
ones). An element splits 1 -> 4 at its edge midpoints, or 1 -> 2 across its
longest edge when it is a sliver; children keep the parent's orientation.
Element ``i`` has ``first_child[i]`` (or -1 for a leaf) and ``n_children[i]``
children stored contiguously.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

#: Longest-edge^2 / area above which an element splits in two across its longest edge.
SLIVER_RATIO = 8.0


@dataclass
class Elements:
    """All elements of the hierarchy.

    Attributes
    ----------
    verts : (N, 3, 3) float   corners, metres
    patch : (N,) int32        root patch of each element
    parent, first_child : (N,) int32 (-1 for none)
    n_children : (N,) int8
    depth : (N,) int16
    area : (N,) float         m^2
    """

    verts: np.ndarray
    patch: np.ndarray
    parent: np.ndarray
    first_child: np.ndarray
    n_children: np.ndarray
    depth: np.ndarray
    area: np.ndarray
    #: clusters (cluster.py) are element ids first_cluster .. first_cluster + C - 1, sources only
    first_cluster: int = -1
    cluster_children: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))

    @classmethod
    def from_patches(cls, verts: np.ndarray) -> "Elements":
        p = len(verts)
        return cls(
            verts=np.ascontiguousarray(verts, dtype=np.float64),
            patch=np.arange(p, dtype=np.int32),
            parent=np.full(p, -1, np.int32),
            first_child=np.full(p, -1, np.int32),
            n_children=np.zeros(p, np.int8),
            depth=np.zeros(p, np.int16),
            area=triangle_areas(verts),
        )

    def __len__(self) -> int:
        return len(self.area)

    def add_clusters(self, tree) -> None:
        """Append the clusters of a ClusterTree (built over the current roots) as source nodes."""
        c = len(tree)
        p = len(self)
        self.first_cluster = p
        self.cluster_children = tree.children.copy()
        self.parent[:p] = tree.parent_of_patch
        self.verts = np.concatenate([self.verts, np.zeros((c, 3, 3))])
        self.patch = np.concatenate([self.patch, np.zeros(c, np.int32)])
        self.parent = np.concatenate([self.parent, tree.parent.astype(np.int32)])
        # not leaves (first_child >= 0) but never split: their children come from the tree
        self.first_child = np.concatenate([self.first_child, np.zeros(c, np.int32)])
        self.n_children = np.concatenate([self.n_children, np.full(c, 2, np.int8)])
        self.depth = np.concatenate([self.depth, np.zeros(c, np.int16)])
        self.area = np.concatenate([self.area, tree.area])

    def is_cluster(self, ids) -> np.ndarray:
        """(M,) bool: which ids are clusters."""
        ids = np.asarray(ids)
        if self.first_cluster < 0:
            return np.zeros(ids.shape, bool)
        return (ids >= self.first_cluster) & (ids < self.first_cluster + len(self.cluster_children))

    @property
    def is_leaf(self) -> np.ndarray:
        return self.first_child < 0

    @property
    def leaves(self) -> np.ndarray:
        return np.flatnonzero(self.first_child < 0)

    @property
    def centroid(self) -> np.ndarray:
        return self.verts.mean(axis=1)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.verts, self.patch, self.parent, self.first_child,
                                      self.n_children, self.depth, self.area))

    def split(self, ids: np.ndarray) -> np.ndarray:
        """Give children to the given leaf elements; returns the ids that were split."""
        ids = np.unique(ids)
        ids = ids[self.first_child[ids] < 0]
        if len(ids) == 0:
            return ids
        v = self.verts[ids]
        edges = np.stack([v[:, 1] - v[:, 0], v[:, 2] - v[:, 1], v[:, 0] - v[:, 2]], 1)
        len2 = np.einsum("nij,nij->ni", edges, edges)
        sliver = len2.max(axis=1) > SLIVER_RATIO * self.area[ids]

        quad_ids, bin_ids = ids[~sliver], ids[sliver]
        kids_q = _midpoint_children(self.verts[quad_ids])              # (q, 4, 3, 3)
        kids_b = _bisect_children(self.verts[bin_ids], len2[sliver])    # (b, 2, 3, 3)
        start = len(self)
        counts = np.concatenate([np.full(len(quad_ids), 4), np.full(len(bin_ids), 2)])
        parents = np.concatenate([quad_ids, bin_ids]).astype(np.int32)
        firsts = start + np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int32)
        new_verts = np.concatenate([kids_q.reshape(-1, 3, 3), kids_b.reshape(-1, 3, 3)])
        child_parent = np.repeat(parents, counts)

        self.first_child[parents] = firsts
        self.n_children[parents] = counts
        self.verts = np.concatenate([self.verts, new_verts])
        self.patch = np.concatenate([self.patch, self.patch[child_parent]])
        self.parent = np.concatenate([self.parent, child_parent])
        self.first_child = np.concatenate([self.first_child, np.full(len(new_verts), -1, np.int32)])
        self.n_children = np.concatenate([self.n_children, np.zeros(len(new_verts), np.int8)])
        self.depth = np.concatenate([self.depth, self.depth[child_parent] + 1])
        self.area = np.concatenate([self.area, triangle_areas(new_verts)])
        return parents

    def children_pairs(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For each id (already split, or a cluster): (index into ids repeated per child, child ids)."""
        counts = self.n_children[ids].astype(np.int64)
        owner = np.repeat(np.arange(len(ids)), counts)
        offset = np.arange(len(owner)) - np.repeat(np.cumsum(counts) - counts, counts)
        child = self.first_child[ids][owner] + offset
        cluster = self.is_cluster(ids[owner])
        if cluster.any():
            child[cluster] = self.cluster_children[ids[owner][cluster] - self.first_cluster, offset[cluster]]
        return owner, child

    def ancestor_matrix(self, leaves: np.ndarray) -> sp.csr_matrix:
        """(L, N) 0/1 matrix: row l has ones at leaf l and all its ancestors (push down)."""
        rows, cols = [], []
        node = leaves.copy()
        idx = np.arange(len(leaves))
        while len(node):
            rows.append(idx)
            cols.append(node)
            node = self.parent[node]
            keep = node >= 0
            node, idx = node[keep], idx[keep]
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        return sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(leaves), len(self)))


def triangle_areas(verts: np.ndarray) -> np.ndarray:
    """(N,) area of (N, 3, 3) triangles."""
    c = np.cross(verts[:, 1] - verts[:, 0], verts[:, 2] - verts[:, 0])
    return 0.5 * np.linalg.norm(c, axis=1)


def triangle_normals(verts: np.ndarray) -> np.ndarray:
    """(N, 3) unit normals of (N, 3, 3) triangles (zero for degenerate ones)."""
    c = np.cross(verts[:, 1] - verts[:, 0], verts[:, 2] - verts[:, 0])
    norm = np.linalg.norm(c, axis=1, keepdims=True)
    return c / np.where(norm > 0, norm, 1.0)


def _midpoint_children(v: np.ndarray) -> np.ndarray:
    m01, m12, m20 = (v[:, 0] + v[:, 1]) / 2, (v[:, 1] + v[:, 2]) / 2, (v[:, 2] + v[:, 0]) / 2
    return np.stack([
        np.stack([v[:, 0], m01, m20], 1),
        np.stack([m01, v[:, 1], m12], 1),
        np.stack([m20, m12, v[:, 2]], 1),
        np.stack([m01, m12, m20], 1),
    ], 1)


def _bisect_children(v: np.ndarray, len2: np.ndarray) -> np.ndarray:
    # Rotate corners so the longest edge is (a, b); (a, b, c) keeps the orientation.
    k = np.argmax(len2, axis=1)
    rot = (np.arange(3)[None, :] + k[:, None]) % 3
    r = np.take_along_axis(v, rot[:, :, None], axis=1)
    a, b, c = r[:, 0], r[:, 1], r[:, 2]
    m = (a + b) / 2
    return np.stack([np.stack([a, m, c], 1), np.stack([m, b, c], 1)], 1)


def facing(recv_verts: np.ndarray, recv_normal: np.ndarray, src_verts: np.ndarray,
           src_normal: np.ndarray, eps: float) -> np.ndarray:
    """(M,) bool: some corner of each source lies in front of its receiver's plane and vice versa.

    ``eps`` is a distance (relative to the scene size) below which a corner counts as
    in the plane, so coplanar pairs never link (their exact transfer is zero).
    """
    d_src = np.einsum("mkc,mc->mk", src_verts - recv_verts[:, :1], recv_normal)
    d_rcv = np.einsum("mkc,mc->mk", recv_verts - src_verts[:, :1], src_normal)
    return (d_src.max(axis=1) > eps) & (d_rcv.max(axis=1) > eps)


@dataclass
class Links:
    """Links receiver <- source as parallel arrays (one row per link).

    recv, src : (M,) int32 element ids
    ff : (M,) float32         form factor with visibility (receiver-area mean)
    ff_max : (M,) float32     largest unoccluded point form factor over the receiver samples
    vis : (M,) float32        fraction of unoccluded sample rays
    ff_std : (M,) float32     standard deviation of the sampled kernel (with visibility)
    ff_range : (M,) float32   max - min of the unoccluded kernel over samples and receiver corners
    ff_lo : (M,) float32      that minimum (so ff_lo + ff_range is the maximum)
    vclass : (M,) int8        visibility class (shaft.py): 0 partial/unknown, 1 proven visible,
                              2 proven blocked
    """

    recv: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    src: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    ff: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    ff_max: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    vis: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    ff_std: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    ff_range: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    ff_lo: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    vclass: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int8))

    _FIELDS = ("recv", "src", "ff", "ff_max", "vis", "ff_std", "ff_range", "ff_lo", "vclass")

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
        """(N, N) sparse form-factor matrix, duplicates summed: H_recv = F @ B_src."""
        return sp.csr_matrix((self.ff.astype(np.float64), (self.recv, self.src)), shape=(n, n))
