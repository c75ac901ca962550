"""Form-factor kernels against Howell's closed forms and against a naive float64 loop."""

import numpy as np
import pytest

import drjit as dr
import mitsuba as mi

from conftest import F_PARALLEL, F_PERPENDICULAR
from mirad.arrays import to_float
from mirad.formfactor import (disc_estimate, parallel_rectangles, perpendicular_rectangles,
                              point_to_polygon, point_to_triangle_dr)


def _gauss_square(n=24):
    x, w = np.polynomial.legendre.leggauss(n)
    return (x + 1) / 2, w / 2


def test_closed_forms_reproduce_howell_values():
    assert parallel_rectangles(1, 1, 1) == pytest.approx(F_PARALLEL, abs=5e-7)
    assert perpendicular_rectangles(1, 1, 1) == pytest.approx(F_PERPENDICULAR, abs=5e-7)
    assert perpendicular_rectangles(2, 1, 3) == pytest.approx(0.30814, abs=5e-6)


def test_lambert_integrated_over_receiver_matches_parallel_closed_form():
    u, w = _gauss_square()
    source = [[0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]]
    total = sum(wi * wj * point_to_polygon([ui, uj, 0], [0, 0, 1], source)
                for ui, wi in zip(u, w) for uj, wj in zip(u, w))
    assert total == pytest.approx(F_PARALLEL, rel=1e-6)


def test_lambert_integrated_over_receiver_matches_perpendicular_closed_form():
    u, w = _gauss_square()
    source = [[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1]]  # y = 0 plane, shares the x axis
    total = sum(wi * wj * point_to_polygon([ui, uj, 0], [0, 0, 1], source)
                for ui, wi in zip(u, w) for uj, wj in zip(u, w))
    assert total == pytest.approx(F_PERPENDICULAR, rel=1e-4)


def test_drjit_kernel_matches_numpy_loop_including_clipped_triangles():
    rng = np.random.default_rng(7)
    n = 300
    x = rng.uniform(-1, 1, (n, 3))
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    tri = rng.uniform(-2, 2, (n, 3, 3))  # many cross the receiver's tangent plane
    vec = lambda a: mi.Vector3f(*(to_float(a[:, i]) for i in range(3)))  # noqa: E731
    got = point_to_triangle_dr(vec(x), vec(normal), vec(tri[:, 0]), vec(tri[:, 1]), vec(tri[:, 2])).numpy()
    expected = np.array([point_to_polygon(x[i], normal[i], tri[i]) for i in range(n)])
    np.testing.assert_allclose(got, expected, atol=2e-4)
    assert np.all((got >= 0) & (got <= 1))


def test_disc_estimate_is_bounded_when_elements_touch():
    f = disc_estimate(np.array([1.0, 1e-6]), np.ones(2), np.ones(2), np.zeros(2))
    np.testing.assert_allclose(f, [1.0, 1.0])
    assert disc_estimate(1.0, 1.0, 1.0, 1.0) == pytest.approx(1 / (np.pi + 1))
