"""Reference radiosity from Mitsuba's own path tracer (the yardstick of mirad's error).

Per triangle: points uniform by area on the triangle; at each, a ray aimed at the
point from just above it along the normal makes Mitsuba's ``path`` integrator
return the outgoing radiance L_o there (emission plus everything reflected, with
emitter sampling at that point), so B = pi * L_o, with its standard error.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from . import _runtime  # noqa: F401
from .visibility import hash_u32, to_unit, triangle_point

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

#: Paths per Mitsuba launch.
BATCH = 1 << 20


@dataclass
class Reference:
    """Per-triangle reference radiosity (T, C) with its standard error, W/m^2."""

    radiosity: np.ndarray
    stderr: np.ndarray
    samples_per_triangle: int
    seconds: float
    paths: int

    def shape_radiosity(self, scene, shape_id: str) -> np.ndarray:
        mask = scene.tri_shape == scene.shape_index(shape_id)
        a = scene.tri_area[mask]
        return (self.radiosity[mask] * a[:, None]).sum(0) / a.sum()


def triangle_reference(scene, *, samples_per_triangle: int = 1024, seed: int = 0,
                       max_depth: int = -1, triangles: np.ndarray | None = None) -> Reference:
    """Path-traced front-side radiosity of every (or the given) input triangle."""
    t0 = time.perf_counter()
    tris = np.arange(scene.triangle_count) if triangles is None else np.asarray(triangles)
    integrator = mi.load_dict({"type": "path", "max_depth": int(max_depth)})
    verts = scene.tri_vertices[tris]
    normal = scene.tri_normal[tris]
    n = samples_per_triangle
    total = np.zeros((len(tris), 3))
    total_sq = np.zeros((len(tris), 3))
    per_batch = max(1, BATCH // n)
    offset = 1e-4 * scene.diagonal
    for start in range(0, len(tris), per_batch):
        stop = min(len(tris), start + per_batch)
        m = stop - start
        v = verts[start:stop].astype(np.float32)
        nn = normal[start:stop].astype(np.float32)
        lane = dr.arange(mi.UInt32, m * n)
        idx = lane // n
        g = lambda a: dr.gather(mi.Vector3f, mi.Vector3f(a[:, 0], a[:, 1], a[:, 2]), idx)  # noqa: E731
        key = hash_u32(lane + mi.UInt32(start * n) + hash_u32(mi.UInt32(seed) + 0x2545F491))
        u, w = to_unit(hash_u32(key ^ 0x1)), to_unit(hash_u32(key ^ 0x2))
        p = triangle_point(g(v[:, 0]), g(v[:, 1]), g(v[:, 2]), u, w)
        nrm = g(nn)
        ray = mi.RayDifferential3f(p + nrm * offset, -nrm)
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(int(seed) * 7919 + start, m * n)
        radiance, _, _ = integrator.sample(scene.mi_scene, sampler, ray)
        b = np.pi * np.array(radiance.numpy(), dtype=np.float64).T.reshape(m, n, 3)
        total[start:stop] = b.sum(1)
        total_sq[start:stop] = (b * b).sum(1)
    mean = total / n
    var = np.maximum(total_sq / n - mean * mean, 0.0)
    stderr = np.sqrt(var / max(n - 1, 1))
    return Reference(mean, stderr, n, time.perf_counter() - t0, len(tris) * n)
