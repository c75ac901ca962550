"""Periodic ("infinite") canopies: a horizontal pattern box whose rays wrap around.

A plot of a few plants inside a box [a0, a0 + La] x [b0, b0 + Lb] (the two horizontal axes of
the scene's up axis) stands for an infinite field: the scene repeats with periods La and Lb
along those axes. A ray that leaves the box through a lateral side re-enters at the opposite
side (its origin shifted by one period) and goes on, until it hits a surface or leaves the
scene's vertical extent (above the highest or below the lowest surface nothing can be hit any
more); see docs/periodic.md.

How a user gives the box: ``mirad.solve(scene, core="hierarchical", periodic="xmin,ymin,xmax,ymax")``
(a string or four numbers, metres, in the scene file's frame, along the two horizontal axes of
``periodic_up``: x and y for "+z", x and z for "+y", y and z for "+x"), the CLI's ``--periodic``,
or ``<string name="periodic" value="..."/>`` in the ``radiosity`` integrator of a scene file.

Functions here are the periodic maths shared by the direct light (``emitters.py``), the link
transfers (``transfer.py``) and the periodic path-traced reference (``periodic_reference.py``):

* ``PeriodicBox``: the box in mirad's internal frame, its images and how rays wrap;
* ``check_scene``: the box must contain every shape laterally (else the pattern is not periodic);
* ``ray_test`` / ``ray_intersect``: wrapped ray queries as one ``dr.while_loop`` each.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import _runtime  # noqa: F401  (LLVM set-up before mitsuba)
from .errors import SceneError, SettingsError

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

__all__ = ["PeriodicBox", "parse_box", "box_for", "check_scene", "ray_test", "ray_intersect", "UP_AXES",
           "SLACK", "MAX_WRAPS", "IMAGE_RING"]

#: Accepted names of the up axis (the two other axes are the periodic ones).
UP_AXES = ("+z", "-z", "+y", "-y", "+x", "-x")
#: A shape may stick out of the box laterally by this fraction of the period (rounding of float32
#: vertices on the box's faces, a leaf touching the side); beyond it the scene is refused.
SLACK = 1e-3
#: Safety cap on the wraps of one ray. A ray stops wrapping when its height leaves the scene's
#: vertical extent, which bounds the wraps by (extent / |d_up|) / period; only a ray within
#: about 1/MAX_WRAPS radians of horizontal reaches the cap, and it is then taken as escaped.
MAX_WRAPS = 4096
#: The images of a source that a link sums exactly: offsets (i, j) with |i|, |j| <= IMAGE_RING
#: (3 x 3 cells around the source's own). Light from farther images comes through the far field
#: (``far_field``), gathered by wrapped rays.
IMAGE_RING = 1


def _axes(up: str) -> tuple[int, int, int]:
    """(first horizontal axis, second horizontal axis, up axis) indices for ``up``."""
    k = "xyz".index(up.strip().lower()[-1])
    return tuple(a for a in range(3) if a != k) + (k,)


def parse_box(value, up: str = "+z", *, name: str = "periodic") -> tuple[float, float, float, float] | None:
    """The four numbers (amin, bmin, amax, bmax) of a periodic box given as a string
    "amin,bmin,amax,bmax" or a sequence of four numbers (metres), or None for None/"".

    Raises SettingsError naming ``name`` and the fix on anything else.

    >>> parse_box("-2, -2, 2, 2")
    (-2.0, -2.0, 2.0, 2.0)
    """
    if not isinstance(up, str) or up.strip().lower() not in UP_AXES + ("x", "y", "z"):
        raise SettingsError(f"periodic_up={up!r} is not an axis; give one of {', '.join(UP_AXES)} (the scene's "
                            "vertical axis; the periodic box spans the two others)")
    if value is None or (isinstance(value, str) and not value.strip()):
        return None
    horizontal = "".join("xyz"[a] for a in _axes(up)[:2])
    fix = (f"give {name}=\"{horizontal[0]}min,{horizontal[1]}min,{horizontal[0]}max,{horizontal[1]}max\" in metres "
           f"(the two horizontal axes of up={up}), e.g. \"-2,-2,2,2\"")
    if isinstance(value, str):
        parts = [p for p in value.replace(";", ",").split(",")]
    else:
        try:
            parts = list(value)
        except TypeError:
            raise SettingsError(f"{name}={value!r} is not a box; {fix}") from None
    if len(parts) != 4:
        raise SettingsError(f"{name}={value!r} has {len(parts)} numbers, not 4; {fix}")
    try:
        numbers = [float(p) for p in parts]
    except (TypeError, ValueError):
        raise SettingsError(f"{name}={value!r} holds something that is not a number; {fix}") from None
    if not all(math.isfinite(v) for v in numbers):
        raise SettingsError(f"{name}={value!r} holds a NaN or infinity; {fix}")
    a0, b0, a1, b1 = numbers
    if not (a1 > a0 and b1 > b0):
        raise SettingsError(f"{name}={value!r}: the box is empty ({horizontal[0]}max must exceed "
                            f"{horizontal[0]}min and {horizontal[1]}max {horizontal[1]}min); {fix}")
    return (a0, b0, a1, b1)


@dataclass(frozen=True)
class PeriodicBox:
    """A lateral pattern box in mirad's internal frame (``Scene.to_internal``; metres).

    axes : (3,) int     the two periodic axes and the up axis (indices into x, y, z)
    lower : (2,) float  the box's lower corner along the two periodic axes, m
    size : (2,) float   its periods along them, m
    zmin, zmax : float  the scene's extent along the up axis, m (rays stop wrapping outside it)
    """

    axes: tuple
    lower: tuple
    size: tuple
    zmin: float
    zmax: float

    @property
    def upper(self) -> tuple:
        return (self.lower[0] + self.size[0], self.lower[1] + self.size[1])

    def images(self, ring: int = IMAGE_RING) -> np.ndarray:
        """(I, 3) float: the lattice offsets (i La, j Lb along the periodic axes) of the
        (2 ring + 1)^2 images, (0, 0) first, m."""
        ij = [(0, 0)] + [(i, j) for i in range(-ring, ring + 1) for j in range(-ring, ring + 1) if (i, j) != (0, 0)]
        out = np.zeros((len(ij), 3))
        for n, (i, j) in enumerate(ij):
            out[n, self.axes[0]] = i * self.size[0]
            out[n, self.axes[1]] = j * self.size[1]
        return out

    def wrap_points(self, p: np.ndarray) -> np.ndarray:
        """(N, 3) points moved by whole periods into the box (numpy, m)."""
        p = np.array(p, dtype=np.float64, copy=True)
        for k in range(2):
            a = self.axes[k]
            p[:, a] = self.lower[k] + np.mod(p[:, a] - self.lower[k], self.size[k])
        return p

    def describe(self, origin=None) -> str:
        """The box as text in the user's frame: "x in [-2, 2] m, y in [-2, 2] m"."""
        origin = np.zeros(3) if origin is None else np.asarray(origin, np.float64)
        parts = []
        for k in range(2):
            a = self.axes[k]
            parts.append(f"{'xyz'[a]} in [{self.lower[k] + origin[a]:.6g}, {self.upper[k] + origin[a]:.6g}] m")
        return ", ".join(parts)


