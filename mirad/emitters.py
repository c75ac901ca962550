"""Direct light from emitters that are not scene surfaces: point, spot, directional, environment.

Each element receives the irradiance of every such emitter, estimated at
stratified points with one shadow ray per sample and emitter. Point, spot and
directional lights are sampled with Mitsuba's own ``Emitter.sample_direction`` (so
falloff and spot profiles are Mitsuba's). Skies (non-delta infinite emitters:
``constant``, ``envmap``) are sampled by the receiver's cosine instead, with
directions stratified per element (``sky_sample``): a ``constant`` sky by the cosine
lobe alone (an unoccluded point then has zero variance), an ``envmap`` by a mixture
of the cosine lobe folded into the map's upper hemisphere (weight ``SKY_COSINE``)
and the map's own ``sample_direction`` (the rest, so a bright sun in a map or
light below its horizon is still found), each sample weighted by the mixture's pdf.
HR then carries the reflected light: B = E + rho * (H_direct + H_gathered).

A band scene (``mirad.bands``; ``scene.light_band_scale`` (E, C)) gets C channels instead of RGB:
each emitter is sampled once per point, its RGB mean taken, and that grey irradiance weighed by
the emitter's factor in each band, so every band shares the same points, directions and shadow rays.
"""

from __future__ import annotations

import math

import numpy as np

from . import _runtime  # noqa: F401
from .arrays import MAX_LANES, RAY_OFFSET, shadow_ray_length, to_float, to_uint, to_vector3
from .visibility import count_true, hash_u32, opaque_u32, project_to_surface, stratified, to_unit, triangle_point

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

#: Share of an envmap's samples drawn from the receiver's cosine lobe folded into the map's
#: upper hemisphere; the rest use the map's own importance sampling (``sky_sample``).
SKY_COSINE = 0.75
#: Multipliers for the per-element permutation of direction strata (one coprime to the count is used).
_PERMUTE = (2654435761, 2246822519, 3266489917, 668265263, 374761393)


def is_sky(emitter) -> bool:
    """True for an emitter sampled as a sky here: infinite and not a delta direction (constant, envmap)."""
    flags = emitter.flags()
    return bool(flags & mi.EmitterFlags.Infinite) and not bool(flags & mi.EmitterFlags.Delta)


def sky_up(emitter) -> np.ndarray | None:
    """(3,) float: the world direction of an ``envmap``'s local +y (its zenith), None for other skies."""
    params = mi.traverse(emitter)
    if emitter.class_name() != "EnvironmentMapEmitter":
        return None
    if "to_world" not in params.keys():
        return np.array([0.0, 1.0, 0.0])
    m = params["to_world"].matrix
    m = np.array(m.numpy() if hasattr(m, "numpy") else m, dtype=np.float64).reshape(4, 4)
    up = m[:3, 1]
    return up / np.linalg.norm(up)


def _permuted(k, n: int, key):
    """Stratum of sample k (of n) after a per-key random shift of a fixed coprime stride: every
    stratum once per element, and each sample's stratum uniform over the n strata."""
    stride = next(a for a in _PERMUTE if math.gcd(a % n or 1, n) == 1) % n or 1
    shift = hash_u32(key ^ 0x3C6EF372) % n
    return mi.UInt32((mi.UInt64(k) * stride + mi.UInt64(shift)) % n)


