"""Form-factor kernels.

* :func:`point_to_triangle_dr` – Lambert's analytic form factor from a
  differential area (point x, normal n) to a triangle, clipped against x's tangent
  half-space, as a Dr.Jit expression (one lane per point/triangle pair).
* :func:`point_to_polygon` – the same in numpy float64 (tests, small queries).
* :func:`parallel_rectangles`, :func:`perpendicular_rectangles` – Howell's closed
  forms, used as test oracles.
* :func:`disc_estimate` – the bounded oracle estimate A cos cos / (pi r^2 + A).

All form factors are dimensionless; points in metres.
"""

from __future__ import annotations

import numpy as np

from . import _runtime  # noqa: F401

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

_TINY = 1e-30


def _edge_term_dr(a, b, n):
    """gamma * n.(a x b)/|a x b| for one edge seen from the origin (Dr.Jit)."""
    c = dr.cross(a, b)
    cn = dr.norm(c)
    gamma = dr.atan2(cn, dr.dot(a, b))
    return gamma * dr.dot(n, c) / dr.maximum(cn, _TINY)


def point_to_triangle_dr(x, n, s0, s1, s2):
    """Unoccluded form factor dA(x, n) -> triangle (s0, s1, s2), clipped to n.(y - x) >= 0.

    Parameters are Dr.Jit 3-vectors (mi.Point3f / mi.Vector3f) of equal width.
    Returns a mi.Float in [0, 1]. The caller checks that x is on the triangle's
    emitting side.
    """
    r = [s0 - x, s1 - x, s2 - x]
    d = [dr.dot(n, ri) for ri in r]
    inside = [di >= 0 for di in d]
    total = dr.zeros(mi.Float, dr.width(d[0]))
    exit_pt = dr.zeros(mi.Vector3f, dr.width(d[0]))
    entry_pt = dr.zeros(mi.Vector3f, dr.width(d[0]))
    crossing = dr.zeros(mi.Bool, dr.width(d[0]))
    for i in range(3):
        j = (i + 1) % 3
        denom = d[i] - d[j]
        t = dr.select(dr.abs(denom) > 0, d[i] / dr.select(denom == 0, 1.0, denom), 0.0)
        p = dr.fma(r[j] - r[i], t, r[i])
        start = dr.select(inside[i], r[i], p)
        end = dr.select(inside[j], r[j], p)
        valid = inside[i] | inside[j]
        total += dr.select(valid, _edge_term_dr(start, end, n), 0.0)
        leaving = inside[i] & ~inside[j]
        entering = ~inside[i] & inside[j]
        exit_pt = dr.select(leaving, p, exit_pt)
        entry_pt = dr.select(entering, p, entry_pt)
        crossing |= leaving
    total += dr.select(crossing, _edge_term_dr(exit_pt, entry_pt, n), 0.0)
    return dr.minimum(dr.abs(total) * (0.5 / dr.pi), 1.0)


def point_to_polygon(x, n, poly) -> float:
    """Form factor from dA at x (normal n) to a planar polygon (k, 3), float64, clipped.

    >>> round(point_to_polygon([0, 0, 0], [0, 0, 1], [[-1e3, -1e3, 1], [1e3, -1e3, 1], [1e3, 1e3, 1], [-1e3, 1e3, 1]]), 4)
    1.0
    """
    x, n = np.asarray(x, float), np.asarray(n, float)
    pts = np.asarray(poly, float) - x
    d = pts @ n
    clipped = []
    k = len(pts)
    for i in range(k):
        a, b = pts[i], pts[(i + 1) % k]
        da, db = d[i], d[(i + 1) % k]
        if da >= 0:
            clipped.append(a)
        if (da >= 0) != (db >= 0):
            clipped.append(a + (b - a) * (da / (da - db)))
    total = 0.0
    for i in range(len(clipped)):
        a, b = clipped[i], clipped[(i + 1) % len(clipped)]
        c = np.cross(a, b)
        cn = np.linalg.norm(c)
        if cn <= _TINY:
            continue
        total += np.arctan2(cn, a @ b) * (n @ c) / cn
    return min(abs(total) / (2 * np.pi), 1.0)


def disc_estimate(area_src, cos_r, cos_s, dist2):
    """Bounded form-factor estimate A cos_r cos_s / (pi r^2 + A) (Wallace et al. 89), numpy."""
    return area_src * np.clip(cos_r, 0, None) * np.clip(cos_s, 0, None) / (np.pi * dist2 + area_src)


def parallel_rectangles(a: float, b: float, c: float) -> float:
    """Form factor between directly opposed a x b rectangles at distance c (Howell)."""
    x, y = a / c, b / c
    return 2 / (np.pi * x * y) * (
        np.log(np.sqrt((1 + x * x) * (1 + y * y) / (1 + x * x + y * y)))
        + x * np.sqrt(1 + y * y) * np.arctan(x / np.sqrt(1 + y * y))
        + y * np.sqrt(1 + x * x) * np.arctan(y / np.sqrt(1 + x * x))
        - x * np.arctan(x) - y * np.arctan(y)
    )


def perpendicular_rectangles(l: float, w: float, h: float) -> float:
    """F from the l x w rectangle to the l x h rectangle sharing the edge of length l (Howell)."""
    W, H = w / l, h / l
    s = H * H + W * W
    log_term = 0.25 * np.log(
        (1 + W * W) * (1 + H * H) / (1 + s)
        * (W * W * (1 + s) / ((1 + W * W) * s)) ** (W * W)
        * (H * H * (1 + s) / ((1 + H * H) * s)) ** (H * H)
    )
    return 1 / (np.pi * W) * (
        W * np.arctan(1 / W) + H * np.arctan(1 / H) - np.sqrt(s) * np.arctan(1 / np.sqrt(s)) + log_term
    )