def box_for(scene, settings) -> PeriodicBox | None:
    """The validated PeriodicBox of ``settings.periodic`` on ``scene`` (``check_scene``), or None."""
    value = getattr(settings, "periodic", None)
    up = getattr(settings, "periodic_up", "+z")
    box = parse_box(value, up)
    if box is None:
        return None
    if getattr(settings, "core", "hierarchical") != "hierarchical":
        raise SettingsError(f"periodic={value!r} runs on the hierarchical core only; add core='hierarchical' "
                            "(CLI: --core hierarchical)")
    if getattr(settings, "workers", 0) or getattr(settings, "scheduler", None):
        raise SettingsError(f"periodic={value!r} does not run on Dask workers yet (their link waves would not wrap); "
                            "leave workers=0 and scheduler unset")
    axes = _axes(up)
    origin = np.asarray(scene.origin, np.float64)
    lower = (float(box[0] - origin[axes[0]]), float(box[1] - origin[axes[1]]))
    size = (float(box[2] - box[0]), float(box[3] - box[1]))
    lo, hi = scene.bbox
    pad = 1e-4 * max(float(hi[axes[2]] - lo[axes[2]]), 1e-9)
    out = PeriodicBox(axes, lower, size, float(lo[axes[2]]) - pad, float(hi[axes[2]]) + pad)
    check_scene(scene, out)
    return out


