"""Property-based tests (hypothesis) of invariants over random small scenes.

Each example is a closed box of random (dyadic) size with walls of random reflectance, one ceiling
light and a random tilted occluder quad inside; solves run at a coarse tolerance so an example costs
well under a second. Invariants: reciprocity of the sampled form factors, the energy bound
0 <= B <= E_max / (1 - rho_max), invariance under exact rigid motions (90 degree turns, dyadic
translations) and uniform power-of-two scaling, and determinism for a fixed seed.
"""

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings as hyp_settings, strategies as st

import mirad
from conftest import RECIPROCITY_REL
from mirad.settings import make_settings
from mirad.solver import Problem

import mitsuba as mi

T = mi.ScalarTransform4f
EXAMPLES = hyp_settings(max_examples=6, deadline=None, derandomize=True,
                        suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
#: A strict xfail needs only its first failing example; shrinking it took 15 s and asserts nothing more.
KNOWN_FAILURE = hyp_settings(EXAMPLES, phases=[Phase.explicit, Phase.reuse, Phase.generate])

dyadic = st.integers(4, 16).map(lambda k: k / 8)                 # 0.5 .. 2 m in steps of 1/8
rho = st.sampled_from([0.0, 0.25, 0.5, 0.75, 0.875])


@st.composite
def boxes(draw, occluder=True):
    """(size (3,), wall rhos (6,), occluder (centre (3,) in [-1/2, 1/2]^3 of the box, angle) or None)."""
    size = np.array([draw(dyadic) for _ in range(3)])
    rhos = [draw(rho) for _ in range(6)]
    occ = None
    if occluder:
        occ = (np.array([draw(st.integers(-3, 3)) / 8 for _ in range(3)]), draw(st.sampled_from([0, 30, 45, 90])))
    return size, rhos, occ


def _scene(size, rhos, occ, *, pre=None, floor_light=False):
    """The box [-size, size] with inward faces, a 0.25 x 0.25 light under the ceiling (``floor_light``:
    the floor emits instead, nothing inside the box), and the occluder. ``pre`` (a ScalarTransform4f)
    is applied after everything (the moved copies)."""
    pre = T() if pre is None else pre
    sx, sy, sz = map(float, size)
    faces = {
        "floor": T().translate([0, 0, -sz]).scale([sx, sy, 1]),
        "ceiling": T().translate([0, 0, sz]).rotate([1, 0, 0], 180).scale([sx, sy, 1]),
        "xp": T().translate([sx, 0, 0]).rotate([0, 1, 0], -90).scale([sz, sy, 1]),
        "xm": T().translate([-sx, 0, 0]).rotate([0, 1, 0], 90).scale([sz, sy, 1]),
        "yp": T().translate([0, sy, 0]).rotate([1, 0, 0], 90).scale([sx, sz, 1]),
        "ym": T().translate([0, -sy, 0]).rotate([1, 0, 0], -90).scale([sx, sz, 1]),
    }
    scene = {"type": "scene"}
    for (name, t), r in zip(faces.items(), rhos):
        scene[name] = {"type": "rectangle", "id": name, "to_world": pre @ t,
                       "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": r}}}
    if floor_light:
        scene["floor"]["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}
        return scene
    scene["light"] = {"type": "rectangle", "id": "light",
                      "to_world": pre @ T().translate([0, 0, sz * (1 - 1 / 64)]).rotate([1, 0, 0], 180).scale(0.125),
                      "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}},
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}}
    if occ is not None:
        c, angle = occ
        scene["occluder"] = {"type": "rectangle", "id": "occluder",
                             "to_world": pre @ T().translate((c * size).tolist()).rotate([1, 0, 0], angle).scale(0.25),
                             "bsdf": {"type": "twosided", "material": {"type": "diffuse",
                                                                        "reflectance": {"type": "rgb", "value": 0.5}}}}
    return scene


