"""validation/bench_seeds.py: the spread between seeds' solutions, against hand-computed cases."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from conftest import ROOT, load_script


@pytest.fixture(scope="module")
def bench():
    return load_script(ROOT / "validation" / "bench_seeds.py", "bench_seeds")


def test_the_spread_is_the_mean_pairwise_l1_over_sqrt_2(bench):
    # two triangles, areas 1 and 3, one channel; the reference's power 1 * 2 + 3 * 2 = 8
    scene = SimpleNamespace(tri_area=np.array([1.0, 3.0]))
    reference = np.array([[2.0], [2.0]])
    a, b, c = np.array([[2.0], [2.0]]), np.array([[2.4], [2.0]]), np.array([[2.0], [1.6]])
    # pairwise area-weighted L1: |a-b| 0.4, |a-c| 1.2, |b-c| 0.4 + 1.2 = 1.6; mean 3.2 / 3 over 8
    expected = (3.2 / 3.0) / 8.0 / math.sqrt(2.0)
    assert bench.spread(scene, [a, b, c], reference) == pytest.approx(expected, rel=1e-12)
    assert bench.spread(scene, [a, a.copy()], reference) == 0.0