def check_scene(scene, box: PeriodicBox) -> None:
    """Refuse a scene the box cannot repeat: a shape (area emitters included) that sticks out of
    the box laterally by more than ``SLACK`` of the period, or a point or spot light (its images
    are not summed). Sun and sky emitters are infinitely far and fine."""
    verts = scene.vertices
    tri_v = verts[scene.faces]                          # (T, 3, 3)
    for s, sid in enumerate(scene.shape_ids):
        pts = tri_v[scene.tri_shape == s].reshape(-1, 3)
        if not len(pts):
            continue
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        for k in range(2):
            a = box.axes[k]
            slack = SLACK * box.size[k]
            if lo[a] < box.lower[k] - slack or hi[a] > box.upper[k] + slack:
                o = scene.origin
                ext = ", ".join(f"{'xyz'[box.axes[q]]} in [{lo[box.axes[q]] + o[box.axes[q]]:.6g}, "
                                f"{hi[box.axes[q]] + o[box.axes[q]]:.6g}] m" for q in range(2))
                raise SceneError(
                    f"shape '{sid}' ({ext}) does not lie inside the periodic box ({box.describe(o)}); "
                    f"a periodic pattern must contain every shape: enlarge the box to hold it (or cut the "
                    f"shape at the box's sides, e.g. a ground plane exactly the box's size)")
    for kind, emitter in zip(scene.light_kinds, scene.light_emitters):
        flags = emitter.flags()
        if bool(flags & mi.EmitterFlags.DeltaPosition):
            eid = emitter.id() or kind
            raise SceneError(f"emitter '{eid}' ({kind}) is a point or spot light, whose periodic images mirad "
                             "does not sum; a periodic scene takes sun (directional), sky (constant, envmap) and "
                             "area emitters: replace it by a small area emitter inside the box")


# ------------------------------------------------------------------------------------------
# Wrapped ray queries (Dr.Jit)
# ------------------------------------------------------------------------------------------

def _into_box(box: PeriodicBox, o):
    """Origins o (mi.Vector3f) moved by whole periods into the box; returns (o, di, dj) with
    the shift in periods (mi.Int32 each) that was *added* to reach the box."""
    shifts = []
    o = mi.Vector3f(o)
    for k in range(2):
        a = box.axes[k]
        lo, size = box.lower[k], box.size[k]
        n = dr.floor((o[a] - lo) * (1.0 / size))
        o[a] = o[a] - n * size
        # (float rounding can leave a point a hair outside)
        o[a] = dr.clip(o[a], lo, lo + size)
        shifts.append(-mi.Int32(n))
    return o, shifts[0], shifts[1]


def _exit_distance(box: PeriodicBox, o, d):
    """Distance along d from o (inside the box) to the lateral side it leaves by, and which
    axis (mi.Bool: the first periodic axis, else the second)."""
    t = []
    for k in range(2):
        a = box.axes[k]
        lo, hi = box.lower[k], box.lower[k] + box.size[k]
        da = d[a]
        safe = dr.select(da == 0, 1.0, da)
        tk = dr.select(da > 0, (hi - o[a]) / safe, dr.select(da < 0, (lo - o[a]) / safe, dr.inf))
        t.append(dr.maximum(tk, 0.0))
    first = t[0] <= t[1]
    return dr.select(first, t[0], t[1]), first