def sky_sample(emitter, si, nn, k, n: int, key, up):
    """Directions and irradiance weights of one sample per lane for a sky emitter.

    si : mi.SurfaceInteraction3f at the receiver points; nn : their normals (mi.Vector3f);
    k : sample index in 0..n-1 of each lane (mi.UInt32), key : per-element hash (mi.UInt32);
    up : (3,) float world zenith of an envmap (``sky_up``), None for a ``constant`` sky.
    Returns (d mi.Vector3f unit directions towards the sky, w mi.Color3f = L(d) cos / pdf(d),
    W/m^2, zero where the sample is useless). The 2D sample is stratified over n strata,
    permuted per element (``_permuted``), and jittered per lane.
    """
    gx = int(math.ceil(math.sqrt(n)))
    gy = int(math.ceil(n / gx))
    cell = _permuted(k, gx * gy, key)
    u2 = mi.Point2f((mi.Float(cell % gx) + to_unit(hash_u32(key ^ (k * 0x2C1B3C6D + 0x297A2D39)))) * (1.0 / gx),
                    (mi.Float(cell // gx) + to_unit(hash_u32(key ^ (k * 0x85EBCA77 + 0x1B873593)))) * (1.0 / gy))
    frame = mi.Frame3f(nn)
    d_cos = frame.to_world(mi.warp.square_to_cosine_hemisphere(u2))
    cos = dr.dot(nn, d_cos)
    if up is None:
        # constant sky: the cosine lobe alone, pdf cos / pi
        d, pdf = d_cos, cos * dr.inv_pi
    else:
        zenith = mi.Vector3f(*[float(c) for c in up])
        # fold the lobe's part below the map's horizon up into the sky: pdf (n.d)+ + (n'.d)+ over pi
        b = dr.dot(d_cos, zenith)
        d_fold = dr.select(b < 0, d_cos - 2 * b * zenith, d_cos)
        pick = to_unit(hash_u32(key ^ (k * 0x68E31DA4 + 0x5BD1E995))) < SKY_COSINE
        ds_e, _ = emitter.sample_direction(si, u2, True)
        d = dr.select(pick, d_fold, ds_e.d)
        mirrored = nn - 2 * dr.dot(nn, zenith) * zenith
        p_fold = dr.select(dr.dot(d, zenith) > 0,
                           (dr.maximum(dr.dot(nn, d), 0) + dr.maximum(dr.dot(mirrored, d), 0)) * dr.inv_pi, 0.0)
        query = dr.zeros(mi.DirectionSample3f, dr.width(d))
        query.d = d
        pdf = SKY_COSINE * p_fold + (1 - SKY_COSINE) * emitter.pdf_direction(si, query, True)
        cos = dr.dot(nn, d)
    look = dr.zeros(mi.SurfaceInteraction3f, dr.width(d))
    look.wi = -d
    radiance = emitter.eval(look, True)
    w = dr.select((cos > 0) & (pdf > 0), radiance * cos / dr.select(pdf > 0, pdf, 1.0), 0.0)
    return d, w


def direct_irradiance(scene, verts: np.ndarray, normals: np.ndarray, curve, *, samples: int,
                      seed: int, keys: np.ndarray, with_error: bool = False, periodic=None,
                      with_spread: bool = False, with_delta_spread: bool = False):
    """Mean direct irradiance (n, C), W/m^2, over triangles verts (n, 3, 3): C = 3 (RGB), or the
    bands of a band scene (``scene.light_band_scale`` (E, C): each emitter's RGB mean times its
    factor in each band).

    Returns (H, rays), or with ``with_error`` (H, standard error of H (n, C), rays): the
    stratified points' collapsed-strata estimate (``stratified_error``; at most the i.i.d. one
    below, which bounds a stratified mean's variance and is exactly zero where every point
    agrees, as at a probe's tiny triangle), and under a sky at least what the sky would bring
    unoccluded over ``samples`` (a feature smaller than one stratum, or a thin band of sky, may be
    missed by every sample). With ``with_spread`` also, after it, the points' i.i.d. standard
    error (their sample standard deviation over sqrt(samples)): how much the light varies over
    the triangle, which decides where a point or spot light's field needs smaller triangles.
    ``periodic``: a ``periodic.PeriodicBox`` whose sides the shadow rays wrap around, or None.
    With ``with_delta_spread``, (H, error, spread, the same spread of the point, spot and
    directional lights' part of H alone (n, C), rays): how much their light varies over the
    triangle, without a sky's noise of drawn directions.
    """
    n = len(verts)
    bands = getattr(scene, "light_band_scale", None)
    channels = 3 if bands is None else bands.shape[1]
    out = np.zeros((n, channels))
    err = np.zeros((n, channels))
    spread = np.zeros((n, channels))
    delta_spread = np.zeros((n, channels))
    rays = 0
    per_launch = max(1, MAX_LANES // samples)
    for start in range(0, n, per_launch):
        stop = min(n, start + per_launch)
        h, e, f, d, r = _direct_kernel(scene, verts[start:stop], normals[start:stop],
                                       [c[start:stop] for c in curve], samples, seed, keys[start:stop], periodic)
        out[start:stop] = h
        err[start:stop] = e
        spread[start:stop] = f
        delta_spread[start:stop] = d
        rays += r
    if with_delta_spread:
        return out, err, spread, delta_spread, rays
    if with_spread:
        return out, err, spread, rays
    return (out, err, rays) if with_error else (out, rays)


def _blocked(mi_scene, ray, active, periodic):
    """mi.Bool: shadow ray blocked; wrapped around the periodic box's sides when there is one."""
    if periodic is None:
        return mi_scene.ray_test(ray, active)
    from .periodic import ray_test

    return ray_test(mi_scene, periodic, ray.o, ray.d, ray.maxt, active)


def _direct_kernel(scene, verts, normals, curve, n: int, seed: int, keys, periodic=None):
    m = len(verts)
    lane = dr.arange(mi.UInt32, m * n)
    idx = lane // n
    k = lane % n
    g = lambda a: dr.gather(mi.Vector3f, to_vector3(a), idx)  # noqa: E731
    v0, v1, v2, nrm = g(verts[:, 0]), g(verts[:, 1]), g(verts[:, 2]), g(normals)
    center, axis = g(curve[0]), g(curve[1])
    radius = dr.gather(mi.Float, to_float(curve[2]), idx)
    key = hash_u32(hash_u32(dr.gather(mi.UInt32, to_uint(keys), idx)
                            ^ hash_u32(opaque_u32(seed) + 0x5BD1E995)) + k * 0x632BE5AB)
    u, v = stratified(k, n, key)
    p, nn = project_to_surface(triangle_point(v0, v1, v2, u, v), nrm, center, axis, radius)

    si = dr.zeros(mi.SurfaceInteraction3f, m * n)
    si.p = p
    si.n = nn
    si.sh_frame = mi.Frame3f(nn)
    offset = RAY_OFFSET * scene.diagonal
    bands = getattr(scene, "light_band_scale", None)
    channels = 3 if bands is None else bands.shape[1]
    # (without a sky every light is a point, spot or directional one: their part is the whole)
    with_sky = any(is_sky(e) for e in scene.light_emitters)
    if bands is None:
        lane_sum = dr.zeros(mi.Color3f, m * n)    # every emitter's contribution at each point
        open_sum = dr.zeros(mi.Color3f, m * n)    # the skies' part of it, were nothing in the way
        delta_sum = dr.zeros(mi.Color3f, m * n)   # the point, spot and directional lights' part of it
    else:                                         # per band: sum over emitters of factor x RGB mean
        lane_sum = [dr.zeros(mi.Float, m * n) for _ in range(channels)]
        open_sum = [dr.zeros(mi.Float, m * n) for _ in range(channels)]
        delta_sum = [dr.zeros(mi.Float, m * n) for _ in range(channels)]

    def add(total, e_i: int, value):
        """total plus emitter e_i's contribution value (mi.Color3f): in RGB, or per band
        its RGB mean times the emitter's factor in the band."""
        if bands is None:
            return total + value
        grey = (value[0] + value[1] + value[2]) * (1.0 / 3.0)
        return [t + float(bands[e_i, c]) * grey for c, t in enumerate(total)]

    traced = 0
    for e_i, emitter in enumerate(scene.light_emitters):
        o = p + nn * offset
        if is_sky(emitter):
            d, weight = sky_sample(emitter, si, nn, k, n, key ^ (0x7FEB352D * (e_i + 1)), sky_up(emitter))
            active = dr.any(weight > 0)
            ray = mi.Ray3f(o, d)
            blocked = _blocked(scene.mi_scene, ray, active, periodic)
            lane_sum = add(lane_sum, e_i, dr.select(active & ~blocked, weight, 0.0))
            open_sum = add(open_sum, e_i, dr.select(active, weight, 0.0))
            traced += count_true(active)
            continue
        s2 = mi.Point2f(to_unit(hash_u32(key ^ (0x27D4EB2F + e_i))), to_unit(hash_u32(key ^ (0x165667B1 + e_i))))
        ds, spec = emitter.sample_direction(si, s2, True)
        cos = dr.dot(nn, ds.d)
        active = (cos > 0) & (ds.pdf > 0)
        is_inf = dr.isinf(ds.dist)
        to_light = ds.p - o
        dist = dr.select(is_inf, dr.largest(mi.Float), dr.norm(to_light))
        direction = dr.select(is_inf, ds.d, to_light / dr.select(dist > 0, dist, 1.0))
        ray = mi.Ray3f(o, direction)
        ray.maxt = dr.select(is_inf, dr.largest(mi.Float), shadow_ray_length(dist, offset))
        blocked = _blocked(scene.mi_scene, ray, active, periodic)
        w = dr.select(active & ~blocked, cos, 0.0)
        lane_sum = add(lane_sum, e_i, spec * w)
        if with_sky:
            delta_sum = add(delta_sum, e_i, spec * w)
        traced += count_true(active)
    dr.eval(lane_sum, open_sum, *((delta_sum,) if with_sky else ()))
    mean, spread = _points_mean_and_spread(lane_sum, n, channels)
    # (the point, spot and directional lights' part alone: its points differ by where they are,
    # a sky's also by the directions each drew)
    delta_spread = _points_mean_and_spread(delta_sum, n, channels)[1] if with_sky else spread
    stderr = np.minimum(stratified_error(lane_sum, lane, k, n, channels), spread)
    if with_sky:
        # samples that all agree (a sky seen whole, or hidden whole) may have missed an occluder
        # or a gap smaller than one stratum: at least one of n samples could have turned over,
        # and one that turns over brings what it would bring unoccluded. (Taken from the light
        # that arrived, a leaf whose samples all missed its sky had no error and never got more
        # samples while its neighbours that saw some did: the undersides of a canopy's leaves
        # read 6 % low in their direct light at any tolerance.) A sun's points are spread over
        # the leaf, where a stratum holds a fleck of light it misses only if the fleck is smaller
        # than the stratum; a sky's thin band of gaps crosses many strata and is missed by all
        # (a band of 8 % of a leaf's sky through 16 samples: one leaf in four)
        open_mean = _points_mean(open_sum, n, channels)
        stderr = np.maximum(stderr, open_mean / n)
        spread = np.maximum(spread, open_mean / n)
    return mean, stderr, spread, delta_spread, traced


def _points_mean(values, n: int, channels: int) -> np.ndarray:
    """(m, C): the mean over each triangle's n points of per-point values (C channels of m n lanes)."""
    return np.stack([dr.block_sum(values[c], n).numpy() / n for c in range(channels)], 1)


def _points_mean_and_spread(values, n: int, channels: int) -> tuple[np.ndarray, np.ndarray]:
    """(m, C) each: the mean over each triangle's n points of per-point values (as
    ``_points_mean``) and its i.i.d. standard error (the points' sample standard deviation over
    sqrt(n))."""
    mean = _points_mean(values, n, channels)
    square = _points_mean([dr.square(values[c]) for c in range(channels)], n, channels)
    return mean, np.sqrt(np.maximum(square - mean * mean, 0.0) / max(n - 1, 1))


def stratified_error(values, lane, k, n: int, channels: int) -> np.ndarray:
    """(m, channels) standard error of the means of ``values`` (per channel, m * n lanes, n per
    element) over stratified points: stratum k's points pair with their neighbour k ^ 1 (the
    next cell of the same row of ``visibility.stratified``'s grid; an odd count's last with the
    one before), and var(mean) = sum over pairs of (f_a - f_b)^2 / n^2, the collapsed-strata
    estimator. It counts what differs within a pair of cells, not across the whole element as
    the i.i.d. sample variance does: a shadow edge across a sunlit leaf is in a few pairs only
    (the i.i.d. value stays sqrt(n) wider however many points), while it stays an over-estimate
    (a pair's difference also holds the change of the mean between its cells). One point:
    zero, as the sample variance of one."""
    if n < 2:
        return np.zeros((dr.width(lane) // max(n, 1), channels))
    partner = dr.select((k ^ 1) < n, lane ^ 1, lane - 1)
    out = []
    for c in range(channels):
        diff = values[c] - dr.gather(mi.Float, values[c], partner)
        out.append(dr.block_sum(dr.square(diff), n).numpy() / (2.0 * n * n))
    return np.sqrt(np.stack(out, 1))


def delta_light_bound(scene, verts: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(n,) W/m^2: an upper bound, anywhere on each triangle verts (n, 3, 3) with front
    normal normals (n, 3), of the irradiance that point and spot lights can bring (brightest
    channel, no occlusion, a spot's profile at most 1), summed over the lights; in a band scene
    each light's bound is scaled by its largest factor over the bands (``light_band_scale``).

    A light at height p above the triangle's plane and at least s from the triangle (its
    bounding sphere) gives I cos / r^2 = I p / r^3 <= I p / max(p, s)^3; 0 behind the
    plane. Stratified samples can miss a feature smaller than one stratum (a narrow spot's
    cone on a large triangle): what they miss is at most this bound over the strata count.
    """
    n = len(verts)
    out = np.zeros(n)
    center = verts.mean(axis=1)
    radius = np.linalg.norm(verts - center[:, None], axis=2).max(axis=1)
    bands = getattr(scene, "light_band_scale", None)
    for e_i, emitter in enumerate(scene.light_emitters):
        if not (emitter.flags() & mi.EmitterFlags.DeltaPosition):
            continue
        params = mi.traverse(emitter)
        keys = set(params.keys())
        if "position" in keys:
            position = np.array(params["position"], np.float64).reshape(-1)[:3]
        elif "to_world" in keys:
            position = np.array(params["to_world"].translation(), np.float64).reshape(-1)[:3]
        else:
            continue
        intensity = float(np.max(np.array(params["intensity.value"], np.float64))) if "intensity.value" in keys else 0.0
        if "texture.value" in keys:
            intensity *= float(np.max(np.array(params["texture.value"], np.float64)))
        if bands is not None:     # a band's value is its factor times the RGB mean, at most the max
            intensity *= float(bands[e_i].max())
        height = np.einsum("nc,nc->n", normals, position - verts[:, 0])
        dist = np.linalg.norm(position - center, axis=1)
        s = np.maximum(dist - radius, 0.0)
        reach = np.maximum(height, s)
        bound = np.where(height > 0, intensity * height / np.maximum(reach, 1e-300) ** 3, 0.0)
        if "cutoff_angle" in keys and "to_world" in keys:
            # a spot lights nothing beyond its cutoff: triangles whose bounding sphere lies
            # wholly outside the cone get nothing
            axis = np.array(params["to_world"].matrix, np.float64).reshape(4, 4)[:3, 2]
            axis = axis / np.linalg.norm(axis)
            cutoff = np.radians(float(np.array(params["cutoff_angle"], np.float64).reshape(-1)[0]))
            to_center = (center - position) / np.maximum(dist, 1e-300)[:, None]
            angle = np.arccos(np.clip(to_center @ axis, -1.0, 1.0))
            spread = np.arcsin(np.clip(radius / np.maximum(dist, 1e-300), 0.0, 1.0))
            bound = np.where((dist > radius) & (angle - spread > cutoff), 0.0, bound)
        out += bound
    return out
