"""validation/bench_peers.py: its own conversions, checked without the peers (pyradiance, pyhelios3d).

The .rad export keeps every triangle and its area and writes the leaf optics exactly; the per-leaf
error and the radiosity -> irradiance -> absorbed-power map agree with hand-computed cases; the
leaves found are the generator's (2 triangles each).
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

import mirad
from conftest import ROOT, load_script


@pytest.fixture(scope="module")
def bench():
    return load_script(ROOT / "validation" / "bench_peers.py", "bench_peers")


@pytest.fixture(scope="module")
def canopy(bench, tmp_path_factory):
    path = bench.make_scene(tmp_path_factory.mktemp("peers"), leaves=12, seed=3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return mirad.load_scene(str(path))


def test_scene_has_translucent_leaves_of_two_triangles_each(bench, canopy):
    leaf, count = bench.leaf_index(canopy)
    assert count == 12
    assert np.array_equal(np.bincount(leaf[leaf >= 0]), np.full(count, 2))
    assert np.array_equal(leaf >= 0, canopy.tri_leaf)
    lv = bench.Leaves(canopy)
    assert np.allclose(lv.rho_f, bench.LEAF_RHO) and np.allclose(lv.rho_b, bench.LEAF_RHO)
    assert np.allclose(lv.tau_f, bench.LEAF_TAU) and np.allclose(lv.tau_b, bench.LEAF_TAU)


def test_rad_export_keeps_every_triangle_and_its_area(bench, canopy):
    sun, sky = bench.lights()
    text = bench.rad_text(canopy, sun_direction=-np.asarray(sun["direction"]), sun_irradiance=[600.0] * 3,
                          sky_radiance=sky["radiance"]["value"])
    count, area = bench.rad_polygons(text)
    assert count == canopy.triangle_count
    assert area == pytest.approx(float(canopy.tri_area.sum()), rel=1e-6)
    # the leaf optics exactly: front rho, back rho, tau per channel in one BRTDfunc; the soil a diffuse plastic
    brtd = [line.split() for line in text.splitlines() if " BRTDfunc " in line]
    assert len(brtd) == 1
    values = np.array(brtd[0][-9:], float)
    assert np.allclose(values, [*bench.LEAF_RHO, *bench.LEAF_RHO, *bench.LEAF_TAU])
    plastic = [line.split() for line in text.splitlines() if " plastic " in line]
    assert len(plastic) == 1 and np.allclose(np.array(plastic[0][-5:], float), [*bench.SOIL_RHO, 0, 0])
    # the sun gives its direct normal irradiance: radiance times the solid angle of its disc
    light = next(line.split() for line in text.splitlines() if " light " in line)
    omega = 2 * math.pi * (1 - math.cos(math.radians(bench.RAD_SUN_ANGLE) / 2))
    assert float(light[-1]) * omega == pytest.approx(600.0, rel=1e-6)
    # polygons keep the triangles' winding: the normal of the first polygon is the triangle's
    first = next(line.split() for line in text.splitlines() if " polygon t0 " in line)
    p = np.array(first[6:], float).reshape(3, 3)
    n = np.cross(p[1] - p[0], p[2] - p[0])
    assert np.allclose(n / np.linalg.norm(n), canopy.tri_normal[0], atol=1e-5)


def test_leaf_error_by_hand(bench):
    power = np.array([[1.0, 4.0], [3.0, 2.0], [2.0, 3.0]])
    ref = np.array([[2.0, 4.0], [2.0, 4.0], [2.0, 2.0]])
    # channel 0: (1 + 1 + 0) / 6; channel 1: (0 + 2 + 1) / 10; mean of the two
    assert bench.leaf_error(power, ref) == pytest.approx((2 / 6 + 3 / 10) / 2)
    assert bench.leaf_error(ref, ref) == 0.0


def test_absorbed_from_both_sides_radiosity_by_hand(bench):
    # a leaf of 2 triangles (1 and 3 m^2), rho 0.1 front, 0.2 back, tau 0.3; H front 10 and 4, back 2 and 1
    rho_f, rho_b, tau = np.full((2, 1), 0.1), np.full((2, 1), 0.2), np.full((2, 1), 0.3)
    h_f, h_b = np.array([[10.0], [4.0]]), np.array([[2.0], [1.0]])
    b_f, b_b = rho_f * h_f + tau * h_b, rho_b * h_b + tau * h_f
    got_f, got_b = bench.irradiance_from_radiosity(b_f, b_b, rho_f, rho_b, tau)
    assert np.allclose(got_f, h_f) and np.allclose(got_b, h_b)
    area = np.array([1.0, 3.0])
    p = bench.absorbed_from_irradiance(got_f, got_b, rho_f, rho_b, tau, tau, area)
    # (1 - 0.1 - 0.3) * 10 * 1 + (1 - 0.2 - 0.3) * 2 * 1 = 7; (0.6 * 4 + 0.5 * 1) * 3 = 8.7
    assert np.allclose(p, [[7.0], [8.7]])
    assert np.allclose(bench.per_leaf(p, np.array([0, 0]), 1), [[15.7]])
    with pytest.raises(ValueError, match="do not"):
        bench.irradiance_from_radiosity(b_f, b_b, tau, tau, tau)


def test_triangle_points_stratify_the_triangle(bench):
    corners = np.array([[[0.0, 0, 0], [2, 0, 0], [0, 1, 0]]])
    for n in (1, 4, 16):
        p = bench.triangle_points(corners, n)
        assert p.shape == (1, n, 3)
        assert np.allclose(p[0].mean(0), corners[0].mean(0))          # equal-area strata: mean = centroid
        assert np.all(p[0, :, 0] / 2 + p[0, :, 1] < 1) and np.all(p[0, :, :2] > 0)
    with pytest.raises(ValueError, match="square"):
        bench.triangle_points(corners, 3)


def test_time_at_interpolates_log_log(bench):
    assert bench.time_at(0.02, [1.0, 4.0], [0.04, 0.01]) == pytest.approx(2.0)
    assert math.isnan(bench.time_at(0.001, [1.0, 4.0], [0.04, 0.01]))
    assert bench.parse_radiance("p16 a4 ab3 ad256") == {"points": 16, "ambient": 4, "params": ["-ab", "3", "-ad", "256"]}
    assert bench.parse_helios("d100 s1000 k3") == {"direct": 100, "diffuse": 1000, "depth": 3}


def test_info_names_the_leaf_shapes_and_a_pattern_that_picks_them(bench, tmp_path, capsys):
    """`mirad info` on a scene with leaves says what share of the area they are and gives the
    --error-shapes pattern that holds the tolerance on them; the pattern names the leaf shapes and
    nothing else."""
    from mirad.cli import main

    path = bench.make_scene(tmp_path, leaves=12, seed=3)
    assert main(["info", str(path)]) == 0
    line = [x for x in capsys.readouterr().out.splitlines() if "leaf shapes:" in x][0]
    pattern = line.split("--error-shapes '")[1].rstrip("'")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = mirad.load_scene(str(path))
    leafy = sorted({scene.shape_ids[k] for k in np.unique(scene.tri_shape[scene.tri_leaf])})
    assert f"leaf shapes: {len(leafy)} (" in line
    sol = mirad.solve(scene, tolerance=0.3, error_shapes=pattern)
    assert sol.stats["error_shapes"] == leafy


def test_probe_blocker_names_the_crash_the_exception_or_nothing(bench):
    # a peer whose driver crashes (Mesa 22.3's lavapipe under Helios's runBand: SIGSEGV) must
    # not take the benchmark's process with it: the probe runs in a child and says how it ended
    crash = "import os, signal; os.kill(os.getpid(), signal.SIGSEGV)"
    said = bench.probe_blocker(crash, "a probe", 60)
    assert said.startswith("a probe crashed (SIGSEGV)")
    raising = "raise RuntimeError('no backend found.\\n  - NVIDIA: none\\n  - Vulkan: none')"
    said = bench.probe_blocker(raising, "a probe", 60)
    assert said == "RuntimeError: no backend found. - NVIDIA: none - Vulkan: none"
    assert bench.probe_blocker("import sys; sys.exit(3)", "a probe", 60) == "a probe failed (exit status 3)"
    assert bench.probe_blocker("print('fine')", "a probe", 60) is None
    assert bench.probe_blocker("import time; time.sleep(5)", "a probe", 0.5) == "a probe did not finish in 0.5 s"
