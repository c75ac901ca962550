"""The scale canopy generator (scenes/canopy-scale/make.py) and per-leaf absorbed power."""

from __future__ import annotations


import numpy as np
import pytest

import mirad
from conftest import SCENES, load_script
from mirad import export


@pytest.fixture(scope="module")
def make():
    return load_script(SCENES / "canopy-scale" / "make.py", "canopy_make")


@pytest.mark.parametrize("triangles", [1000, 10000, 100000])
def test_plan_hits_the_requested_size(make, triangles):
    plants, per = make.plan(triangles)
    assert abs(2 * plants * per - triangles) <= 0.01 * triangles
    assert plants >= 1 and per >= 1


def test_canopy_geometry(make, tmp_path):
    path = make.make_canopy(tmp_path / "c", plants=3, leaves_per_plant=20, seed=4)
    scene = mirad.load_scene(path)
    assert scene.shape_ids[0] == "ground" or "ground" in scene.shape_ids
    leaf_tris = np.flatnonzero(scene.tri_shape != scene.shape_index("ground"))
    assert len(leaf_tris) == 2 * 3 * 20
    # every leaf is a diamond: triangles 2j, 2j+1 of a plant, coplanar, together L * W / 2
    for k in range(1, 4):
        tris = np.flatnonzero(scene.tri_shape == scene.shape_index(f"plant-{k}"))
        pair_area = scene.tri_area[tris].reshape(-1, 2).sum(axis=1)
        np.testing.assert_allclose(pair_area, make.LEAF_LENGTH * make.LEAF_WIDTH / 2, rtol=1e-5)
        n = scene.tri_normal[tris].reshape(-1, 2, 3)
        np.testing.assert_allclose(np.einsum("lc,lc->l", n[:, 0], n[:, 1]), 1.0, atol=1e-5)
    # leaves are two-sided (back patches), the ground is not
    assert len(scene.patch_tri) == scene.triangle_count + len(leaf_tris)
    # same seed, same scene; another seed, another scene
    again = mirad.load_scene(make.make_canopy(tmp_path / "d", plants=3, leaves_per_plant=20, seed=4))
    other = mirad.load_scene(make.make_canopy(tmp_path / "e", plants=3, leaves_per_plant=20, seed=5))
    assert again.fingerprint == scene.fingerprint != other.fingerprint


def test_per_leaf_absorbed_power(make, tmp_path):
    """Per-leaf absorbed power from the per-triangle table: pairs of triangles, summing to the
    shape summary; every leaf absorbs something (sky light reaches all of them)."""
    path = make.make_canopy(tmp_path / "c", plants=2, leaves_per_plant=40, seed=1)
    sol = mirad.solve(path, tolerance=0.2)
    table = export.triangle_table(sol)
    summary = export.shape_summary(sol)
    absorbed = table["absorbed"]                                       # (T, C) W
    for k in (1, 2):
        s = sol.shape_ids.index(f"plant-{k}")
        rows = np.flatnonzero(table["shape"] == s) if "shape" in table else np.flatnonzero(sol.triangle_shape == s)
        per_leaf = absorbed[rows].reshape(-1, 2, absorbed.shape[1]).sum(axis=1)
        assert per_leaf.shape[0] == 40
        assert np.all(per_leaf > 0)
        np.testing.assert_allclose(per_leaf.sum(axis=0), summary["absorbed"][s], rtol=1e-9)
        # a leaf cannot absorb more than its two sides receive: (1 - rho) (H_front + H_back) A
        area = sol.triangle_area[rows].reshape(-1, 2).sum(axis=1)
        assert np.all(per_leaf[:, 0] <= area * (table["irradiance"][rows, 0] + table["back_irradiance"][rows, 0]
                                                ).reshape(-1, 2).max(axis=1) + 1e-12)
