"""Reference radiosity and images from Mitsuba's own path tracer (the yardstick of mirad's error).

Per triangle, two estimators, both unbiased and both driven by Mitsuba's ``path`` integrator:

``method="outgoing"`` (default, the cheaper one: emitter sampling at the point itself; see docs/method.md)
    points uniform by area on the triangle; at each, a ray aimed at the point from just above it
    along the front normal makes ``path`` return the outgoing radiance L_o there (emission plus
    everything reflected, with emitter sampling at that very point), so B = pi * L_o.
``method="irradiance"``
    points uniform by area and cosine-weighted directions over the front hemisphere; ``path``
    traces the incident radiance L_in along each, so H = pi * mean(L_in) and B = E + rho * H
    (E and rho as mirad ingested them).

``side="back"`` estimates the other side of each triangle (its own radiosity where the BSDF is
two-sided): the same estimators with the normal reversed, the back's reflectance and no emission.

Every estimate comes with its standard error (sample standard deviation / sqrt(n)), so nobody
mistakes the reference's noise for solver error. Paths are traced in Dr.Jit launches of at most
``batch`` lanes; the sampler seed is opaque, so every launch reuses one compiled kernel.

References are cached on disk (``cached_reference``, in ``default_cache_dir()``: the platform's
cache folder, or ``$MIRAD_CACHE``), keyed by the scene fingerprint and every
sampling setting; the fingerprint is also stored inside the file and checked on load, so a cache
from another scene is never reused. Files are written atomically.

>>> scene = mirad.load_scene("scenes/closed-form/parallel-squares.xml")     # doctest: +SKIP
>>> ref = triangle_reference(scene, samples_per_triangle=4096, seed=1)      # doctest: +SKIP
>>> ref.shape_radiosity(scene, "receiver")                                 # doctest: +SKIP
array([0.0999, 0.0999, 0.0999])
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import _runtime  # noqa: F401  (LLVM set-up before mitsuba)
from .errors import SceneError, SettingsError
from .arrays import to_float, to_uint, to_vector3
from .files import atomic_write

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
from tqdm.auto import tqdm  # noqa: E402

__all__ = ["Reference", "ReferenceImage", "triangle_reference", "cached_reference", "reference_image",
           "camera_rays", "DEFAULT_CACHE"]

#: Paths per Dr.Jit launch (bounds memory: about 1 GB of path state at 2^21 lanes).
BATCH = 1 << 20
#: Ray origins are lifted this fraction of the scene diagonal off the surface.
OFFSET = 1e-4
#: ``cache_dir`` value meaning the default cache folder (see ``default_cache_dir``).
DEFAULT_CACHE = "default"
#: Fewest paths a triangle gets when paths are allocated by area.
MIN_AREA_SAMPLES = 16
#: Bumped whenever the estimator changes, so old caches are recomputed.
CACHE_VERSION = 2
METHODS = ("outgoing", "irradiance")
SIDES = ("front", "back")


# ------------------------------------------------------------------------------------------
# Results
# ------------------------------------------------------------------------------------------

@dataclass
class Reference:
    """Per-triangle reference radiosity (T, C) and its standard error (T, C), W/m^2.

    ``triangles`` are the input-triangle indices estimated (all of them unless a subset was
    asked for); ``radiosity`` and ``stderr`` rows follow that order. ``side`` is the side
    estimated: "front" (along the triangle's normal) or "back" (two-sided BSDFs).
    """

    radiosity: np.ndarray
    stderr: np.ndarray
    samples_per_triangle: int
    seconds: float
    paths: int
    method: str = "outgoing"
    seed: int = 0
    fingerprint: str = ""
    triangles: np.ndarray | None = None
    from_cache: bool = False
    side: str = "front"

    def _rows(self, scene, shape_id: str) -> tuple[np.ndarray, np.ndarray]:
        tris = np.arange(len(self.radiosity)) if self.triangles is None else self.triangles
        mask = scene.tri_shape[tris] == scene.shape_index(shape_id)
        return mask, scene.tri_area[tris][mask]

    def shape_radiosity(self, scene, shape_id: str) -> np.ndarray:
        """(C,) area-weighted mean reference radiosity over a shape's side ``self.side``, W/m^2."""
        mask, a = self._rows(scene, shape_id)
        return (self.radiosity[mask] * a[:, None]).sum(0) / a.sum()

    def shape_stderr(self, scene, shape_id: str) -> np.ndarray:
        """(C,) standard error of ``shape_radiosity`` (triangles are independent), W/m^2."""
        mask, a = self._rows(scene, shape_id)
        return np.sqrt(((self.stderr[mask] * a[:, None]) ** 2).sum(0)) / a.sum()

    # --- files ----------------------------------------------------------------------------------
    def _meta(self) -> dict:
        return {"version": CACHE_VERSION, "fingerprint": self.fingerprint, "method": self.method,
                "seed": self.seed, "samples_per_triangle": self.samples_per_triangle,
                "seconds": self.seconds, "paths": self.paths, "side": self.side}

    def save(self, path) -> Path:
        """Write as .npz (atomically)."""
        arrays = {"radiosity": self.radiosity, "stderr": self.stderr}
        if self.triangles is not None:
            arrays["triangles"] = self.triangles
        meta = np.frombuffer(json.dumps(self._meta()).encode(), np.uint8)
        atomic_write(path, lambda handle: np.savez(handle, __meta__=meta, **arrays))
        return Path(path)

    @classmethod
    def load(cls, path) -> "Reference":
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(bytes(data["__meta__"]).decode())
            tris = data["triangles"] if "triangles" in data.files else None
            return cls(radiosity=data["radiosity"], stderr=data["stderr"],
                       samples_per_triangle=int(meta["samples_per_triangle"]), seconds=float(meta["seconds"]),
                       paths=int(meta["paths"]), method=meta["method"], seed=int(meta["seed"]),
                       fingerprint=meta["fingerprint"], triangles=tris, from_cache=True,
                       side=meta.get("side", "front"))


@dataclass
class ReferenceImage:
    """Path-traced image (H, W, 3) of radiance, its per-pixel standard error, and coverage.

    ``coverage`` (H, W) is the fraction of each pixel's camera rays that hit a surface.
    """

    image: np.ndarray
    stderr: np.ndarray
    coverage: np.ndarray
    spp: int
    seconds: float
    fingerprint: str = ""
    from_cache: bool = False
    extra: dict = field(default_factory=dict)


# ------------------------------------------------------------------------------------------
# Helpers
# ------------------------------------------------------------------------------------------

def _batch_seed(seed: int, batch: int, salt: int) -> int:
    digest = hashlib.blake2b(f"{seed}:{batch}:{salt}".encode(), digest_size=4).digest()
    return int.from_bytes(digest, "little")


def _sampler(seed: int, batch: int, salt: int, lanes: int):
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(dr.opaque(mi.UInt32, _batch_seed(seed, batch, salt)), lanes)
    return sampler


def _colour(spectrum, count: int) -> np.ndarray:
    arr = np.array(spectrum.numpy(), dtype=np.float64)
    arr = arr.T if arr.ndim == 2 and arr.shape[0] == 3 else arr.reshape(-1, 3)
    return np.broadcast_to(arr, (count, 3)) if len(arr) != count else arr


def _integrator(max_depth: int):
    if int(max_depth) < -1 or int(max_depth) == 0:
        raise SettingsError(f"max_depth={max_depth}: give -1 (unlimited) or a depth >= 1")
    return mi.load_dict({"type": "path", "max_depth": int(max_depth)})


def _check_count(name: str, value: int) -> int:
    if int(value) != value or int(value) < 1:
        raise SettingsError(f"{name}={value!r}: give a positive whole number of samples")
    return int(value)


# ------------------------------------------------------------------------------------------
# Per-triangle reference
# ------------------------------------------------------------------------------------------

def sample_counts(area: np.ndarray, mean: int, allocation: str) -> np.ndarray:
    """(K,) paths per triangle: ``mean`` each ("uniform"), or in proportion to area with the same
    total and at least ``MIN_AREA_SAMPLES`` each ("area": the area-weighted error of the
    reference then gets its best standard error for the paths spent)."""
    area = np.asarray(area, np.float64)
    if allocation == "uniform" or not len(area):
        return np.full(len(area), int(mean), np.int64)
    if allocation != "area":
        raise SettingsError(f"allocation={allocation!r}: choose 'uniform' or 'area'")
    share = area / max(area.sum(), 1e-300) * int(mean) * len(area)
    return np.maximum(np.round(share).astype(np.int64), min(MIN_AREA_SAMPLES, int(mean)))


def triangle_reference(scene, *, samples_per_triangle: int = 1024, seed: int = 0, max_depth: int = -1,
                       triangles: np.ndarray | None = None, method: str = "outgoing",
                       batch: int = BATCH, allocation: str = "uniform", quiet: bool = True,
                       side: str = "front") -> Reference:
    """Path-traced radiosity of one side of every (or the given) input triangle.

    Parameters
    ----------
    scene : mirad.Scene
    samples_per_triangle : paths per triangle (the mean number with ``allocation="area"``)
    seed : random seed; different seeds give independent estimates
    max_depth : Mitsuba ``path`` depth (-1: unlimited, with Russian roulette: unbiased)
    triangles : (K,) int, optional subset of input triangles
    method : "outgoing" (B = pi L_o, emitter sampling at the point) or "irradiance"
             (cosine-weighted L_in, B = E + rho H)
    batch : most paths per Dr.Jit launch
    allocation : "uniform" (every triangle the same paths) or "area" (in proportion to area,
                 see ``sample_counts``)
    quiet : no progress bar
    side : "front" (along the triangle's normal) or "back" (the other side, which has its own
           radiosity where the BSDF is two-sided: reflectance ``scene.back_rho``, no emission)

    Returns
    -------
    Reference with radiosity and stderr (K, 3), W/m^2.
    """
    if method not in METHODS:
        raise SettingsError(f"method={method!r}: choose one of {', '.join(METHODS)}")
    if side not in SIDES:
        raise SettingsError(f"side={side!r}: choose one of {', '.join(SIDES)}")
    n = _check_count("samples_per_triangle", samples_per_triangle)
    batch = _check_count("batch", batch)
    t0 = time.perf_counter()
    tris = np.arange(scene.triangle_count) if triangles is None else np.asarray(triangles, dtype=np.int64)
    if tris.size and (tris.min() < 0 or tris.max() >= scene.triangle_count):
        raise SettingsError(f"triangles: indices must lie in [0, {scene.triangle_count})")
    integrator = _integrator(max_depth)
    verts = scene.tri_vertices[tris]
    if side == "front":
        normal = scene.tri_normal[tris]
        rho, emission = scene.tri_rho[tris], scene.tri_emission[tris]
    else:                      # Mitsuba's area emitters emit on the front side only
        normal = -scene.tri_normal[tris]
        rho, emission = scene.back_rho[tris], np.zeros_like(scene.tri_emission[tris])
    k = len(tris)
    total = np.zeros((k, 3))
    total_sq = np.zeros((k, 3))
    offset = OFFSET * scene.diagonal
    counts = sample_counts(scene.tri_area[tris], n, allocation)
    ends = np.cumsum(counts)
    count = int(ends[-1]) if k else 0
    bar = tqdm(total=count, desc="reference paths" if side == "front" else "reference paths (back)", unit="path",
               unit_scale=True, disable=quiet, leave=False)
    for index, start in enumerate(range(0, count, batch)):
        stop = min(count, start + batch)
        lanes = stop - start
        local = np.searchsorted(ends, np.arange(start, stop, dtype=np.int64), side="right")  # triangle of each lane
        first, last = int(local[0]), int(local[-1]) + 1
        # --- upload the triangles this launch touches, gather per lane inside Dr.Jit ----------
        idx = to_uint(local - first)
        v0, v1, v2 = (dr.gather(mi.Vector3f, to_vector3(verts[first:last, c]), idx) for c in range(3))
        nrm = dr.gather(mi.Vector3f, to_vector3(normal[first:last]), idx)
        sampler = _sampler(seed, index, 0x51, lanes)
        u = sampler.next_2d()
        su = dr.sqrt(u.x)
        p = v0 * (1 - su) + v1 * (su * (1 - u.y)) + v2 * (su * u.y)
        if method == "outgoing":
            ray = mi.RayDifferential3f(p + nrm * offset, -nrm)
        else:
            d = mi.Frame3f(nrm).to_world(mi.warp.square_to_cosine_hemisphere(sampler.next_2d()))
            ray = mi.RayDifferential3f(p + nrm * offset, d)
        radiance, _, _ = integrator.sample(scene.mi_scene, sampler, ray)
        sample = np.pi * _colour(radiance, lanes)
        if method == "irradiance":
            sample = emission[local] + rho[local] * sample
        if not np.all(np.isfinite(sample)):
            raise SceneError("the path tracer returned NaN or Inf radiance; check the scene's emitters "
                             "and BSDFs for invalid values")
        for c in range(3):
            total[:, c] += np.bincount(local, weights=sample[:, c], minlength=k)
            total_sq[:, c] += np.bincount(local, weights=sample[:, c] ** 2, minlength=k)
        bar.update(lanes)
    bar.close()
    m = np.maximum(counts, 1)[:, None].astype(np.float64)
    mean = total / m
    var = np.maximum(total_sq / m - mean * mean, 0.0) * (m / np.maximum(m - 1, 1))
    stderr = np.sqrt(var / m)
    return Reference(mean, stderr, n, time.perf_counter() - t0, count, method=method, seed=int(seed),
                     fingerprint=scene.fingerprint, triangles=None if triangles is None else tris, side=side)


def default_cache_dir() -> Path:
    """The reference cache folder: ``$MIRAD_CACHE`` if set, else the platform's user cache folder
    for mirad (``~/.cache/mirad`` on Linux, via platformdirs)."""
    import platformdirs

    return Path(os.environ.get("MIRAD_CACHE") or platformdirs.user_cache_dir("mirad"))


def cache_path(scene, *, cache_dir=DEFAULT_CACHE, kind: str = "triangles", **settings) -> Path:
    """The cache file of a reference: scene fingerprint + a hash of every setting."""
    text = json.dumps({"version": CACHE_VERSION, "kind": kind, **settings}, sort_keys=True, default=str)
    key = hashlib.sha256(text.encode()).hexdigest()[:12]
    folder = default_cache_dir() if cache_dir == DEFAULT_CACHE else Path(cache_dir)
    return folder / f"{kind}-{scene.fingerprint}-{key}.npz"


def cached_reference(scene, *, cache_dir=DEFAULT_CACHE, samples_per_triangle: int = 1024, seed: int = 0,
                     max_depth: int = -1, method: str = "outgoing", triangles=None, allocation: str = "uniform",
                     quiet: bool = True, side: str = "front") -> Reference:
    """``triangle_reference`` through an on-disk cache (``cache_dir=None``: no cache).

    A cached file is reused only when its stored fingerprint, method, seed and sample count all
    match this scene and these settings; otherwise (or when unreadable) it is recomputed and
    overwritten atomically.
    """
    settings = {"samples_per_triangle": int(samples_per_triangle), "seed": int(seed),
                "max_depth": int(max_depth), "method": method,
                **({} if allocation == "uniform" else {"allocation": allocation}),
                **({} if side == "front" else {"side": side}),
                "triangles": None if triangles is None else hashlib.sha256(
                    np.asarray(triangles, np.int64).tobytes()).hexdigest()[:12]}
    if cache_dir is None:
        return triangle_reference(scene, samples_per_triangle=samples_per_triangle, seed=seed,
                                  max_depth=max_depth, method=method, triangles=triangles,
                                  allocation=allocation, quiet=quiet, side=side)
    path = cache_path(scene, cache_dir=cache_dir, **settings)
    if path.exists():
        try:
            ref = Reference.load(path)
        except Exception:
            ref = None
        if (ref is not None and ref.fingerprint == scene.fingerprint and ref.method == method
                and ref.seed == int(seed) and ref.samples_per_triangle == int(samples_per_triangle) and ref.side == side
                and len(ref.radiosity) == (scene.triangle_count if triangles is None else len(triangles))):
            return ref
    ref = triangle_reference(scene, samples_per_triangle=samples_per_triangle, seed=seed,
                             max_depth=max_depth, method=method, triangles=triangles, allocation=allocation,
                             quiet=quiet, side=side)
    os.makedirs(path.parent, exist_ok=True)
    ref.save(path)
    return ref


# ------------------------------------------------------------------------------------------
# Images
# ------------------------------------------------------------------------------------------

def _sensor(scene):
    sensors = scene.mi_scene.sensors()
    if not sensors:
        raise SceneError(f"{scene.source or '<scene>'}: the scene has no sensor; add a <sensor> (camera) "
                         "to get images, or run without images")
    return sensors[0]


def camera_rays(scene, *, spp: int, seed: int = 0, batch: int = BATCH):
    """Yield (pixel (N,) int, ray, sampler) batches of jittered camera rays, ``spp`` per pixel.

    Pixels are numbered row by row over the sensor's film (its crop window).
    """
    spp = _check_count("spp", spp)
    sensor = _sensor(scene)
    film = sensor.film()
    width, height = (int(x) for x in film.crop_size())
    ox, oy = (int(x) for x in film.crop_offset())
    full_w, full_h = (int(x) for x in film.size())
    count = width * height * spp
    for index, start in enumerate(range(0, count, batch)):
        stop = min(count, start + batch)
        pixel = np.arange(start, stop, dtype=np.int64) // spp
        sampler = _sampler(seed, index, 0xC4, stop - start)
        px = to_float(pixel % width + ox)
        py = to_float(pixel // width + oy)
        jitter = sampler.next_2d()
        pos = mi.Point2f((px + jitter.x) / full_w, (py + jitter.y) / full_h)
        ray, _ = sensor.sample_ray_differential(0.0, sampler.next_1d(), pos, sampler.next_2d())
        yield pixel, ray, sampler


def reference_image(scene, *, spp: int = 64, seed: int = 0, max_depth: int = -1) -> ReferenceImage:
    """Path-traced radiance image (H, W, 3) from the scene's first sensor, box-filtered per pixel.

    Raises SceneError when the scene has no sensor or when the sensor sees no shape at all.
    """
    t0 = time.perf_counter()
    integrator = _integrator(max_depth)
    film = _sensor(scene).film()
    width, height = (int(x) for x in film.crop_size())
    pixels = width * height
    total, total_sq = np.zeros((pixels, 3)), np.zeros((pixels, 3))
    hits = np.zeros(pixels)
    for pixel, ray, sampler in camera_rays(scene, spp=spp, seed=seed):
        hit = np.asarray(scene.mi_scene.ray_test(mi.Ray3f(ray)).numpy(), dtype=np.float64)
        radiance, _, _ = integrator.sample(scene.mi_scene, sampler, ray)
        value = _colour(radiance, len(pixel))
        hits += np.bincount(pixel, weights=hit, minlength=pixels)
        for c in range(3):
            total[:, c] += np.bincount(pixel, weights=value[:, c], minlength=pixels)
            total_sq[:, c] += np.bincount(pixel, weights=value[:, c] ** 2, minlength=pixels)
    if hits.sum() == 0:
        raise SceneError(f"{scene.source or '<scene>'}: the sensor sees no shape (every camera ray misses "
                         "the geometry); point the sensor at the scene (check its to_world / lookat)")
    mean = total / spp
    var = np.maximum(total_sq / spp - mean * mean, 0.0) * (spp / max(spp - 1, 1))
    shape = (height, width, 3)
    return ReferenceImage(mean.reshape(shape), np.sqrt(var / spp).reshape(shape),
                          (hits / spp).reshape(height, width), spp, time.perf_counter() - t0,
                          fingerprint=scene.fingerprint)


def cached_image(scene, *, cache_dir=DEFAULT_CACHE, spp: int = 64, seed: int = 0,
                 max_depth: int = -1) -> ReferenceImage:
    """``reference_image`` through the on-disk cache (same rules as ``cached_reference``)."""
    if cache_dir is None:
        return reference_image(scene, spp=spp, seed=seed, max_depth=max_depth)
    film = _sensor(scene).film()
    settings = {"spp": int(spp), "seed": int(seed), "max_depth": int(max_depth),
                "size": [int(x) for x in film.crop_size()], "offset": [int(x) for x in film.crop_offset()]}
    path = cache_path(scene, cache_dir=cache_dir, kind="image", **settings)
    if path.exists():
        try:
            with np.load(path, allow_pickle=False) as data:
                meta = json.loads(bytes(data["__meta__"]).decode())
                if meta.get("fingerprint") == scene.fingerprint and meta.get("settings") == settings:
                    return ReferenceImage(data["image"], data["stderr"], data["coverage"], int(spp),
                                          float(meta["seconds"]), fingerprint=scene.fingerprint,
                                          from_cache=True)
        except Exception:
            pass
    img = reference_image(scene, spp=spp, seed=seed, max_depth=max_depth)
    meta = np.frombuffer(json.dumps({"fingerprint": scene.fingerprint, "settings": settings,
                                     "seconds": img.seconds}).encode(), np.uint8)
    os.makedirs(path.parent, exist_ok=True)
    atomic_write(path, lambda handle: np.savez(handle, __meta__=meta, image=img.image, stderr=img.stderr,
                                               coverage=img.coverage))
    return img