def _vertical_reach(box: PeriodicBox, o, d, maxt):
    """maxt cut at the distance where the ray leaves the scene's vertical extent."""
    u = box.axes[2]
    du = d[u]
    safe = dr.select(du == 0, 1.0, du)
    tv = dr.select(du > 0, (box.zmax - o[u]) / safe, dr.select(du < 0, (box.zmin - o[u]) / safe, dr.inf))
    return dr.minimum(maxt, dr.maximum(tv, 0.0))


def _march(mi_scene, box: PeriodicBox, o, d, maxt, active):
    """Walk rays (o, d) up to maxt through the periodic cells; in each cell one ``ray_test``
    up to the lateral side. Returns (hit mi.Bool, o_cell mi.Vector3f the ray's entry point in
    the cell where it stopped, t_cell mi.Float its length there, di, dj mi.Int32 the periods
    added to the origin)."""
    o, di, dj = _into_box(box, o)
    remaining = _vertical_reach(box, o, d, mi.Float(maxt))
    hit = dr.zeros(mi.Bool, dr.width(o))
    wraps = dr.zeros(mi.UInt32, dr.width(o))
    seg = dr.zeros(mi.Float, dr.width(o))
    a0, a1 = box.axes[0], box.axes[1]
    L0, L1 = box.size

    def cond(o, remaining, active, hit, wraps, di, dj, seg):
        return active

    def body(o, remaining, active, hit, wraps, di, dj, seg):
        t_exit, first = _exit_distance(box, o, d)
        seg = dr.minimum(t_exit, remaining)
        ray = mi.Ray3f(o, d)
        ray.maxt = seg
        blocked = mi_scene.ray_test(ray, active)
        hit = hit | (active & blocked)
        go_on = active & ~blocked & (t_exit < remaining) & (wraps < MAX_WRAPS)
        p = dr.fma(d, t_exit, o)
        step0 = dr.select(go_on & first, dr.select(d[a0] > 0, -1, 1), 0)
        step1 = dr.select(go_on & ~first, dr.select(d[a1] > 0, -1, 1), 0)
        p[a0] = dr.select(go_on & first, dr.select(d[a0] > 0, box.lower[0], box.lower[0] + L0), p[a0])
        p[a1] = dr.select(go_on & ~first, dr.select(d[a1] > 0, box.lower[1], box.lower[1] + L1), p[a1])
        o = dr.select(go_on, p, o)
        remaining = dr.select(go_on, remaining - t_exit, remaining)
        di = di + mi.Int32(step0)
        dj = dj + mi.Int32(step1)
        wraps = wraps + dr.select(go_on, 1, 0)
        return o, remaining, go_on, hit, wraps, di, dj, seg

    o, remaining, active, hit, wraps, di, dj, seg = dr.while_loop(
        state=(o, remaining, mi.Bool(active), hit, wraps, di, dj, seg), cond=cond, body=body)
    return hit, o, seg, di, dj


def ray_test(mi_scene, box: PeriodicBox, o, d, maxt=None, active=True):
    """mi.Bool: whether rays from o (mi.Vector3f) along unit d (mi.Vector3f) are blocked within
    maxt (mi.Float, m; None: unbounded, i.e. until the ray leaves the scene's vertical extent),
    the scene repeating with the box's periods.

    A segment to a point y given in unwrapped coordinates (a source point plus a lattice
    offset) is ``ray_test(o, (y - o) / |y - o|, |y - o|)``: the wraps carry it across the
    box's sides to the image."""
    width = dr.width(o)
    maxt = dr.full(mi.Float, dr.inf, width) if maxt is None else mi.Float(maxt)
    hit, *_ = _march(mi_scene, box, o, d, maxt, dr.full(mi.Bool, True, width) & active)
    return hit


