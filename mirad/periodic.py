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
* ``ray_test`` / ``ray_intersect``: wrapped ray queries as one ``dr.while_loop`` each;
* ``image_form_factor`` / ``image_visibility``: a link's transfer summed over the source's images.

The light of images beyond those a link sums is gathered by ``far_field.py``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import _runtime  # noqa: F401  (LLVM set-up before mitsuba)
from .arrays import shadow_ray_length
from .errors import SceneError, SettingsError

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

__all__ = ["PeriodicBox", "parse_box", "box_for", "check_scene", "ray_test", "ray_intersect", "image_form_factor",
           "image_visibility", "UP_AXES", "SLACK", "MAX_WRAPS", "IMAGE_RING"]

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
#: (``far_field.py``), gathered by wrapped rays.
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
    tri_v = scene.vertices[scene.faces]                 # (T, 3, 3)
    n_shapes = len(scene.shape_ids)
    shape_lo = np.full((n_shapes, 3), np.inf)
    shape_hi = np.full((n_shapes, 3), -np.inf)
    np.minimum.at(shape_lo, scene.tri_shape, tri_v.min(axis=1))
    np.maximum.at(shape_hi, scene.tri_shape, tri_v.max(axis=1))
    for s, sid in enumerate(scene.shape_ids):           # (one check per shape, not per triangle)
        lo, hi = shape_lo[s], shape_hi[s]
        if not np.all(np.isfinite(lo)):
            continue
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


def image_visibility(mi_scene, box: PeriodicBox, x, nx, y, ny, planar, g_exact, tri_corners, per_area,
                     offset: float, key, volume_sample):
    """One shadow ray per lane from receiver points x (normals nx) to one image of the source
    point y (normal ny), for ``transfer._lanes`` on a periodic scene.

    Every image y + o_I (``PeriodicBox.images``) gets its point-to-point kernel k_I =
    cos_x cos_y / r^2 (planar sources) or, for volume clusters, the sample g_I of
    ``volume_sample`` (``transfer.volume_sample``: the exact form factor of the image of the sampled triangle,
    ``tri_corners``, times the cluster's area over the triangle's, ``per_area``); one image is picked with probability proportional to
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
        gs.append(volume_sample(x, nx, ny, [c + off for c in tri_corners], per_area, planar, offset))
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
    blocked = ray_test(mi_scene, box, o, d / dr.maximum(dist, 1e-30), shadow_ray_length(dist, offset), traced)
    v = dr.select(traced & ~blocked, 1.0, 0.0)
    return kernel, g_volume, traced, v
