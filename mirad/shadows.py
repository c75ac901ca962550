"""Soft-shadow textures by convolution (THEORY.md section 5).

For a link receiver <- source, the visible fraction of the source seen from each point y
of the receiver is computed as

    V(y) = 1 - (B' (*) E')(y)

with B' the occluders' hard shadow cast from the source centre onto the receiver plane and
E' the source image mirrored and scaled by b/a (source->occluder distance a, occluder->
receiver distance b). This is exact when source, occluder and receiver lie in parallel
planes (section 5.1). General configurations use the receiver's plane as the virtual
receiver plane, the source projected (from the receiver centre) onto a parallel plane
through its centre, and the occluders sorted into depth layers by the hit distances of
Mitsuba rays; layer visibilities are multiplied (section 5.3).

Texture layout: the texture of a link is an (R, R) grid over the receiver's own
parametrisation y(u, v) = v0 + u (v1 - v0) + v (v2 - v0) (a triangle: texels with
u + v > 1 lie outside; a parallelogram (4, 3) v0 v1 v2 v3: v = v3 - v0 direction), texel
(i, j) centred at u = (i + 1/2)/R, v = (j + 1/2)/R. The convolution is done in that
(possibly sheared) lattice: a linear change of coordinates maps a convolution to a
convolution, and the kernel is rasterised in the same lattice.

Pipeline, all links of a batch at once:

1. occluder masks: one Dr.Jit launch traces, for every link and every texel of the
   receiver grid plus a margin (one kernel half-width, so shadows cast from outside reach
   in), the segment source centre -> texel point with ``mi.Scene.ray_intersect``,
   re-spawned after each hit (``max_hits`` passes): the hit fractions f = a / D along the
   segment are the occluders' depths (central projection from the source centre is the
   hard shadow B' of section 5.1 for any depth);
2. depth layers: hits are binned in 1/f (the penumbra width s (1/f - 1) is linear in 1/f)
   into as many layers as keep each layer's penumbra-width spread within two texels
   (``layers="auto"``, at most ``max_layers``), each layer represented by the harmonic mean
   of its depth range (section 5.3);
3. kernels: the source polygon projected from the receiver centre, mirrored and scaled,
   rasterised with sub-texel supersampling (numpy), weighted by the point-to-point kernel
   seen from the receiver centre (``weighting="kernel"``) or uniformly (``"uniform"``: the
   exact visible fraction of section 5.1), normalised to sum 1;
4. one batched zero-padded FFT convolution (scipy.fft) of every (link, layer) mask with
   its kernel, for two mask sets: all hits and first hits; layers combine as a union
   V = clip(1 - sum_l O_l^first, 0, 1) (default) or a product V = prod_l (1 - O_l^all);
5. predicted error (visibility units, mean over the receiver): the residual penumbra-width
   error of each layer (depth spread and source tilt) over the penumbra it falls on, plus
   the layer-combination error, estimated as the mean difference between the union and
   the product models (the two ends of the correlation between layers; both lie within
   the bounds max(0, sum V_l - (L - 1)) <= V <= min V_l of section 5.3).

Functions here also give a ray-traced reference visibility (``ray_visibility``) and the
glue for the solver (``TextureLinks``, ``apply_texture_links``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft

from . import _runtime  # noqa: F401
from .formfactor import point_to_triangle_dr
from .arrays import MAX_LANES, RAY_OFFSET, scene_diagonal, to_float, to_vector3
from .visibility import hash_u32, opaque_u32, stratified, triangle_point

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

__all__ = ["ShadowTextures", "shadow_textures", "shadow_texture", "ray_visibility", "point_form_factor",
           "prefer_texture",
           "TextureLinks", "apply_texture_links", "texel_uv", "receiver_points", "bilinear",
           "narrowest_penumbra"]

#: Ray origins and ends are moved this fraction of the scene diagonal off the surfaces.
OFFSET = RAY_OFFSET
#: Largest kernel half-width, in texels, as a multiple of the resolution R.
MAX_MARGIN = 1.0
#: Links per batch of textures (memory: masks and spectra of a batch are a few hundred MB).
BATCH_LINKS = 256
#: Kernel supersampling per texel side.
SUPERSAMPLE = 4
#: A depth layer's penumbra-width spread may reach this many texels ("auto" layers).
LAYER_TEXELS = 2.0


# ------------------------------------------------------------------------------------------
# Geometry of the receiver parametrisation
# ------------------------------------------------------------------------------------------

def _edges(verts: np.ndarray):
    """Corner and edge vectors (M, 3) of (M, 3|4, 3) triangles or parallelograms."""
    verts = np.asarray(verts, dtype=np.float64)
    e_u = verts[:, 1] - verts[:, 0]
    e_v = (verts[:, 3] if verts.shape[1] == 4 else verts[:, 2]) - verts[:, 0]
    return verts[:, 0], e_u, e_v


def _frame(src: np.ndarray, rcv: np.ndarray):
    """Receiver corner and edges (M, 3) and its unit normal (M, 3) turned towards the source."""
    o, e_u, e_v = _edges(rcv)
    n = np.cross(e_u, e_v)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    n[np.einsum("mc,mc->m", src.mean(axis=1) - o, n) < 0] *= -1.0
    return o, e_u, e_v, n


def _offset(mi_scene) -> float:
    """Ray offset off the surfaces, metres: OFFSET times the scene diagonal."""
    bbox = mi_scene.bbox()
    return OFFSET * scene_diagonal(np.array([bbox.min, bbox.max], dtype=np.float64))


def texel_uv(resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """(R, R) u and v of the texel centres (index [i, j] -> u_i, v_j).

    >>> u, v = texel_uv(2); float(u[1, 0]), float(v[1, 0])
    (0.75, 0.25)
    """
    c = (np.arange(resolution) + 0.5) / resolution
    return np.meshgrid(c, c, indexing="ij")


def receiver_points(receiver_verts: np.ndarray, resolution: int) -> np.ndarray:
    """(M, R, R, 3) texel centres of receivers (M, 3|4, 3), metres."""
    o, e_u, e_v = _edges(receiver_verts)
    u, v = texel_uv(resolution)
    return o[:, None, None] + u[None, ..., None] * e_u[:, None, None] + v[None, ..., None] * e_v[:, None, None]


def _inside(receiver_verts: np.ndarray, resolution: int) -> np.ndarray:
    """(M, R, R) bool: texel centres inside each receiver (all for parallelograms)."""
    u, v = texel_uv(resolution)
    m = len(receiver_verts)
    if np.asarray(receiver_verts).shape[1] == 4:
        return np.ones((m, resolution, resolution), bool)
    return np.broadcast_to(u + v <= 1.0, (m, resolution, resolution)).copy()


# ------------------------------------------------------------------------------------------
# Results
# ------------------------------------------------------------------------------------------

@dataclass
class ShadowTextures:
    """Shadow textures of M links (numpy).

    texture : (M, R, R) float32     visible fraction of the source per receiver texel, [0, 1]
    point_ff : (M, R, R) float32    unoccluded form factor dA(texel) -> source (Lambert)
    inside : (M, R, R) bool         texel centre inside the receiver
    ff_unoccluded : (M,) float      area mean of point_ff over the receiver
    mean_visibility : (M,) float    point_ff-weighted mean of texture (kernel-weighted)
    ff : (M,) float                 ff_unoccluded * mean_visibility = mean of point_ff * texture
    predicted_error : (M,) float    predicted mean |V - V_true| (visibility units), 1 when the
                                    penumbra exceeds the largest kernel (texture unusable)
    depth_error, combination_error : (M,) float   the two parts of predicted_error
    layers : (M,) int               depth layers used
    penumbra : (M,) float           narrowest layer penumbra width s (1/f - 1), metres
                                    (inf where nothing occludes)
    occluded : (M,) bool            some mask ray hit an occluder
    rays : int                      mask rays traced
    """

    texture: np.ndarray
    point_ff: np.ndarray
    inside: np.ndarray
    ff_unoccluded: np.ndarray
    mean_visibility: np.ndarray
    ff: np.ndarray
    predicted_error: np.ndarray
    depth_error: np.ndarray
    combination_error: np.ndarray
    layers: np.ndarray
    penumbra: np.ndarray
    occluded: np.ndarray
    rays: int

    def __len__(self) -> int:
        return len(self.texture)

    @classmethod
    def concatenate(cls, parts) -> "ShadowTextures":
        return cls(*(np.concatenate([getattr(p, f) for p in parts]) for f in _ST_FIELDS[:-1]),
                   sum(p.rays for p in parts))

    def __getitem__(self, k: int) -> "ShadowTextures":
        sl = slice(k, k + 1)
        return ShadowTextures(*(getattr(self, f)[sl] for f in _ST_FIELDS[:-1]), self.rays)


_ST_FIELDS = ("texture", "point_ff", "inside", "ff_unoccluded", "mean_visibility", "ff", "predicted_error",
              "depth_error", "combination_error", "layers", "penumbra", "occluded", "rays")


# ------------------------------------------------------------------------------------------
# Step 1: mask rays (one Dr.Jit launch per chunk of links)
# ------------------------------------------------------------------------------------------

def _trace_depths(mi_scene, src_centre, o, e_u, e_v, resolution: int, margin: int, max_hits: int,
                  offset: float):
    """Hit fractions f in (0, 1) along source centre -> texel point, (M, G, G, max_hits) float32
    (inf: no hit), G = R + 2 margin; and the number of rays traced."""
    m = len(o)
    g = resolution + 2 * margin
    out = np.full((m, g * g, max_hits), np.inf, np.float32)
    rays = 0
    per_launch = max(1, MAX_LANES // (g * g))
    for start in range(0, m, per_launch):
        stop = min(m, start + per_launch)
        k = stop - start
        lane = dr.arange(mi.UInt32, k * g * g)
        link = lane // (g * g)
        t = lane % (g * g)
        i, j = t // g, t % g
        u = (mi.Float(i) - margin + 0.5) * (1.0 / resolution)
        v = (mi.Float(j) - margin + 0.5) * (1.0 / resolution)
        gat = lambda a: dr.gather(mi.Vector3f, to_vector3(a[start:stop]), link)  # noqa: E731
        c, y = gat(src_centre), gat(o) + gat(e_u) * u + gat(e_v) * v
        d = y - c
        length = dr.norm(d)
        d = d / dr.maximum(length, 1e-30)
        origin = c + d * offset
        remaining = length - 2 * offset
        travelled = mi.Float(offset)
        active = remaining > 0
        hits = []
        for _ in range(max_hits):
            ray = mi.Ray3f(origin, d)
            ray.maxt = dr.maximum(remaining, 0.0)
            si = mi_scene.ray_intersect(ray, mi.RayFlags.Minimal, False, active)
            hit = active & si.is_valid()
            rays += int(dr.count(active)[0]) if dr.width(active) else 0
            f = dr.select(hit, (travelled + si.t) / length, dr.inf)
            step = si.t + offset
            origin = dr.select(hit, origin + d * step, origin)
            travelled = travelled + dr.select(hit, step, 0.0)
            remaining = remaining - dr.select(hit, step, 0.0)
            active = hit & (remaining > 0)
            dr.eval(f, origin, travelled, remaining, active)
            hits.append(f.numpy().reshape(k, g * g))
        out[start:stop] = np.stack(hits, axis=-1)
    return out.reshape(m, g, g, max_hits), rays


# ------------------------------------------------------------------------------------------
# Step 3: kernels (numpy, vectorised over (link, layer) entries)
# ------------------------------------------------------------------------------------------

def _source_image(source_verts, src_centre, recv_centre, n):
    """Source polygon projected from the receiver centre onto the plane ⊥ n through its centre.

    Returns q (M, K, 3) projected corners relative to the source centre, the source height
    D (M,) above the receiver plane and the height spread of the real corners (M,).
    """
    rel = source_verts - recv_centre[:, None]
    h = np.einsum("mkc,mc->mk", rel, n)
    depth = np.einsum("mc,mc->m", src_centre - recv_centre, n)
    proj = recv_centre[:, None] + rel * (depth[:, None] / np.maximum(h, 1e-12))[..., None]
    spread = np.abs(h - depth[:, None]).max(axis=1)
    return proj - src_centre[:, None], depth, spread


def _rasterise_kernels(q2, scale, to_plane, resolution: int, margin: int, weight_fn, active=None):
    """Kernels (E, K, K), K = 2 margin + 1, summing to 1.

    q2 : (E, P, 2) source polygon corners (convex) in a 2D plane frame; scale : (E,) b/a;
    to_plane : (E, 2, 2) maps a (du, dv) texel offset to the 2D plane offset; weight_fn(points
    (E', S, 2), entries (E',)) gives the weights of source points; active : (E,) bool, entries
    to rasterise (the others get a delta). Entries are grouped by kernel size (a loop over at
    most log2(K) size classes): small kernels get SUPERSAMPLE^2 sub-samples per texel on a
    small grid, large ones fewer.
    """
    e = len(q2)
    size = 2 * margin + 1
    kern = np.zeros((e, size, size))
    kern[:, margin, margin] = 1.0
    active = np.ones(e, bool) if active is None else np.asarray(active, bool)
    # half-extent in texels of each kernel
    from_plane = np.linalg.inv(to_plane)
    ext = np.abs(np.einsum("eab,ekb->eka", from_plane, q2 * scale[:, None, None])).max(axis=(1, 2))
    half = np.minimum(np.ceil(ext * resolution).astype(int) + 1, margin)
    size_class = np.ceil(np.log2(np.maximum(half, 1))).astype(int)
    for c in np.unique(size_class[active]):
        sel = np.flatnonzero(active & (size_class == c))
        hb = int(min(margin, 2 ** c))
        ss = SUPERSAMPLE if hb <= 4 else (2 if hb <= 16 else 1)
        kern[sel] = 0.0
        kern[sel, margin - hb: margin + hb + 1, margin - hb: margin + hb + 1] = _raster(
            q2[sel], scale[sel], to_plane[sel], resolution, hb, ss, lambda pts, sel=sel: weight_fn(pts, sel))
    total = kern.sum(axis=(1, 2))
    # a kernel smaller than the sub-samples (hard shadow): a delta at the centre
    empty = total <= 0
    kern[empty, margin, margin] = 1.0
    total[empty] = 1.0
    return kern / total[:, None, None]


def _raster(q2, scale, to_plane, resolution: int, hb: int, ss: int, weight_fn):
    """Unnormalised (E, 2 hb + 1, 2 hb + 1) kernels with ss x ss sub-samples per texel (float32)."""
    e = len(q2)
    size = 2 * hb + 1
    sub = ((np.arange(size * ss) + 0.5) / ss - hb - 0.5) / resolution   # offsets in (u, v)
    du, dv = (x.ravel().astype(np.float32) for x in np.meshgrid(sub, sub, indexing="ij"))
    # plane offsets of the sub-samples, mirrored and scaled by a/b: points of the source image
    a = (-to_plane / scale[:, None, None]).astype(np.float32)            # (E, 2, 2)
    x = a[:, 0, :1] * du + a[:, 0, 1:] * dv                              # (E, S)
    y = a[:, 1, :1] * du + a[:, 1, 1:] * dv
    # convex polygon test with the polygon's orientation
    q2 = q2.astype(np.float32)
    p0, p1 = q2, np.roll(q2, -1, axis=1)
    area2 = np.sum(p0[..., 0] * p1[..., 1] - p1[..., 0] * p0[..., 1], axis=1)
    sign = np.where(area2 >= 0, 1.0, -1.0).astype(np.float32)
    inside = np.ones((e, len(du)), bool)
    for k in range(q2.shape[1]):                                         # polygon edges (3 or 4)
        ex, ey = ((p1[:, k] - p0[:, k]) * sign[:, None]).T
        inside &= ex[:, None] * (y - p0[:, k, 1:]) - ey[:, None] * (x - p0[:, k, :1]) >= 0
    w = np.where(inside, weight_fn(np.stack([x, y], -1)), np.float32(0.0))
    return w.reshape(e, size, ss, size, ss).sum(axis=(2, 4), dtype=np.float64)


# ------------------------------------------------------------------------------------------
# Step 4: batched FFT convolution
# ------------------------------------------------------------------------------------------

def _convolve(masks: np.ndarray, kernels: np.ndarray, resolution: int, margin: int) -> np.ndarray:
    """Linear convolution (zero-padded FFT) of (S, E, G, G) mask sets with (E, K, K) kernels
    (transformed once for all S sets), cropped to the (S, E, R, R) receiver texels."""
    g, k = masks.shape[-1], kernels.shape[-1]
    n = sfft.next_fast_len(g + k - 1, real=True)
    fk = sfft.rfft2(kernels.astype(np.float32), s=(n, n), workers=-1)
    fm = sfft.rfft2(masks, s=(n, n), workers=-1)
    fm *= fk[None]
    full = sfft.irfft2(fm, s=(n, n), workers=-1)
    # full index = mask index + kernel index; kernel centre at index margin, receiver texels at
    # mask indices margin .. margin + R - 1
    return full[..., 2 * margin: 2 * margin + resolution, 2 * margin: 2 * margin + resolution]


# ------------------------------------------------------------------------------------------
# The batched shadow-texture builder
# ------------------------------------------------------------------------------------------

def shadow_textures(mi_scene, source_verts, receiver_verts, resolution: int = 64, *, layers="auto",
                    max_layers: int = 8, max_hits: int = 4, weighting: str = "kernel",
                    combine: str = "union") -> ShadowTextures:
    """Shadow textures of M links receiver <- source.

    Parameters
    ----------
    mi_scene : mi.Scene
        The occluders: every shape of the scene that a segment source centre -> receiver
        point crosses (the source and receiver themselves are skipped by offsets).
    source_verts : (M, 3, 3) or (M, 4, 3) float
        Source triangles or parallelograms (v0 v1 v2 v3 in order), front side towards the
        receiver.
    receiver_verts : (M, 3, 3) or (M, 4, 3) float
        Receivers; the texture covers their (u, v) parametrisation (module docstring).
    resolution : int
        R, texels per side.
    layers : "auto" or int
        Depth layers: "auto" picks the fewest that keep each layer's penumbra-width spread
        within LAYER_TEXELS texels (at most ``max_layers``); an int forces that count.
    max_hits : int
        Occluder surfaces recorded per mask ray (depth layering sees that many).
    weighting : "kernel" or "uniform"
        Source image weighted by the point-to-point kernel from the receiver centre, or
        uniformly (exact visible fraction of section 5.1).
    combine : "union" or "product"
        How depth layers combine: "union" adds the occlusions of first-hit masks (the
        occluders' union as seen from the source centre; exact where layers hide disjoint
        parts of the source, and for one connected occluder split into layers), "product"
        multiplies the layers' visibilities computed from all-hit masks (section 5.3,
        exact where they hide independent parts).

    Returns
    -------
    ShadowTextures
    """
    if combine not in ("union", "product"):
        raise ValueError(f"combine must be 'union' or 'product', not {combine!r}")
    if weighting not in ("kernel", "uniform"):
        raise ValueError(f"weighting must be 'kernel' or 'uniform', not {weighting!r}")
    src = np.asarray(source_verts, dtype=np.float64)
    rcv = np.asarray(receiver_verts, dtype=np.float64)
    if src.ndim == 2:
        src, rcv = src[None], rcv[None]
    m, r = len(src), int(resolution)
    if m > BATCH_LINKS:
        # masks and spectra take ~ links x layers x (R + 2 margin)^2 floats: bound the wave
        options = dict(layers=layers, max_layers=max_layers, max_hits=max_hits, weighting=weighting,
                       combine=combine)
        return ShadowTextures.concatenate([shadow_textures(mi_scene, src[i:i + BATCH_LINKS], rcv[i:i + BATCH_LINKS],
                                                          r, **options) for i in range(0, m, BATCH_LINKS)])
    o, e_u, e_v, n = _frame(src, rcv)
    src_centre = src.mean(axis=1)
    recv_centre = o + (e_u + e_v) * (1 / 3 if rcv.shape[1] == 3 else 0.5)
    offset = _offset(mi_scene)

    # --- source image and sizes --------------------------------------------------------------
    q, depth, tilt = _source_image(src, src_centre, recv_centre, n)
    t1 = e_u / np.maximum(np.linalg.norm(e_u, axis=1, keepdims=True), 1e-300)
    t2 = np.cross(n, t1)
    q2 = np.stack([np.einsum("mkc,mc->mk", q, t1), np.einsum("mkc,mc->mk", q, t2)], -1)   # (M, K, 2)
    s = np.linalg.norm(q2[:, :, None] - q2[:, None], axis=-1).max(axis=(1, 2))           # source width
    to_plane = np.stack([np.stack([np.einsum("mc,mc->m", e_u, t1), np.einsum("mc,mc->m", e_v, t1)], -1),
                         np.stack([np.einsum("mc,mc->m", e_u, t2), np.einsum("mc,mc->m", e_v, t2)], -1)], 1)
    from_plane = np.linalg.inv(to_plane)                                                  # (M, 2, 2)
    texel = np.minimum(np.linalg.norm(e_u, axis=1), np.linalg.norm(e_v, axis=1)) / r

    # --- margin: the largest kernel half-width over links at their shallowest occluders ----
    # first a cheap pass without margin to find the depth range, then the real one
    cap = int(np.ceil(MAX_MARGIN * r))
    probe, _ = _trace_depths(mi_scene, src_centre, o, e_u, e_v, max(8, r // 4), 0, 1, offset)
    f_probe = probe[..., 0].reshape(m, -1)
    f_lo = np.where(np.isfinite(f_probe), f_probe, np.inf).min(axis=1)
    f_lo = np.minimum(f_lo, 0.5)   # unseen shallow occluders at the margin: assume mid-way
    scale_hi = (1 - f_lo) / np.maximum(f_lo, 1e-6)
    extent_uv = np.abs(np.einsum("mab,mkb->mka", from_plane, q2 * scale_hi[:, None, None])).max(axis=(1, 2))
    need = np.ceil(extent_uv * r).astype(int) + 1
    # Links whose penumbra is wider than the largest kernel (a small receiver far below its
    # occluders) get no texture (group -1); the others are computed in groups of like margin,
    # since the widest kernel of a batch sets the mask grid and FFT size of all its links
    group = np.where(need > cap, -1, np.ceil(np.log2(np.maximum(need, 2))).astype(int))
    if len(np.unique(group)) > 1 or group[0] < 0:
        return _in_groups(mi_scene, src, rcv, r, group, f_probe.size,
                          dict(layers=layers, max_layers=max_layers, max_hits=max_hits,
                               weighting=weighting, combine=combine))
    margin = int(min(cap, need.max()))
    hits, rays = _trace_depths(mi_scene, src_centre, o, e_u, e_v, r, margin, max_hits, offset)
    g = r + 2 * margin

    # --- depth layers in 1/f ----------------------------------------------------------------
    inv = np.where(np.isfinite(hits), 1.0 / np.maximum(hits, 1e-9), np.nan).reshape(m, -1)
    occluded = np.isfinite(inv).any(axis=1)
    inv_min = np.where(occluded, np.nanmin(np.where(occluded[:, None], inv, 1.0), axis=1), 2.0)
    inv_max = np.where(occluded, np.nanmax(np.where(occluded[:, None], inv, 1.0), axis=1), 2.0)
    spread_p = s * (inv_max - inv_min)                       # penumbra-width spread, metres
    if layers == "auto":
        n_layers = np.clip(np.ceil(spread_p / (LAYER_TEXELS * texel)), 1, max_layers).astype(int)
    else:
        n_layers = np.full(m, int(layers))
    lmax = int(n_layers.max())
    width = (inv_max - inv_min) / n_layers
    layer_of = np.floor((inv - inv_min[:, None]) / np.where(width > 0, width, 1.0)[:, None])
    layer_of = np.clip(np.nan_to_num(layer_of, nan=-1), -1, n_layers[:, None] - 1).astype(int)
    layer_of[~np.isfinite(inv)] = -1
    # two mask stacks: every hit (product model: layers block independent parts of the
    # source) and the first hit seen from the source centre only (union model: layers
    # block disjoint parts, occlusions add)
    masks = np.zeros((2, m, lmax, g * g), np.float32)
    hit_link, hit_idx = np.nonzero(layer_of >= 0)
    masks[0, hit_link, layer_of[hit_link, hit_idx], hit_idx // max_hits] = 1.0
    first = (hit_idx % max_hits) == 0
    hit_link, hit_idx = hit_link[first], hit_idx[first]
    masks[1, hit_link, layer_of[hit_link, hit_idx], hit_idx // max_hits] = 1.0
    lo = inv_min[:, None] + width[:, None] * np.arange(lmax)[None]      # (M, L) layer 1/f ranges
    hi = lo + width[:, None]
    inv_star = 0.5 * (lo + hi)                                          # harmonic-mean depth
    f_star = 1.0 / inv_star
    scale = np.maximum(inv_star - 1.0, 1e-9)                             # b/a = 1/f - 1

    # --- kernels -----------------------------------------------------------------------------
    rel_c = src_centre - recv_centre                                    # lateral offset of the source
    c2 = np.stack([np.einsum("mc,mc->m", rel_c, t1), np.einsum("mc,mc->m", rel_c, t2)], -1)
    rep = lambda a: np.repeat(a, lmax, axis=0)  # noqa: E731
    c2_e, d_e = rep(c2), rep(depth)

    def weight_fn(pts, sel):
        if weighting == "uniform":
            return np.ones(pts.shape[:2])
        d2 = (d_e[sel, None] ** 2).astype(np.float32)
        c = c2_e[sel].astype(np.float32)
        r2 = d2 + (c[:, None, 0] + pts[..., 0]) ** 2 + (c[:, None, 1] + pts[..., 1]) ** 2
        return (d2 / r2) ** 2

    kernels = _rasterise_kernels(rep(q2), scale.ravel(), rep(to_plane), r, margin, weight_fn,
                                 active=(np.arange(lmax)[None] < n_layers[:, None]).ravel())
    used = np.arange(lmax)[None] < n_layers[:, None]                   # (M, L)
    masks = masks.reshape(2, m * lmax, g, g)
    occl = np.zeros((2, m * lmax, r, r))
    run = np.flatnonzero(used.ravel())                                  # only the layers in use
    occl[0, run] = np.clip(_convolve(masks[:1, run], kernels[run], r, margin)[0], 0.0, 1.0)
    # with one layer, first hits and all hits make the same mask
    multi = np.flatnonzero((used & (n_layers[:, None] > 1)).ravel())
    occl[1] = occl[0]
    if len(multi):
        occl[1, multi] = np.clip(_convolve(masks[1:, multi], kernels[multi], r, margin)[0], 0.0, 1.0)
    occl = occl.reshape(2, m, lmax, r, r)
    v_layers = 1.0 - occl[0]
    v_product = np.prod(v_layers, axis=1)
    v_union = np.clip(1.0 - occl[1].sum(axis=1), 0.0, 1.0)
    vis = v_union if combine == "union" else v_product

    # --- predicted error ---------------------------------------------------------------------
    # combination: the two correlation models (independent / disjoint blocked parts of the
    # source) bracket the usual cases; their difference estimates the combination error
    # (both lie within max(0, sum V_l - (L - 1)) <= V <= min V_l, section 5.3)
    inside = _inside(rcv, r)
    cnt = np.maximum(inside.sum(axis=(1, 2)), 1)
    mean_in = lambda x: np.where(inside, x, 0.0).sum(axis=(1, 2)) / cnt  # noqa: E731
    combination_error = mean_in(np.abs(v_product - v_union))
    penumbra = s[:, None] * (inv_star - 1.0)                            # (M, L) width p_l
    delta = 0.5 * s[:, None] * (hi - lo) + penumbra * tilt[:, None] / np.maximum(f_star * depth[:, None], 1e-12)
    rel_err = np.minimum(1.0, delta / np.maximum(penumbra, texel[:, None]))
    in_pen = ((v_layers > 1e-3) & (v_layers < 1 - 1e-3)).astype(float)  # (M, L, R, R)
    depth_error = mean_in((in_pen * (rel_err * used)[..., None, None]).max(axis=1))
    predicted = depth_error + combination_error

    # --- unoccluded point form factors and means ---------------------------------------------
    point_ff = _texel_ff(src, rcv, n, r)
    ff_unocc = mean_in(point_ff)
    fv = mean_in(point_ff * vis)
    mean_vis = np.where(ff_unocc > 0, fv / np.where(ff_unocc > 0, ff_unocc, 1.0), 1.0)
    return ShadowTextures(vis.astype(np.float32), point_ff.astype(np.float32), inside, ff_unocc, mean_vis, fv,
                          predicted, depth_error, combination_error, n_layers,
                          np.where(occluded, np.where(used, penumbra, np.inf).min(axis=1), np.inf), occluded, rays)


def narrowest_penumbra(mi_scene, source_verts, receiver_verts, probe: int = 8) -> np.ndarray:
    """(M,) width of the sharpest shadow detail on each receiver, metres (inf: no occluder seen):
    s (1/f - 1) for the occluder hit nearest the receiver (largest fraction f along source
    centre -> receiver point) among probe x probe rays per link, s the source's diameter.
    Cheap (one Dr.Jit launch of probe^2 rays per link): tells whether a receiver spans
    several penumbrae, where a texture beats subdivision, before building one."""
    src = np.asarray(source_verts, dtype=np.float64)
    rcv = np.asarray(receiver_verts, dtype=np.float64)
    if len(src) == 0:
        return np.zeros(0)
    o, e_u, e_v = _edges(rcv)
    hits, _ = _trace_depths(mi_scene, src.mean(axis=1), o, e_u, e_v, probe, 0, 1, _offset(mi_scene))
    f = hits[..., 0].reshape(len(src), -1)
    f_max = np.where(np.isfinite(f), f, -np.inf).max(axis=1)
    size = np.linalg.norm(src[:, :, None] - src[:, None], axis=-1).max(axis=(1, 2))
    return np.where(f_max > 0, size * (1.0 / np.maximum(f_max, 1e-9) - 1.0), np.inf)


def _in_groups(mi_scene, src, rcv, r: int, group: np.ndarray, probe_rays: int, options: dict) -> ShadowTextures:
    """``shadow_textures`` of a batch in groups: links of group -1 get no texture (V = 1,
    predicted error 1: unusable), each other group is computed on its own."""
    m = len(src)
    inside = _inside(rcv, r)
    point_ff = _texel_ff(src, rcv, _frame(src, rcv)[3], r)
    ff_unocc = np.where(inside, point_ff, 0.0).sum(axis=(1, 2)) / np.maximum(inside.sum(axis=(1, 2)), 1)
    out = ShadowTextures(np.ones((m, r, r), np.float32), point_ff.astype(np.float32), inside, ff_unocc,
                         np.ones(m), ff_unocc.copy(), np.ones(m), np.ones(m), np.zeros(m), np.zeros(m, int),
                         np.full(m, np.inf), np.ones(m, bool), probe_rays)
    for g in np.unique(group[group >= 0]):
        keep = np.flatnonzero(group == g)
        part = shadow_textures(mi_scene, src[keep], rcv[keep], r, **options)
        for f in _ST_FIELDS[:-1]:
            getattr(out, f)[keep] = getattr(part, f)
        out.rays += part.rays
    return out


def _texel_ff(src: np.ndarray, rcv: np.ndarray, n: np.ndarray, r: int) -> np.ndarray:
    """(M, R, R) unoccluded point form factor from each receiver texel centre (normal n) to its
    source."""
    pts = receiver_points(rcv, r).reshape(-1, 3)
    return point_form_factor(pts, np.repeat(n, r * r, axis=0), np.repeat(src, r * r, axis=0)).reshape(len(src), r, r)


def shadow_texture(mi_scene, source_verts, receiver_verts, resolution: int = 64, **kwargs) -> ShadowTextures:
    """One link: ``shadow_textures`` on (3|4, 3) corner arrays; fields keep a leading axis of 1."""
    return shadow_textures(mi_scene, np.asarray(source_verts)[None], np.asarray(receiver_verts)[None],
                           resolution, **kwargs)


def point_form_factor(points: np.ndarray, normals: np.ndarray, source_verts: np.ndarray) -> np.ndarray:
    """(P,) unoccluded form factor dA(points, normals) -> source triangle or parallelogram (Dr.Jit),
    zero where the point lies behind the source."""
    x, nx = to_vector3(points), to_vector3(normals)
    s0, s1, s2 = (to_vector3(source_verts[:, i]) for i in range(3))
    src_n = dr.cross(s1 - s0, s2 - s0)
    front = dr.dot(src_n, x - s0) > 0
    if source_verts.shape[1] == 4:
        s3 = to_vector3(source_verts[:, 3])
        f = point_to_triangle_dr(x, nx, s0, s1, s2) + point_to_triangle_dr(x, nx, s0, s2, s3)
    else:
        f = point_to_triangle_dr(x, nx, s0, s1, s2)
    f = dr.select(front, f, 0.0)
    dr.eval(f)
    return f.numpy().astype(np.float64)


# ------------------------------------------------------------------------------------------
# Ray-traced reference
# ------------------------------------------------------------------------------------------

def ray_visibility(mi_scene, source_verts, points, normals, *, rays: int = 256, seed: int = 0,
                   weighting: str = "kernel") -> tuple[np.ndarray, np.ndarray]:
    """Visible fraction of a source from points, by shadow rays (Dr.Jit, one launch).

    source_verts : (3, 3) or (4, 3); points, normals : (P, 3). Each point traces ``rays``
    stratified rays to the source; ``weighting="kernel"`` weights each by cos cos / r^2.
    Returns (visibility (P,), standard error (P,)).
    """
    src = np.asarray(source_verts, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    p = len(points)
    offset = _offset(mi_scene)
    lane = dr.arange(mi.UInt32, p * rays)
    pt = lane // rays
    k = lane % rays
    x = dr.gather(mi.Vector3f, to_vector3(points), pt)
    nx = dr.gather(mi.Vector3f, to_vector3(normals), pt)
    key = hash_u32(hash_u32(pt + hash_u32(opaque_u32(seed) + 0x51ED27)) + k * 0x632BE5AB)
    u, v = stratified(k, rays, key)
    s0, s1, s2 = (mi.Vector3f(*map(float, c)) for c in src[:3])
    if len(src) == 4:
        y = s0 + (s1 - s0) * u + (mi.Vector3f(*map(float, src[3])) - s0) * v
    else:
        y = triangle_point(s0, s1, s2, u, v)
    sn = dr.normalize(dr.cross(s1 - s0, s2 - s0))
    if len(src) == 4:
        sn = dr.normalize(dr.cross(s1 - s0, mi.Vector3f(*map(float, src[3])) - s0))
    d = y - x
    dist = dr.norm(d)
    d = d / dr.maximum(dist, 1e-30)
    cos_x = dr.dot(d, nx)
    cos_y = dr.abs(dr.dot(d, sn))
    active = (cos_x > 0) & (dist > 2 * offset)
    ray = mi.Ray3f(x + d * offset, d)
    ray.maxt = dist - 2 * offset
    blocked = mi_scene.ray_test(ray, active)
    w = dr.select(active, cos_x * cos_y / dr.maximum(dist * dist, 1e-30), 0.0) if weighting == "kernel" \
        else dr.select(active, 1.0, 0.0)
    wv = dr.select(blocked, 0.0, w)
    dr.eval(w, wv)
    w_np = w.numpy().reshape(p, rays).astype(np.float64)
    wv_np = wv.numpy().reshape(p, rays).astype(np.float64)
    sw = w_np.sum(axis=1)
    vis = np.where(sw > 0, wv_np.sum(axis=1) / np.where(sw > 0, sw, 1.0), 1.0)
    # standard error of a ratio estimator (stratification makes it conservative)
    wn = w_np / np.where(sw > 0, sw, 1.0)[:, None]
    indicator = np.where(w_np > 0, wv_np / np.where(w_np > 0, w_np, 1.0), 0.0)
    var = np.sum(wn ** 2 * (indicator - vis[:, None]) ** 2, axis=1)
    return vis, np.sqrt(var)


# ------------------------------------------------------------------------------------------
# Decision and solver glue
# ------------------------------------------------------------------------------------------

def prefer_texture(predicted_error, tolerance: float) -> np.ndarray:
    """(M,) bool: links whose texture's predicted error is within ``tolerance`` (visibility units).

    >>> prefer_texture(np.array([0.01, 0.2]), 0.05).tolist()
    [True, False]
    """
    return np.asarray(predicted_error) <= tolerance


@dataclass
class TextureLinks:
    """Links whose visibility is a shadow texture (struct of arrays, K links, R texels a side).

    recv, src : (K,) int32          receiver and source element ids
    visibility : (K, R, R) float32  V over the receiver's (u, v) parametrisation
    point_ff : (K, R, R) float32    unoccluded point form factor at the texels
    inside : (K, R, R) bool         texels inside the receiver
    ff_unoccluded : (K,) float      area-mean unoccluded form factor
    ff : (K,) float                 transfer with visibility: mean over the receiver of point_ff V
                                    (= ff_unoccluded * kernel-weighted mean visibility)
    predicted_error : (K,) float
    penumbra : (K,) float           narrowest penumbra width on the receiver, metres (inf: none)
    """

    recv: np.ndarray
    src: np.ndarray
    visibility: np.ndarray
    point_ff: np.ndarray
    inside: np.ndarray
    ff_unoccluded: np.ndarray
    ff: np.ndarray
    predicted_error: np.ndarray
    penumbra: np.ndarray

    def __len__(self) -> int:
        return len(self.recv)

    @classmethod
    def empty(cls, resolution: int) -> "TextureLinks":
        r = int(resolution)
        return cls(np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros((0, r, r), np.float32),
                   np.zeros((0, r, r), np.float32), np.zeros((0, r, r), bool), np.zeros(0), np.zeros(0), np.zeros(0),
                   np.zeros(0))

    @classmethod
    def concatenate(cls, parts, resolution: int) -> "TextureLinks":
        parts = [p for p in parts if len(p)]
        if not parts:
            return cls.empty(resolution)
        return cls(*(np.concatenate([getattr(p, f) for p in parts]) for f in _TL_FIELDS))

    def select(self, idx) -> "TextureLinks":
        """The links ``idx`` (int array or bool mask)."""
        return TextureLinks(*(getattr(self, f)[idx] for f in _TL_FIELDS))

    @property
    def resolution(self) -> int:
        return self.visibility.shape[1]

    @property
    def nbytes(self) -> int:
        return sum(getattr(self, f).nbytes for f in _TL_FIELDS)

    def detail(self, b_src: np.ndarray, rho: np.ndarray) -> np.ndarray:
        """(K, R, R, C) float32 radiosity detail of each link on its receiver, W/m^2:
        rho * B_s * (F_unocc(texel) V(texel) - ff).

        The link's mean transfer ff is already in its receiver's radiosity; this is how the
        link's light varies around it (shadow and fall-off), with zero mean over the receiver's
        texels, so adding it to the receiver's flat radiosity shows the shadow without moving
        energy. b_src : (K, C) source radiosity; rho : (K, C) receiver reflectance.
        """
        varying = self.point_ff * self.visibility - self.ff[:, None, None].astype(np.float32)
        return (varying[..., None] * (np.asarray(rho) * np.asarray(b_src))[:, None, None, :]).astype(np.float32)

    def irradiance(self, b_src: np.ndarray) -> np.ndarray:
        """(K, R, R, C) irradiance texture, W/m^2, from element radiosity b_src (N, C):
        B_s * F_unocc(texel) * V(texel)."""
        b = np.asarray(b_src)[self.src]
        return (self.point_ff * self.visibility)[..., None] * b[:, None, None, :]

    def mean_irradiance(self, b_src: np.ndarray) -> np.ndarray:
        """(K, C) irradiance averaged over each receiver: B_s * ff (the energy balance)."""
        return self.ff[:, None] * np.asarray(b_src)[self.src]

    def matrix(self, n: int):
        """(N, N) sparse matrix of the links' mean transfers (H_recv = F @ B_src)."""
        import scipy.sparse as sp

        return sp.csr_matrix((self.ff.astype(np.float64), (self.recv, self.src)), shape=(n, n))

    def visibility_at(self, link, uv) -> np.ndarray:
        """(P,) bilinear lookup of V for links ``link`` (P,) int at parameters ``uv`` (P, 2).

        (u, v) are the receiver's parameters (barycentric weights of v1 and v2 for a triangle).
        """
        return self._lookup(self.visibility, link, uv)

    def irradiance_at(self, link, uv, b_src: np.ndarray) -> np.ndarray:
        """(P, C) irradiance B_s F_unocc V at (u, v) on the receiver of links ``link``."""
        link = np.asarray(link)
        g = self._lookup(self.point_ff * self.visibility, link, uv)
        return g[:, None] * np.asarray(b_src)[self.src[link]]

    def _lookup(self, tex, link, uv):
        return bilinear(tex, link, uv)