@EXAMPLES
@given(boxes(occluder=False))
def test_sampled_form_factors_are_reciprocal_between_unoccluded_faces(box):
    size, rhos, _ = box
    scene = mirad.load_scene(_scene(size, rhos, None, floor_light=True))
    prob = Problem(scene, make_settings(samples_per_link=256, clustering="off", core="legacy"))   # sampling noise < 1 %
    recv, src = prob.initial_pairs()
    links = prob.evaluate(recv, src, prob.geometry())
    assert np.all(links.ff >= 0) and np.all(links.ff <= 1)
    face = scene.tri_shape[scene.patch_tri]
    n = len(scene.shape_ids)
    transfer = np.zeros((n, n))
    np.add.at(transfer, (face[links.recv], face[links.src]), prob.elements.area[links.recv] * links.ff)
    walls = [scene.shape_index(s) for s in ("floor", "ceiling", "xp", "xm", "yp", "ym")]
    t = transfer[np.ix_(walls, walls)]
    np.testing.assert_allclose(t, t.T, rtol=RECIPROCITY_REL)


@EXAMPLES
@given(boxes())
def test_radiosity_stays_within_the_energy_bound(box):
    size, rhos, occ = box
    scene = mirad.load_scene(_scene(size, rhos, occ))
    sol = mirad.solve(scene, tolerance=0.2)
    b = sol.triangle_radiosity
    bound = scene.tri_emission.max() / (1 - max(scene.tri_rho.max(), scene.back_rho.max()))
    assert np.all(np.isfinite(b)) and b.min() >= 0 and b.max() <= bound * (1 + 1e-9)
    assert np.all(sol.back_radiosity >= 0) and sol.back_radiosity.max() <= bound * (1 + 1e-9)


@EXAMPLES
@given(boxes(), st.sampled_from([0.125, 0.5, 2.0, 4.0, 1024.0]))
def test_power_of_two_scaling_leaves_the_solution_bitwise_unchanged(box, scale):
    # a power-of-two scale is exact in float32: the scaled scene is the same geometry in other units,
    # and B (W/m^2, radiance kept) must not change at all
    size, rhos, occ = box
    base = mirad.solve(_scene(size, rhos, occ), tolerance=0.2)
    scaled = mirad.solve(_scene(size, rhos, occ, pre=T().scale(scale)), tolerance=0.2)
    assert scaled.stats["elements"] == base.stats["elements"]
    assert np.array_equal(scaled.triangle_radiosity, base.triangle_radiosity)


@pytest.mark.xfail(strict=True, reason="measured 2026-11-23 (llvm_ad_rgb): same element counts, but up to 1.35e-6 "
                   "relative on 3 of 48 triangles (turn + shift; 90/180 degree turns alone 1e-7..6e-7, shifts "
                   "alone 1.5e-7..6e-7): float32 evaluation order of the moved coordinates")
@KNOWN_FAILURE
@given(boxes(), st.sampled_from([0, 90, 180, 270]), st.tuples(*[st.integers(-8, 8).map(float)] * 3))
def test_exact_rigid_motion_leaves_the_solution_unchanged(box, turn, shift):
    # 90 degree turns and integer shifts of dyadic coordinates are exact in float32, so the moved scene
    # is the same geometry; issue 7: same elements, B within 1e-6 relative
    size, rhos, occ = box
    base = mirad.solve(_scene(size, rhos, occ), tolerance=0.2)
    moved = mirad.solve(_scene(size, rhos, occ, pre=T().translate(list(shift)).rotate([0, 0, 1], turn)),
                        tolerance=0.2)
    assert moved.stats["elements"] == base.stats["elements"]
    np.testing.assert_allclose(moved.triangle_radiosity, base.triangle_radiosity, rtol=1e-6, atol=1e-12)


@EXAMPLES
@given(boxes(), st.integers(0, 2**16))
def test_same_seed_gives_the_same_bits(box, seed):
    size, rhos, occ = box
    scene = mirad.load_scene(_scene(size, rhos, occ))
    a = mirad.solve(scene, tolerance=0.2, seed=seed)
    b = mirad.solve(scene, tolerance=0.2, seed=seed)
    assert np.array_equal(a.triangle_radiosity, b.triangle_radiosity)
    assert np.array_equal(a.back_radiosity, b.back_radiosity)