def ray_intersect(mi_scene, box: PeriodicBox, o, d, maxt=None, active=True):
    """The first surface along wrapped rays (see ``ray_test``).

    Returns (si mi.SurfaceInteraction3f in the cell where the ray hit (positions inside the
    box), di, dj mi.Int32: how many periods the hit lies from the ray's origin along the two
    periodic axes, i.e. the hit's unwrapped position is si.p - (di La, dj Lb))."""
    width = dr.width(o)
    maxt = dr.full(mi.Float, dr.inf, width) if maxt is None else mi.Float(maxt)
    active = dr.full(mi.Bool, True, width) & active
    hit, o_cell, seg, di, dj = _march(mi_scene, box, o, d, maxt, active)
    ray = mi.Ray3f(o_cell, d)
    ray.maxt = seg
    si = mi_scene.ray_intersect(ray, active & hit)
    return si, di, dj


# ------------------------------------------------------------------------------------------
# Link transfers over the source's images (transfer.py)
# ------------------------------------------------------------------------------------------

def _offsets(box: PeriodicBox) -> list:
    """The images' lattice offsets as mi.ScalarVector3f (``PeriodicBox.images``)."""
    return [mi.ScalarVector3f(*[float(c) for c in o]) for o in box.images()]


def image_form_factor(box: PeriodicBox, one):
    """A point-to-polygon form factor function like ``transfer._point_form_factor`` (``one``)
    that sums the source's (2 IMAGE_RING + 1)^2 images: the polygon moved by each lattice
    offset, each clipped to the receiver point's tangent half-space."""
    offsets = _offsets(box)

    def summed(buf, x, nx, corners, ns, planar, s, offset):
        total = one(buf, x, nx, corners, ns, planar, s, offset)
        for o in offsets[1:]:
            total = total + one(buf, x, nx, [c + o for c in corners], ns, planar, s, offset)
        return total

    return summed


def image_visibility(mi_scene, box: PeriodicBox, x, nx, y, ny, planar, g_exact, area_s, offset: float, key,
                     source_points: int):
    """One shadow ray per lane from receiver points x (normals nx) to one image of the source
    point y (normal ny), for ``transfer._kernel`` on a periodic scene.

    Every image y + o_I (``PeriodicBox.images``) gets its point-to-point kernel k_I =
    cos_x cos_y / r^2 (planar sources) or the bounded volume kernel g_I = cos_x cos_y A_s /
    (pi r^2 + A_s / S) (volume clusters); one image is picked with probability proportional to
    it (``key``: a per-lane hash) and its visibility v traced by a wrapped segment
    (``ray_test``). The lane's weights are the sums over images, K = sum k_I and G = sum g_I:
    sum(K v) / sum(K) over a link's rays is then the kernel-weighted visibility of all its
    images together (the transfer multiplies it by the summed exact form factor), and G v an
    unbiased estimate of sum g_I v_I. Returns (K, G (mi.Float), traced (mi.Bool), v (mi.Float))."""
    o = x + nx * offset
    ks, gs, targets = [], [], []
    for off in _offsets(box):
        yi = y + off + ny * offset
        d = yi - o
        dist2 = dr.squared_norm(d)
        dist = dr.sqrt(dist2)
        cos_x = dr.dot(d, nx) / dr.maximum(dist, 1e-30)
        cos_y = -dr.dot(d, ny) / dr.maximum(dist, 1e-30)
        valid = (cos_x > 0) & (cos_y > 0) & (dist > 0)
        ks.append(dr.select(valid, cos_x * cos_y / dr.maximum(dist2, 1e-30), 0.0))
        gs.append(dr.select(valid & ~planar, cos_x * cos_y * area_s / (dr.pi * dist2 + area_s * (1.0 / source_points)),
                            0.0))
        targets.append(yi)
    kernel = ks[0]
    g_volume = gs[0]
    for k_i, g_i in zip(ks[1:], gs[1:]):
        kernel = kernel + k_i
        g_volume = g_volume + g_i
    weight = [dr.select(planar, k_i, g_i) for k_i, g_i in zip(ks, gs)]
    total = dr.select(planar, kernel, g_volume)
    from .visibility import to_unit
    u = to_unit(key) * total
    target = mi.Vector3f(targets[0])
    acc = mi.Float(weight[0])
    chosen = dr.zeros(mi.Bool, dr.width(u)) | (u < acc)
    for w_i, t_i in zip(weight[1:], targets[1:]):
        take = ~chosen & (w_i > 0) & (u < acc + w_i)
        target = dr.select(take, t_i, target)
        chosen |= take
        acc = acc + w_i
    # (rounding: u at the very top of the sum keeps the last image with a weight)
    for w_i, t_i in zip(weight, targets):
        target = dr.select(~chosen & (w_i > 0), t_i, target)
    traced = (total > 0) & ((g_exact > 0) | ~planar)
    d = target - o
    dist = dr.norm(d)
    blocked = ray_test(mi_scene, box, o, d / dr.maximum(dist, 1e-30), dist * (1 - 1e-4), traced)
    v = dr.select(traced & ~blocked, 1.0, 0.0)
    return kernel, g_volume, traced, v