def bilinear(textures: np.ndarray, index, uv) -> np.ndarray:
    """Bilinear lookup in (K, R, R[, C]) textures over a receiver's (u, v) parametrisation
    (texel [i, j] centred at ((i + 1/2)/R, (j + 1/2)/R); clamped at the borders).

    index : (P,) int, the texture of each point; uv : (P, 2). Returns (P[, C]) float64.

    >>> bilinear(np.arange(4.0).reshape(1, 2, 2), [0, 0], [[0.25, 0.25], [0.5, 0.5]]).tolist()
    [0.0, 1.5]
    """
    r = textures.shape[1]
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    index = np.broadcast_to(np.asarray(index), (len(uv),))
    x = np.clip(uv * r - 0.5, 0.0, r - 1.0)
    i0 = np.minimum(np.floor(x).astype(int), r - 2 if r > 1 else 0)
    t = x - i0
    i1 = np.minimum(i0 + 1, r - 1)
    if textures.ndim == 4:
        t = t[:, :, None]
    a = textures[index, i0[:, 0], i0[:, 1]] * (1 - t[:, 1]) + textures[index, i0[:, 0], i1[:, 1]] * t[:, 1]
    b = textures[index, i1[:, 0], i0[:, 1]] * (1 - t[:, 1]) + textures[index, i1[:, 0], i1[:, 1]] * t[:, 1]
    return (a * (1 - t[:, 0]) + b * t[:, 0]).astype(np.float64)


