"""The far field of a periodic canopy: light from the images of the scene beyond those a link sums.

A link of a periodic solve (``periodic.image_form_factor``, ``periodic.image_visibility``) carries
the light of its source's 3 x 3 nearest lattice images. What the farther images send is gathered
here after the refinement passes: wrapped cosine rays from every leaf (``hit_patches``), the hits
on far images weighted by the radiosity of the patch they meet, added to the leaves' direct light
and solved again (``far_field``, called by ``core.solve_hierarchical``); see docs/periodic.md.
"""

from __future__ import annotations

import math

import numpy as np

from . import _runtime  # noqa: F401  (LLVM set-up before mitsuba)
from .periodic import IMAGE_RING, PeriodicBox, ray_intersect

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

__all__ = ["far_field", "hit_patches", "periodic_stats", "FAR_RAYS", "FAR_MAX_RAYS", "FAR_SHARE", "FAR_ITERATIONS"]

#: Cosine-weighted rays per leaf that first gather the far field; leaves whose far-field noise
#: exceeds their share of FAR_SHARE get four times as many, up to FAR_MAX_RAYS.
FAR_RAYS = 64
FAR_MAX_RAYS = 4096
#: Share of the tolerance the far field's sampling noise may take (summed over leaves, as the
#: final gather's noise is).
FAR_SHARE = 0.25
#: Solves with the far field's irradiance lagged from the previous one (its gain is
#: rho times the far field's small form factor, so two leave a residual of that squared).
FAR_ITERATIONS = 2


def _cosine_directions(normals: np.ndarray, count: int, rng) -> np.ndarray:
    """(N, count, 3) cosine-weighted unit directions about unit normals (N, 3), stratified
    over a sqrt(count) x sqrt(count) grid per point, jittered, the strata in a random order per
    point (so that they are independent of the order of stratified positions they leave from)."""
    n = len(normals)
    g = int(math.ceil(math.sqrt(count)))
    cell = rng.permuted(np.broadcast_to(np.arange(count), (n, count)), axis=1)
    u1 = ((cell % g) + rng.random((n, count))) / g
    u2 = ((cell // g % g) + rng.random((n, count))) / g
    r, phi = np.sqrt(u1), 2 * np.pi * u2
    local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1 - u1, 0.0))], axis=-1)
    helper = np.where(np.abs(normals[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    t = np.cross(normals, helper)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    b = np.cross(normals, t)
    return local[..., :1] * t[:, None] + local[..., 1:2] * b[:, None] + local[..., 2:] * normals[:, None]


def hit_patches(scene, box: PeriodicBox, origins: np.ndarray, directions: np.ndarray, *, ring: int = IMAGE_RING):
    """The patch each wrapped ray first hits, where the hit lies on an image beyond ``ring``.

    origins, directions : (R, 3) float (internal frame, m; unit directions).
    Returns (R,) int: the patch (``scene.patch_tri``/``patch_side`` index) hit on a far image
    (an image offset (i, j) with max(|i|, |j|) > ring from the ray's cell), -1 where the ray
    escapes or hits a nearer image, -2 where it hits the side of a triangle that has no patch
    (a one-sided surface's back: black).
    """
    from .arrays import MAX_LANES, to_float

    mi_scene = scene.mi_scene
    shapes = list(mi_scene.shapes())
    reg = np.array([int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s))[0]) for s in shapes], np.int64)
    order = np.argsort(reg)
    # face -> triangle per mesh shape (triangles mirad dropped map to -1)
    faces_per = np.array([s.face_count() if s.is_mesh() else 0 for s in shapes], np.int64)
    first = np.concatenate([[0], np.cumsum(faces_per)])
    face_tri = np.full(int(first[-1]), -1, np.int64)
    mesh = np.array([s.is_mesh() for s in shapes])
    ok = mesh[scene.tri_shape]
    face_tri[first[scene.tri_shape[ok]] + scene.tri_face[ok]] = np.flatnonzero(ok)
    front = np.full(len(scene.faces), -2, np.int64)
    back = np.full(len(scene.faces), -2, np.int64)
    side = scene.patch_side
    front[scene.patch_tri[side == 0]] = np.flatnonzero(side == 0)
    back[scene.patch_tri[side == 1]] = np.flatnonzero(side == 1)
    out = np.full(len(origins), -1, np.int64)
    for a in range(0, len(origins), MAX_LANES):
        b = min(len(origins), a + MAX_LANES)
        o = mi.Vector3f(*[to_float(origins[a:b, k]) for k in range(3)])
        d = mi.Vector3f(*[to_float(directions[a:b, k]) for k in range(3)])
        si, di, dj = ray_intersect(mi_scene, box, o, d)
        shape = dr.reinterpret_array(mi.UInt32, si.shape)
        valid = si.is_valid()
        dr.eval(shape, si.prim_index, valid, di, dj, si.n)
        valid = np.asarray(valid.numpy(), bool)
        far = valid & (np.maximum(np.abs(di.numpy()), np.abs(dj.numpy())) > ring)
        s_idx = order[np.clip(np.searchsorted(reg[order], shape.numpy().astype(np.int64)), 0, len(reg) - 1)]
        prim = si.prim_index.numpy().astype(np.int64)
        tri = np.where(mesh[s_idx], face_tri[first[s_idx] + np.minimum(prim, np.maximum(faces_per[s_idx] - 1, 0))],
                       -1)
        # analytic shapes: the triangle of mirad's tessellation nearest the hit
        need = far & (tri < 0)
        if need.any():
            p = si.p.numpy().T.astype(np.float64)[need]
            cen = scene.vertices[scene.faces].mean(axis=1)
            tri_need = np.empty(len(p), np.int64)
            for s in np.unique(s_idx[need]):
                rows = np.flatnonzero(s_idx[need] == s)
                cand = np.flatnonzero(scene.tri_shape == s)
                if not len(cand):
                    tri_need[rows] = -1
                    continue
                dist = np.linalg.norm(p[rows, None] - cen[cand][None], axis=2)
                tri_need[rows] = cand[np.argmin(dist, axis=1)]
            tri[need] = tri_need
        far &= tri >= 0
        t = np.maximum(tri, 0)
        on_front = np.einsum("rc,rc->r", directions[a:b], scene.tri_normal[t]) < 0
        out[a:b] = np.where(far, np.where(on_front, front[t], back[t]), -1)
    return out


