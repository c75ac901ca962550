"""A path-traced reference for periodic canopies: per-triangle radiosity or irradiance, rays wrapped.

Mitsuba's own integrators cannot wrap rays around a pattern box, so this is a small path tracer
in Dr.Jit on Mitsuba's geometry, emitters and BSDFs (``diffuse``, ``twosided``, mirad's ``leaf``
with its transmittance): every ray query is ``periodic.ray_intersect``/``ray_test`` (or plain
Mitsuba queries without a box, which is how ``tests/test_periodic.py`` checks it against
Mitsuba's ``path`` integrator on a large tiled copy of the pattern).

Per lane: a point uniform by area on a triangle side, then

``quantity="radiosity"``  the outgoing radiance L_o there (a ray aimed at the point from just
                          above it along the side's normal, as ``reference.triangle_reference``'s
                          "outgoing" method), B = pi L_o, W/m^2;
``quantity="irradiance"`` a cosine-weighted direction over the side's hemisphere, H = pi L_in
                          plus the suns' direct irradiance at the point (a shadow ray each).

The path: at every hit the area emitter's radiance, the suns by next-event estimation (their
``sample_direction``, the BSDF's ``eval``, a wrapped shadow ray), then the BSDF's own ``sample``
(reflection or transmission) for the next ray; skies (``constant``, ``envmap``) are met by the
rays that escape, which is unbiased for them (no next-event estimation, so no double counting).
Russian roulette after ``RR_DEPTH`` bounces, at most ``MAX_DEPTH`` (a path still alive there
carries a throughput of at most rho_max^MAX_DEPTH). Point and spot lights are not handled (a
periodic scene refuses them, ``periodic.check_scene``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from . import _runtime  # noqa: F401  (LLVM set-up before mitsuba)
from .arrays import to_uint, to_vector3
from .errors import SettingsError

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

__all__ = ["PeriodicReference", "periodic_reference"]

#: Paths per Dr.Jit launch.
BATCH = 1 << 19
#: Bounces before Russian roulette.
RR_DEPTH = 4
#: Most bounces of a path.
MAX_DEPTH = 64
#: Ray origins lifted this fraction of the scene diagonal off surfaces.
OFFSET = 1e-4


@dataclass
class PeriodicReference:
    """Per-triangle reference (K, 3) and its standard error (K, 3), W/m^2, of one side.

    ``quantity`` is "radiosity" or "irradiance"; ``triangles`` (K,) the input triangles estimated
    (None: all), ``side`` "front" or "back"; ``paths`` traced in ``seconds``."""

    value: np.ndarray
    stderr: np.ndarray
    quantity: str
    side: str
    triangles: np.ndarray | None
    paths: int
    seconds: float


def _suns(scene) -> list:
    return [e for e in scene.light_emitters if bool(e.flags() & mi.EmitterFlags.Delta)]


def _skies(scene) -> list:
    return [e for e in scene.light_emitters if not bool(e.flags() & mi.EmitterFlags.Delta)]


def _intersect(scene, box, o, d, maxt, active):
    if box is None:
        ray = mi.Ray3f(o, d)
        ray.maxt = maxt
        return scene.mi_scene.ray_intersect(ray, active)
    from .periodic import ray_intersect

    si, _, _ = ray_intersect(scene.mi_scene, box, o, d, maxt, active)
    return si


def _occluded(scene, box, o, d, active):
    if box is None:
        return scene.mi_scene.ray_test(mi.Ray3f(o, d), active)
    from .periodic import ray_test

    return ray_test(scene.mi_scene, box, o, d, None, active)


def _sun_light(scene, box, si, rng, active, *, bsdf=None, normal=None, offset=0.0):
    """Light of every sun at interaction si: outgoing radiance through the BSDF (``bsdf``
    given) or the irradiance on ``normal`` (mi.Color3f), each with a wrapped shadow ray."""
    total = dr.zeros(mi.Color3f, dr.width(active))
    for sun in _suns(scene):
        ds, spec = sun.sample_direction(si, mi.Point2f(rng.next_float32(), rng.next_float32()), active)
        if bsdf is None:
            weight = dr.maximum(dr.dot(normal, ds.d), 0.0)
            o = si.p + normal * offset
        else:
            ctx = mi.BSDFContext()
            weight = bsdf.eval(ctx, si, si.to_local(ds.d), active)
            o = si.spawn_ray(ds.d).o
        seen = active & (ds.pdf > 0) & dr.any(weight > 0)
        blocked = _occluded(scene, box, o, ds.d, seen)
        total += dr.select(seen & ~blocked, spec * weight, 0.0)
    return total


def _sky_radiance(scene, d):
    look = dr.zeros(mi.SurfaceInteraction3f, dr.width(d))
    look.wi = -d
    total = dr.zeros(mi.Color3f, dr.width(d))
    for sky in _skies(scene):
        total += sky.eval(look, True)
    return total


def _trace(scene, box, o, d, maxt, rng, *, count_sky_first: bool, offset: float):
    """Radiance arriving at o from direction d (mi.Color3f per lane), by path tracing."""
    width = dr.width(o)
    beta = dr.full(mi.Color3f, 1.0, width)
    radiance = dr.zeros(mi.Color3f, width)
    active = dr.full(mi.Bool, True, width)
    maxt = mi.Float(maxt)
    for depth in range(MAX_DEPTH):
        si = _intersect(scene, box, o, d, maxt, active)
        escaped = active & ~si.is_valid()
        if depth > 0 or count_sky_first:
            radiance += dr.select(escaped, beta * _sky_radiance(scene, d), 0.0)
        active &= si.is_valid()
        emitter = si.emitter(scene.mi_scene, active)
        radiance += dr.select(active, beta * emitter.eval(si, active), 0.0)
        bsdf = si.bsdf()
        radiance += beta * _sun_light(scene, box, si, rng, active, bsdf=bsdf)
        ctx = mi.BSDFContext()
        bs, weight = bsdf.sample(ctx, si, rng.next_float32(), mi.Point2f(rng.next_float32(), rng.next_float32()),
                                 active)
        beta = beta * weight
        active &= dr.any(weight > 0) & (bs.pdf > 0)
        d_new = si.to_world(bs.wo)
        o = dr.select(active, si.spawn_ray(d_new).o, o)
        d = dr.select(active, d_new, d)
        maxt = dr.full(mi.Float, dr.inf, width)
        if depth + 1 >= RR_DEPTH:
            q = dr.minimum(dr.max(beta), 0.95)
            survive = rng.next_float32() < q
            beta = dr.select(survive, beta / dr.maximum(q, 1e-8), 0.0)
            active &= survive
        dr.eval(o, d, beta, radiance, active, maxt)
        if not dr.any(active):
            break
    return radiance


def periodic_reference(scene, box, *, samples_per_triangle: int = 1024, seed: int = 0,
                       triangles: np.ndarray | None = None, quantity: str = "radiosity", side: str = "front",
                       batch: int = BATCH) -> PeriodicReference:
    """Path-traced radiosity or irradiance of one side of input triangles of a periodic scene.

    Parameters
    ----------
    scene : mirad.Scene
    box : periodic.PeriodicBox (``periodic.box_for``), or None for an ordinary (non-periodic) scene
    samples_per_triangle : paths per triangle
    seed : random seed
    triangles : (K,) int input triangles (default all)
    quantity : "radiosity" (B = pi L_o) or "irradiance" (H, suns included)
    side : "front" (along ``scene.tri_normal``) or "back"

    Returns
    -------
    PeriodicReference: value and stderr (K, 3), W/m^2.
    """
    if quantity not in ("radiosity", "irradiance"):
        raise SettingsError(f"quantity={quantity!r}: choose 'radiosity' or 'irradiance'")
    if side not in ("front", "back"):
        raise SettingsError(f"side={side!r}: choose 'front' or 'back'")
    if int(samples_per_triangle) != samples_per_triangle or samples_per_triangle < 2:
        raise SettingsError(f"samples_per_triangle={samples_per_triangle!r}: give a whole number >= 2")
    t0 = time.perf_counter()
    n = int(samples_per_triangle)
    tris = np.arange(scene.triangle_count) if triangles is None else np.asarray(triangles, np.int64)
    verts = scene.tri_vertices[tris]
    normal = scene.tri_normal[tris] * (1.0 if side == "front" else -1.0)
    offset = OFFSET * scene.diagonal
    k = len(tris)
    total = np.zeros((k, 3))
    total_sq = np.zeros((k, 3))
    count = k * n
    for index, start in enumerate(range(0, count, batch)):
        stop = min(count, start + batch)
        lanes = stop - start
        local = np.arange(start, stop) // n
        first, last = int(local[0]), int(local[-1]) + 1
        idx = to_uint(local - first)
        v0, v1, v2 = (dr.gather(mi.Vector3f, to_vector3(verts[first:last, c]), idx) for c in range(3))
        nrm = dr.gather(mi.Vector3f, to_vector3(normal[first:last]), idx)
        rng = mi.PCG32(lanes, initstate=mi.UInt64(seed * 0x9E3779B9 + index + 1),
                       initseq=dr.arange(mi.UInt64, lanes))
        u1, u2 = rng.next_float32(), rng.next_float32()
        su = dr.sqrt(u1)
        p = v0 * (1 - su) + v1 * (su * (1 - u2)) + v2 * (su * u2)
        if quantity == "radiosity":
            # a ray aimed at the point from just above it: the path from there is L_o
            radiance = _trace(scene, box, p + nrm * offset, -nrm, 2 * offset, rng, count_sky_first=False,
                              offset=offset)
            sample = dr.pi * radiance
        else:
            d = mi.Frame3f(nrm).to_world(mi.warp.square_to_cosine_hemisphere(
                mi.Point2f(rng.next_float32(), rng.next_float32())))
            radiance = _trace(scene, box, p + nrm * offset, d, dr.inf, rng, count_sky_first=True, offset=offset)
            si = dr.zeros(mi.SurfaceInteraction3f, lanes)
            si.p, si.n = p, nrm
            si.sh_frame = mi.Frame3f(nrm)
            sample = dr.pi * radiance + _sun_light(scene, box, si, rng, dr.full(mi.Bool, True, lanes), normal=nrm,
                                                   offset=offset)
        dr.eval(sample)
        values = np.stack([np.asarray(sample[c].numpy(), np.float64) for c in range(3)], axis=1)
        for c in range(3):
            total[:, c] += np.bincount(local, weights=values[:, c], minlength=k)
            total_sq[:, c] += np.bincount(local, weights=values[:, c] ** 2, minlength=k)
    mean = total / n
    var = np.maximum(total_sq / n - mean * mean, 0.0) * n / (n - 1)
    return PeriodicReference(mean, np.sqrt(var / n), quantity, side, None if triangles is None else tris, count,
                             time.perf_counter() - t0)