_TL_FIELDS = ("recv", "src", "visibility", "point_ff", "inside", "ff_unoccluded", "ff", "predicted_error",
              "penumbra")


def apply_texture_links(problem, mask, *, resolution: int = 32, tolerance: float | None = None,
                        **kwargs) -> tuple[TextureLinks, np.ndarray]:
    """Shadow textures for the links ``problem.links`` selected by ``mask`` (M,) bool.

    Cluster sources are skipped. Returns (TextureLinks of the accepted links, accepted (M,)
    bool over all links); with ``tolerance`` only links whose predicted error is within it
    are accepted (the others stay ray links), else every selected element link is.
    """
    links = problem.links
    e = problem.elements
    mask = np.asarray(mask, bool) & ~e.is_cluster(links.src)
    idx = np.flatnonzero(mask)
    accepted = np.zeros(len(links), bool)
    if len(idx) == 0:
        return TextureLinks.empty(resolution), accepted
    tex = shadow_textures(problem.scene.mi_scene, e.verts[links.src[idx]], e.verts[links.recv[idx]],
                          resolution, **kwargs)
    keep = np.ones(len(idx), bool) if tolerance is None else prefer_texture(tex.predicted_error, tolerance)
    accepted[idx[keep]] = True
    return TextureLinks(links.recv[idx[keep]].astype(np.int32), links.src[idx[keep]].astype(np.int32),
                        tex.texture[keep], tex.point_ff[keep], tex.inside[keep], tex.ff_unoccluded[keep],
                        tex.ff[keep], tex.predicted_error[keep], tex.penumbra[keep]), accepted
