"""Absorbed power (``export.absorbed_power``): (1 - rho - tau) H A per side, translucent leaves
included; per-shape and per-organ tables add up to the per-triangle totals."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import mirad
import mitsuba as mi
from conftest import SCENES
from mirad import export

#: The loader's transmission notice for a leaf.
pytestmark = pytest.mark.filterwarnings("ignore:.*transmits light")

T = mi.ScalarTransform4f
RHO = np.array([0.1, 0.5, 0.2])
RHO_BACK = np.array([0.3, 0.1, 0.05])
TAU = np.array([0.3, 0.2, 0.6])


def leaf(rho, tau=TAU) -> dict:
    return {"type": "leaf", "reflectance": {"type": "rgb", "value": list(rho)},
            "transmittance": {"type": "rgb", "value": list(tau)}}


def solve(scene: dict, **options):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return mirad.solve(scene, **options)


def test_a_leaf_under_the_sun_absorbs_what_it_neither_reflects_nor_transmits():
    """A 2 x 2 m leaf alone under a sun of irradiance 2 W/m^2 at normal incidence: H = 2 on top, 0
    below, so it absorbs (1 - rho - tau) 2 W/m^2 x 4 m^2 = (4.8, 2.4, 1.6) W ((1 - rho) H A, 7.2 /
    4 / 6.4 W, counted the transmitted light as absorbed)."""
    sol = solve({"type": "scene", "blade": {"type": "rectangle", "id": "blade", "bsdf": leaf(RHO)},
                 "sun": {"type": "directional", "direction": [0, 0, -1], "irradiance": 2.0}}, tolerance=0.05)
    total = export.triangle_table(sol)["absorbed"].sum(0)
    assert np.allclose(total, (1 - RHO - TAU) * 2.0 * 4.0, rtol=1e-5)
    assert np.allclose(export.shape_summary(sol)["absorbed"][0], total, rtol=1e-12)


@pytest.fixture(scope="module")
def canopy():
    """Two tilted two-sided leaves (front rho RHO, back RHO_BACK, tau TAU both ways) over a white
    ground under a slanted sun: both sides of each leaf are lit, the undersides by the ground."""
    pair = {"type": "twosided", "allow_transmission": True, "front": leaf(RHO), "back": leaf(RHO_BACK)}
    scene = {"type": "scene",
             "sun": {"type": "directional", "direction": [0.3, 0.2, -1.0], "irradiance": 3.0},
             "ground": {"type": "rectangle", "id": "ground", "to_world": T().scale(3.0),
                        "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.6}}},
             "leaf_a": {"type": "rectangle", "id": "leaf_a", "bsdf": pair,
                        "to_world": T().translate([-0.6, 0, 1.0]).rotate([1, 0, 0], 20).scale(0.4)},
             "leaf_b": {"type": "rectangle", "id": "leaf_b", "bsdf": pair,
                        "to_world": T().translate([0.6, 0.2, 1.4]).rotate([0, 1, 0], -30).scale(0.5)}}
    return solve(scene, tolerance=0.05)


def test_absorbed_is_one_minus_rho_minus_tau_per_side_from_the_solutions_own_h(canopy, tmp_path):
    sol, scene = canopy, canopy.scene
    table = export.triangle_table(sol)
    leafy = scene.tri_leaf
    assert leafy.any() and (~leafy).any()
    assert np.all(table["back_irradiance"][leafy] > 0) and np.all(table["irradiance"][leafy] > 0)
    # tau from the scene's own arrays, rho from the loader: per side, per channel
    tau_f = np.where(leafy[:, None], scene.tri_transmittance, 0.0)
    tau_b = np.where(leafy[:, None], scene.back_transmittance, 0.0)
    assert np.allclose(tau_f[leafy], TAU) and np.allclose(tau_b[leafy], TAU)
    assert np.allclose(scene.tri_rho[leafy], RHO) and np.allclose(scene.back_rho[leafy], RHO_BACK)
    a = scene.tri_area[:, None]
    expected = ((1 - scene.tri_rho - tau_f) * table["irradiance"]
                + (1 - scene.back_rho - tau_b) * table["back_irradiance"]) * a
    assert np.allclose(table["absorbed"], expected, rtol=1e-12, atol=0)
    # the transmitted light is no longer counted: tau H A less per side on leaves, the ground as before
    old = ((1 - scene.tri_rho) * table["irradiance"] + (1 - scene.back_rho) * table["back_irradiance"]) * a
    transmitted = (tau_f * table["irradiance"] + tau_b * table["back_irradiance"]) * a
    assert np.allclose(old - table["absorbed"], transmitted, rtol=1e-9, atol=1e-12)
    assert np.all(transmitted[leafy] > 0)
    assert np.array_equal(table["absorbed"][~leafy], old[~leafy])
    # per shape and per organ: sums of the same per-triangle column
    summary = export.shape_summary(sol)
    assert np.allclose(summary["absorbed"].sum(0), table["absorbed"].sum(0), rtol=1e-12)
    for by in ("shape", "component"):
        organs = export.organ_table(sol, by=by)
        assert np.allclose(organs["absorbed"].sum(0), table["absorbed"].sum(0), rtol=1e-12)
    for i, sid in enumerate(sol.shape_ids):
        assert np.allclose(summary["absorbed"][i], table["absorbed"][table["shape"] == i].sum(0), rtol=1e-12)
    # a saved solution keeps tau: the same table without its scene
    again = mirad.load_solution(sol.save(tmp_path / "leaves.npz"))
    assert again.scene is None
    assert np.array_equal(export.triangle_table(again)["absorbed"], table["absorbed"])


def test_absorbed_of_an_opaque_scene_is_unchanged_bitwise(tmp_path):
    sol = mirad.solve(SCENES / "cornell-box" / "scene.xml", tolerance=0.1)
    table = export.triangle_table(sol)
    before = ((1 - sol.triangle_reflectance) * sol.triangle_irradiance
              + (1 - sol.back_reflectance) * sol.back_irradiance) * sol.triangle_area[:, None]
    assert np.array_equal(table["absorbed"], before)
    assert not np.any(sol.triangle_transmittance) and not np.any(sol.back_transmittance)
    with np.load(sol.save(tmp_path / "c.npz")) as data:
        assert "triangle_tau" not in data.files          # opaque solutions are saved as before
