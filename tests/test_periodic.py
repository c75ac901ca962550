"""Periodic ("infinite") canopies (mirad/periodic.py, docs/periodic.md): the pattern box's
refusals, wrapped ray queries against closed forms, energy under a sky, the periodic reference
against a large tiled canopy, and mirad against the periodic reference per leaf."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

import mirad
import mitsuba as mi
import drjit as dr
from conftest import run_cli
from mirad import periodic
from mirad.errors import SceneError, SettingsError

pytestmark = pytest.mark.filterwarnings("ignore:.*transmits light")

T = mi.ScalarTransform4f
HIER = {"core": "hierarchical", "quiet": True}


def leaf_bsdf() -> dict:
    def one(rho):
        return {"type": "leaf", "reflectance": {"type": "rgb", "value": rho},
                "transmittance": {"type": "rgb", "value": [0.05, 0.25, 0.04]}}
    return {"type": "twosided", "allow_transmission": True, "front": one([0.08, 0.35, 0.06]),
            "back": one([0.12, 0.4, 0.1])}


def pattern(n_leaves: int = 12, half: float = 1.0, seed: int = 3, *, tiles: int = 1, sun: bool = True,
            sky: bool = True, ground: bool = True) -> dict:
    """A plot [-half, half]^2 (z up) of n_leaves square two-sided translucent leaves (0.24 m)
    at random heights 0.3-0.9 m over a soil ground exactly the plot's size, under a slanted
    sun and a constant sky; ``tiles`` (odd) copies it tiles x tiles times side by side, the
    original in the middle (ids of the copies get a suffix)."""
    rng = np.random.default_rng(seed)
    leaves = [(rng.uniform(-half + 0.2, half - 0.2, 2), rng.uniform(0.3, 0.9), rng.uniform(0, 360),
               rng.uniform(0, 60)) for _ in range(n_leaves)]
    sc = {"type": "scene"}
    if sun:
        sc["sun"] = {"type": "directional", "direction": [-0.35, 0.3, -0.89],
                     "irradiance": {"type": "rgb", "value": [5.0, 4.7, 4.2]}}
    if sky:
        sc["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": [0.25, 0.32, 0.45]}}
    r = tiles // 2
    for i in range(-r, r + 1):
        for j in range(-r, r + 1):
            sfx = "" if (i, j) == (0, 0) else f"@{i},{j}"
            ox, oy = 2 * half * i, 2 * half * j
            if ground:
                sc["ground" + sfx] = {"type": "rectangle", "id": "ground" + sfx,
                                      "to_world": T().translate([ox, oy, 0]).scale([half, half, 1]),
                                      "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb",
                                                                                  "value": [0.25, 0.2, 0.15]}}}
            for k, (c, h, azimuth, tilt) in enumerate(leaves):
                sc[f"leaf{k}" + sfx] = {
                    "type": "rectangle", "id": f"leaf{k}" + sfx, "bsdf": leaf_bsdf(),
                    "to_world": T().translate([c[0] + ox, c[1] + oy, h]).rotate([0, 0, 1], azimuth)
                    .rotate([1, 0, 0], tilt).scale(0.12)}
    return sc


def load(scene: dict):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return mirad.load_scene(scene)


# ------------------------------------------------------------------------------------------
# The box and its refusals
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("value, words", [("1,2,3", "4"), ("0,0,-1,1", "empty"), ("a,0,1,1", "not a number"),
                                          ("0,0,nan,1", "NaN"), (3.0, "not a box")])
def test_bad_boxes_are_refused_naming_the_parameter_and_the_fix(value, words):
    with pytest.raises(SettingsError, match="periodic") as err:
        mirad.Settings(periodic=value, core="hierarchical")
    assert words in str(err.value) and "e.g." in str(err.value)


def test_the_legacy_core_and_a_bad_up_axis_are_refused():
    with pytest.raises(SettingsError, match="core='hierarchical'"):
        mirad.Settings(periodic="-1,-1,1,1")
    with pytest.raises(SettingsError, match="periodic_up"):
        mirad.Settings(periodic="-1,-1,1,1", periodic_up="up", core="hierarchical")


def test_a_box_that_does_not_contain_the_plants_is_refused_with_shape_box_and_fix():
    scene = load(pattern(4))
    with pytest.raises(SceneError) as err:
        mirad.solve(scene, periodic="-0.5,-1,1,1", **HIER)
    text = str(err.value)
    assert "shape 'ground'" in text and "x in [-0.5, 1] m" in text and "enlarge the box" in text
    # a point light's images are not summed: refused, with the way out
    scene = load({**pattern(2, sky=False), "lamp": {"type": "point", "position": [0, 0, 2], "intensity": 1.0}})
    with pytest.raises(SceneError, match="point or spot light.*area emitter"):
        mirad.solve(scene, periodic="-1,-1,1,1", **HIER)


def test_the_box_within_slack_is_accepted_and_given_in_the_files_frame():
    scene = load(pattern(2))
    settings = mirad.Settings(periodic=(-1.0005, -1, 1, 1.0005), **HIER)
    box = periodic.box_for(scene, settings)
    assert box.size == pytest.approx((2.0005, 2.0005)) and box.axes == (0, 1, 2)
    assert box.describe(scene.origin) == "x in [-1.0005, 1] m, y in [-1, 1.0005] m"


def test_cli_refuses_a_bad_box_without_a_traceback(tmp_path):
    from pathlib import Path

    scene = Path(__file__).resolve().parents[1] / "scenes" / "plant-canopy" / "scene.xml"
    out = run_cli("solve", str(scene), "--core", "hierarchical", "--periodic=-1,-1,1", "-o", str(tmp_path / "x.npz"))
    assert out.returncode != 0 and "periodic" in out.stderr and "Traceback" not in out.stderr
    out = run_cli("solve", str(scene), "--core", "hierarchical", "--periodic=-2,-2,2,2", "-o", str(tmp_path / "x.npz"))
    assert out.returncode != 0 and "shape 'ground'" in out.stderr and "Traceback" not in out.stderr


# ------------------------------------------------------------------------------------------
# Wrapped rays
# ------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def post_scene():
    """A 2 x 2 m box (z up) holding one post: a 0.2 m cube centred at (0.5, 0, 0.5) over a ground."""
    scene = load({"type": "scene", "sky": {"type": "constant"},
                  "ground": {"type": "rectangle", "id": "ground"},
                  "post": {"type": "cube", "id": "post", "to_world": T().translate([0.5, 0, 0.5]).scale(0.1)}})
    box = periodic.box_for(scene, mirad.Settings(periodic="-1,-1,1,1", **HIER))
    return scene, box


def vec(rows):
    rows = np.asarray(rows, np.float32)
    return mi.Vector3f(*(mi.Float(rows[:, k]) for k in range(3)))


def test_a_ray_hits_the_post_on_its_third_wrap(post_scene):
    """From (-0.9, 0.3, 0.5) with slope dy/dx = -0.04 the ray meets the planes of the post's
    -x face (x = 0.4 + 2 k in its images k = 0, 1, 2) at y = 0.248, 0.168, 0.088: it passes the
    first two images (|y| > 0.1, the post's half-width) and hits the third, two periods on."""
    scene, box = post_scene
    d = np.array([4.0, -0.16, 0.0])
    d /= np.linalg.norm(d)
    si, di, dj = periodic.ray_intersect(scene.mi_scene, box, vec([[-0.9, 0.3, 0.5]]), vec([d]))
    # y along the ray at the post's faces x = 0.4 + 2 k: 0.3 - 0.04 (1.3 + 2 k) = 0.248, 0.168, 0.088
    assert bool(si.is_valid()[0])
    assert int(di[0]) == -2 and int(dj[0]) == 0          # the hit lies two periods along +x
    assert float(si.p.x[0]) == pytest.approx(0.4, abs=1e-4)
    assert float(si.p.y[0]) == pytest.approx(0.3 - 0.04 * 5.3, abs=1e-4)
    assert bool(periodic.ray_test(scene.mi_scene, box, vec([[-0.9, 0.3, 0.5]]), vec([d]))[0])
    # cut short before the third image: free
    assert not bool(periodic.ray_test(scene.mi_scene, box, vec([[-0.9, 0.3, 0.5]]), vec([d]), 5.0)[0])


def test_rays_through_an_empty_box_cross_it_as_often_as_the_closed_form_says(post_scene):
    """Above the post (z in (0.6, 0.6001] is still inside the vertical extent) nothing can be
    hit: a ray climbing at slope s leaves the extent after (zmax - z) / s of horizontal travel,
    i.e. after floor(that / 2 m) wraps, and is never blocked; a ray at the post's height along
    y = 0.5 (off the post) never hits either, and stops at the safety cap."""
    scene, box = post_scene
    z0 = 0.55
    slope = 1e-3
    d = np.array([1.0, 0.0, slope])
    d /= np.linalg.norm(d)
    o = vec([[-1.0 + 1e-3, 0.5, z0]])
    hit, o_cell, seg, di, dj = periodic._march(scene.mi_scene, box, o, vec([d]), mi.Float(np.inf), mi.Bool(True))
    travel = (box.zmax - z0) / slope
    assert not bool(hit[0])
    assert -int(di[0]) == math.floor((travel - 1e-3) / 2.0 + 1e-9)
    # a horizontal ray wraps until the cap
    hit, _, _, di, _ = periodic._march(scene.mi_scene, box, vec([[0.0, 0.5, 0.5]]), vec([[1.0, 0.0, 0.0]]),
                                       mi.Float(np.inf), mi.Bool(True))
    assert not bool(hit[0]) and -int(di[0]) == periodic.MAX_WRAPS
    # a segment to a point given in unwrapped coordinates: blocked exactly when the post's image lies on it
    o = vec([[-0.9, 0.0, 0.5], [-0.9, 0.0, 0.5]])
    ends = np.array([[-1.45, 0.0, 0.5], [-1.3, 0.0, 0.5]])     # the post's image spans x in [-1.6, -1.4]
    dd = ends - np.array([[-0.9, 0.0, 0.5]] * 2)
    dist = np.linalg.norm(dd, axis=1)
    hit = periodic.ray_test(scene.mi_scene, box, o, vec(dd / dist[:, None]), mi.Float(dist.astype(np.float32)))
    assert hit.numpy().tolist() == [True, False]