# ------------------------------------------------------------------------------------------
# The far field: light from images beyond the linked ones (core.py)
# ------------------------------------------------------------------------------------------

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
    from .arrays import MAX_LANES

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
        o = mi.Vector3f(*[mi.Float(np.ascontiguousarray(origins[a:b, k], np.float32)) for k in range(3)])
        d = mi.Vector3f(*[mi.Float(np.ascontiguousarray(directions[a:b, k], np.float32)) for k in range(3)])
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


def far_field(state, solved, solve):
    """Periodic canopies: the light that reaches each leaf from images of the scene beyond the
    (2 IMAGE_RING + 1)^2 that its links sum, gathered by wrapped cosine rays (``hit_patches``),
    added to the leaves' direct light and solved again (FAR_ITERATIONS times, lagged:
    H_far = W B_patch with B from the previous solve).

    Each leaf starts with FAR_RAYS rays; while the summed noise (EXPECTED_ABS A_l se_l, the
    brightest channel's standard error se_l) exceeds FAR_SHARE of the tolerance's power budget,
    the leaves above their area's share of it are traced again with four times the rays (up to
    FAR_MAX_RAYS).

    state, solved : ``core.State`` and ``core.Solved``; solve : ``core.solve``.
    Returns (solved, noise (L,) W): the last solve and the far field's noise as power. Without
    a periodic box: (solved, 0.0) unchanged."""
    box = state.periodic
    if box is None:
        return solved, 0.0
    import scipy.sparse as sp
    from .core import reference_mean
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
    budget = FAR_SHARE * state.settings.tolerance * state.total_area * reference_mean(state, solved)
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
    for _ in range(FAR_ITERATIONS):
        state.direct[leaves] = base + gather @ (mean @ solved.b_leaf)
        solved = solve(state, solved)
    b_max = (mean @ solved.b_leaf).max(axis=1)
    noise = noise_of(hits, b_max)
    far = (gather @ b_max)
    state.far_field = {"rays": int(sum(c * len(r) for c, (r, _) in hits.items())),
                       "most_rays_per_leaf": int(max(c for c, (r, _) in hits.items() if len(r))),
                       "hit_share": float(gather.sum() / n_leaf),
                       "irradiance": float((far * area).sum() / max(float(area.sum()), 1e-300)),
                       "estimated_noise": float(noise.sum() / max(state.total_area * reference_mean(state, solved),
                                                                  1e-300))}
    return solved, noise


def periodic_stats(state) -> dict | None:
    """``Solution.stats["periodic"]``: the box (user frame), the images a link sums and the far
    field's figures (rays traced, the most per leaf, the share of them that met a far image, the
    area-weighted mean far-field irradiance of the brightest channel in W/m^2, and its noise
    relative to the estimate's scale), or None for an ordinary solve."""
    box = state.periodic
    if box is None:
        return None
    return {"box": box.describe(state.scene.origin), "images": int(len(box.images())),
            **getattr(state, "far_field", {})}