def _far_rays(state, leaves: np.ndarray, count: int, salt: int) -> np.ndarray:
    """(len(leaves), count) patch hit on a far image by each of ``count`` wrapped cosine rays
    from stratified points of each leaf (``hit_patches``; -1: none)."""
    from .nodes import triangle_samples

    nodes = state.nodes
    seed = state.settings.seed + 0xFA5 + salt
    pts, nrm = triangle_samples(nodes, leaves, count, seed)
    dirs = _cosine_directions(nodes.normal[leaves], count, np.random.default_rng(seed))
    patch = hit_patches(state.scene, state.periodic, (pts + nrm * state.offset).reshape(-1, 3), dirs.reshape(-1, 3))
    state.rays += patch.size
    return patch.reshape(len(leaves), count)


def far_field(state, solved, solve, reference_mean):
    """Periodic canopies: the light that reaches each leaf from images of the scene beyond the
    (2 IMAGE_RING + 1)^2 that its links sum, gathered by wrapped cosine rays (``hit_patches``),
    added to the leaves' direct light and solved again (FAR_ITERATIONS times, lagged:
    H_far = W B_patch with B from the previous solve).

    Each leaf starts with FAR_RAYS rays; while the summed noise (EXPECTED_ABS A_l se_l, the
    brightest channel's standard error se_l) exceeds FAR_SHARE of the tolerance's power budget,
    the leaves above their area's share of it are traced again with four times the rays (up to
    FAR_MAX_RAYS).

    state, solved : ``core.State`` and ``core.Solved``; solve, reference_mean : ``core.solve`` and
    ``core.reference_mean`` (the estimate's scale, W/m^2).
    Returns (solved, noise (L,) W): the last solve and the far field's noise as power. Without
    a periodic box: (solved, 0.0) unchanged."""
    box = state.periodic
    if box is None:
        return solved, 0.0
    import scipy.sparse as sp
    from .refine import EXPECTED_ABS

    scene, nodes = state.scene, state.nodes
    leaves = solved.leaves
    n_leaf = len(leaves)
    n_patch = len(scene.patch_tri)
    # area-weighted mean radiosity of each patch over its leaves (P, L)
    leaf_patch = nodes.patch[leaves]
    area = nodes.area[leaves]
    total = np.bincount(leaf_patch, weights=area, minlength=n_patch)
    mean = sp.csr_matrix((area / np.maximum(total[leaf_patch], 1e-300), (leaf_patch, np.arange(n_leaf))),
                         shape=(n_patch, n_leaf))
    budget = FAR_SHARE * state.settings.tolerance * state.counted_area * reference_mean(state, solved)
    allowed = budget * area / max(float(area.sum()), 1e-300)

    def noise_of(hits_by_count, b_patch):
        out = np.zeros(n_leaf)
        for count, (rows, patch) in hits_by_count.items():
            per_ray = np.where(patch >= 0, b_patch[np.maximum(patch, 0)], 0.0)
            out[rows] = EXPECTED_ABS * area[rows] * per_ray.std(axis=1, ddof=1) / np.sqrt(count)
        return out

    b_max = (mean @ solved.b_leaf).max(axis=1)
    count = FAR_RAYS
    rows = np.arange(n_leaf)
    hits = {count: (rows, _far_rays(state, leaves, count, 0))}
    noise = noise_of(hits, b_max)
    while noise.sum() > budget and count < FAR_MAX_RAYS:
        again = np.flatnonzero(noise > allowed)
        if not len(again):
            break
        count = min(4 * count, FAR_MAX_RAYS)
        for c, (r, p) in list(hits.items()):        # the leaves traced again leave their old group
            keep = ~np.isin(r, again)
            hits[c] = (r[keep], p[keep])
        hits[count] = (again, _far_rays(state, leaves[again], count, count))
        noise = noise_of(hits, b_max)
    # (L, P): the share of each leaf's rays that met each far patch
    r_all, p_all, w_all = [], [], []
    for c, (r, p) in hits.items():
        hit = p >= 0
        r_all.append(np.repeat(r, c)[hit.ravel()])
        p_all.append(p[hit])
        w_all.append(np.full(int(hit.sum()), 1.0 / c))
    gather = sp.csr_matrix((np.concatenate(w_all), (np.concatenate(r_all), np.concatenate(p_all))),
                           shape=(n_leaf, n_patch))
    base = state.direct[leaves].copy()
    state.far = np.zeros((len(nodes), base.shape[1]))
    for _ in range(FAR_ITERATIONS):
        state.far[leaves] = gather @ (mean @ solved.b_leaf)
        state.direct[leaves] = base + state.far[leaves]
        solved = solve(state, solved)
    b_max = (mean @ solved.b_leaf).max(axis=1)
    noise = noise_of(hits, b_max)
    far = (gather @ b_max)
    state.far_field = {"leaves": int(n_leaf), "rays": int(sum(c * len(r) for c, (r, _) in hits.items())),
                       "most_rays_per_leaf": int(max(c for c, (r, _) in hits.items() if len(r))),
                       "hit_share": float(gather.sum() / n_leaf),
                       "irradiance": float((far * area).sum() / max(float(area.sum()), 1e-300)),
                       "estimated_noise": float(noise.sum() / max(state.counted_area * reference_mean(state, solved),
                                                                  1e-300))}
    return solved, noise


def periodic_stats(state) -> dict | None:
    """``Solution.stats["periodic"]``: the box (user frame), the images a link sums and the far
    field's figures (the leaves it traced from, before the final gather split any; rays traced,
    the most per leaf, the share of them that met a far image, the
    area-weighted mean far-field irradiance of the brightest channel in W/m^2, and its noise
    relative to the estimate's scale), or None for an ordinary solve."""
    box = state.periodic
    if box is None:
        return None
    return {"box": box.describe(state.scene.origin), "images": int(len(box.images())),
            **getattr(state, "far_field", {})}
