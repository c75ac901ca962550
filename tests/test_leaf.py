"""The ``leaf`` BSDF (mirad/leaf.py) and what the loader reads of it (mirad/scene.py).

Closed forms: a leaf's BSDF value is rho / pi * cos(theta_o) on the incident side and
tau / pi * |cos(theta_o)| on the other, its pdf the lobe's probability (channel means) times
|cos(theta_o)| / pi; under a light from above only, its underside's radiosity is tau times the
irradiance of its top.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

import mirad
from mirad.arrays import to_float
import mitsuba as mi
import drjit as dr

from conftest import F_PARALLEL, run_cli

#: The loader's transmission warning for a leaf (today's solver does not carry that light).
pytestmark = pytest.mark.filterwarnings("ignore:.*transmits light")

RHO = [0.1, 0.5, 0.2]
TAU = [0.3, 0.2, 0.6]
#: Float32 evaluation: values computed in single precision.
F32 = 1e-5

T = mi.ScalarTransform4f


def leaf(rho=RHO, tau=TAU) -> dict:
    return {"type": "leaf", "reflectance": {"type": "rgb", "value": rho},
            "transmittance": {"type": "rgb", "value": tau}}


def pair(front: dict, back: dict) -> dict:
    return {"type": "twosided", "allow_transmission": True, "front": front, "back": back}


def sun_scene(bsdf: dict, *, direction=(0, 0, -1), irradiance=2.0) -> dict:
    """A 2 x 2 m leaf square in z = 0 (front +z) under a directional light."""
    return {"type": "scene", "blade": {"type": "rectangle", "bsdf": bsdf},
            "sun": {"type": "directional", "direction": list(direction), "irradiance": irradiance}}


def interaction(wi: np.ndarray):
    """SurfaceInteraction3f in the local frame (normal +z) with the (N, 3) incident directions."""
    si = dr.zeros(mi.SurfaceInteraction3f, len(wi))
    si.wi = mi.Vector3f(*(to_float(wi[:, k]) for k in range(3)))
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    si.n = mi.Normal3f(0, 0, 1)
    return si


def colour(spectrum, n: int) -> np.ndarray:
    a = np.array(spectrum.numpy(), dtype=np.float64)
    return np.broadcast_to(a.T if a.ndim == 2 and a.shape[0] == 3 else a.reshape(-1, 3), (n, 3))


def directions(n: int, seed: int) -> np.ndarray:
    """(n, 3) unit vectors uniform on the sphere."""
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def load(scene: dict):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return mirad.load_scene(scene)


# ------------------------------------------------------------------------------------------
# The BSDF against its closed form
# ------------------------------------------------------------------------------------------

def test_eval_pdf_match_the_closed_form_on_both_sides():
    bsdf = mi.load_dict(leaf())
    n = 4096
    wi, wo = directions(n, 1), directions(n, 2)
    si, ctx = interaction(wi), mi.BSDFContext()
    vo = mi.Vector3f(*(to_float(wo[:, k]) for k in range(3)))
    value, pdf = colour(bsdf.eval(ctx, si, vo), n), np.array(bsdf.pdf(ctx, si, vo).numpy())
    both, both_pdf = bsdf.eval_pdf(ctx, si, vo)
    same = (wi[:, 2] * wo[:, 2] > 0)[:, None]
    cos = np.abs(wo[:, 2:3])
    expected = np.where(same, RHO, TAU) / np.pi * cos
    p_reflect = np.mean(RHO) / (np.mean(RHO) + np.mean(TAU))
    expected_pdf = np.where(same[:, 0], p_reflect, 1 - p_reflect) * cos[:, 0] / np.pi
    np.testing.assert_allclose(value, expected, rtol=F32, atol=1e-7)
    np.testing.assert_allclose(pdf, expected_pdf, rtol=F32, atol=1e-7)
    np.testing.assert_allclose(colour(both, n), value, rtol=F32, atol=1e-7)
    np.testing.assert_allclose(np.array(both_pdf.numpy()), pdf, rtol=F32, atol=1e-7)
    np.testing.assert_allclose(colour(bsdf.eval_diffuse_reflectance(si), n), np.broadcast_to(RHO, (n, 3)), rtol=F32)
    flags = int(bsdf.flags())
    for flag in (mi.BSDFFlags.DiffuseReflection, mi.BSDFFlags.DiffuseTransmission, mi.BSDFFlags.FrontSide,
                 mi.BSDFFlags.BackSide):
        assert flags & int(flag)
    assert bsdf.component_count() == 2


def test_sample_weights_pdf_and_albedos():
    """Each sample's weight is rho / P(reflect) or tau / P(transmit), equal to eval / pdf, and its pdf
    is ``pdf(wo)``; the weights' means per side are the albedos (Monte Carlo, 5 standard errors)."""
    bsdf = mi.load_dict(leaf())
    n = 1 << 16
    rng = np.random.default_rng(3)
    wi = directions(n, 4)
    si, ctx = interaction(wi), mi.BSDFContext()
    u = rng.random((n, 3)).astype(np.float32)
    bs, weight = bsdf.sample(ctx, si, to_float(u[:, 0]), mi.Point2f(to_float(u[:, 1]), to_float(u[:, 2])))
    weight = colour(weight, n)
    wo = np.array(bs.wo.numpy()).reshape(3, -1).T
    reflected = wi[:, 2] * wo[:, 2] > 0
    p_reflect = np.mean(RHO) / (np.mean(RHO) + np.mean(TAU))
    kind = np.array(bs.sampled_type.numpy())
    assert np.all((kind == int(mi.BSDFFlags.DiffuseReflection)) == reflected)
    assert np.all(np.array(bs.sampled_component.numpy()) == np.where(reflected, 0, 1))
    np.testing.assert_allclose(np.linalg.norm(wo, axis=1), 1, rtol=1e-5)
    np.testing.assert_allclose(weight, np.where(reflected[:, None], np.array(RHO) / p_reflect,
                                                np.array(TAU) / (1 - p_reflect)), rtol=F32)
    np.testing.assert_allclose(np.array(bs.pdf.numpy()), np.array(bsdf.pdf(ctx, si, bs.wo).numpy()), rtol=1e-4)
    value = colour(bsdf.eval(ctx, si, bs.wo), n)
    np.testing.assert_allclose(weight, value / np.array(bs.pdf.numpy())[:, None], rtol=1e-4)
    # lobe choice: binomial, 5 standard deviations
    assert abs(reflected.mean() - p_reflect) < 5 * math.sqrt(p_reflect * (1 - p_reflect) / n)
    # albedos: the mean weight sent back to the incident side is rho, through it tau
    through = ~reflected[:, None]
    for part, target in ((np.where(through, 0, weight), RHO), (np.where(through, weight, 0), TAU)):
        err = part.std(axis=0) / math.sqrt(n)
        assert np.all(np.abs(part.mean(axis=0) - target) < 5 * err), (part.mean(axis=0), target, err)


@pytest.mark.parametrize("wi", [(0.0, 0.0, 1.0), (0.6, 0.0, -0.8), (0.2, 0.98, 0.05)])
def test_sampling_passes_mitsubas_chi2_test(wi):
    from mitsuba.chi2 import BSDFAdapter, ChiSquareTest, SphericalDomain

    sample, pdf = BSDFAdapter("leaf", leaf(), wi=dr.normalize(mi.ScalarVector3f(wi)))
    test = ChiSquareTest(domain=SphericalDomain(), sample_func=sample, pdf_func=pdf, sample_dim=3,
                         sample_count=200_000)
    assert test.run()


def test_context_selects_one_lobe():
    bsdf = mi.load_dict(leaf())
    n = 1024
    wi = directions(n, 5)
    wi[:, 2] = np.abs(wi[:, 2]) + 0.1
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    si = interaction(wi)
    u = np.random.default_rng(6).random((n, 3)).astype(np.float32)
    for flag, component, albedo, side in ((mi.BSDFFlags.DiffuseReflection, 0, RHO, 1),
                                          (mi.BSDFFlags.DiffuseTransmission, 1, TAU, -1)):
        ctx = mi.BSDFContext(mi.TransportMode.Radiance, +flag, component)
        bs, weight = bsdf.sample(ctx, si, to_float(u[:, 0]), mi.Point2f(to_float(u[:, 1]), to_float(u[:, 2])))
        wo = np.array(bs.wo.numpy()).reshape(3, -1).T
        assert np.all(wo[:, 2] * side > 0)
        np.testing.assert_allclose(colour(weight, n), np.broadcast_to(albedo, (n, 3)), rtol=F32)


def test_plain_leaf_has_the_same_optics_on_both_sides_in_mitsubas_path_tracer():
    """Directional light of irradiance E from above or below: pi L_o = rho E on the lit side, tau E on
    the other (Mitsuba's own path integrator, one camera ray per case)."""
    for direction, lit, dark in (((0, 0, -1), 1.0, -1.0), ((0, 0, 1), -1.0, 1.0)):
        scene = mi.load_dict(sun_scene(leaf(), direction=direction))
        for side, albedo in ((lit, RHO), (dark, TAU)):
            assert np.allclose(pi_radiance(scene, side), 2.0 * np.array(albedo), rtol=1e-5)


def pi_radiance(scene, side: float) -> np.ndarray:
    """(3,) pi times the radiance Mitsuba's path tracer sees at the leaf's centre from ``side``."""
    integrator = mi.load_dict({"type": "path"})
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(0, 1)
    ray = mi.RayDifferential3f(mi.Point3f(0.1, 0.2, side), mi.Vector3f(0, 0, -side))
    radiance, _, _ = integrator.sample(scene, sampler, ray)
    return np.pi * colour(radiance, 1)[0]


def test_twosided_picks_the_leaf_facing_the_camera():
    """What twosided does with two leaves (the reason mirad asks for equal transmittances): the
    nested BSDF is chosen by the side of ``si.wi``, the camera's side in the path tracer, so light
    from above reaching a camera below passes with the *back* leaf's transmittance."""
    front, back = leaf([0.1, 0.1, 0.1], [0.3, 0.3, 0.3]), leaf([0.5, 0.5, 0.5], [0.2, 0.2, 0.2])
    scene = mi.load_dict(sun_scene(pair(front, back)))
    np.testing.assert_allclose(pi_radiance(scene, 1.0), 2.0 * 0.1, rtol=1e-5)   # front reflects
    np.testing.assert_allclose(pi_radiance(scene, -1.0), 2.0 * 0.2, rtol=1e-5)  # back leaf's tau
    with pytest.raises(mirad.SceneError, match="shape 'blade'.*same transmittance"):
        load(sun_scene(pair(front, back)))


# ------------------------------------------------------------------------------------------
# Path-traced reference: the underside of a leaf lit from above
# ------------------------------------------------------------------------------------------

def test_path_traced_underside_is_tau_times_the_top_irradiance():
    """A unit leaf square 1 m below a unit emitting square (radiance L, black): the top's mean
    irradiance is pi L F with F = 0.199825 (parallel squares); nothing lights the underside, so its
    radiosity is tau pi L F and the top's rho pi L F. The reference's own standard error sets the
    tolerance: 4 of them (2,048 paths per triangle side give about 1 %)."""
    L = 1.0
    scene = load({
        "type": "scene",
        "blade": {"type": "rectangle", "to_world": T().scale(0.5), "bsdf": leaf()},
        "lamp": {"type": "rectangle", "to_world": T().translate([0, 0, 1]).rotate([1, 0, 0], 180).scale(0.5),
                 "bsdf": {"type": "diffuse", "reflectance": 0.0},
                 "emitter": {"type": "area", "radiance": L}},
    })
    from mirad.reference import triangle_reference

    blade = np.flatnonzero(scene.tri_shape == scene.shape_index("blade"))
    irradiance = np.pi * L * F_PARALLEL
    for side, albedo, seed in (("back", TAU, 1), ("front", RHO, 2)):
        ref = triangle_reference(scene, samples_per_triangle=2048, seed=seed, triangles=blade, side=side)
        expected = np.broadcast_to(np.array(albedo) * irradiance, ref.radiosity.shape)
        assert np.all(ref.stderr < 0.02 * expected)
        assert np.all(np.abs(ref.radiosity - expected) < 4 * ref.stderr), (side, ref.radiosity, expected, ref.stderr)


# ------------------------------------------------------------------------------------------
# Loader: per-side reflectance and transmittance, patches
# ------------------------------------------------------------------------------------------

def test_loader_reads_a_leaf_on_both_sides():
    scene = load(sun_scene(leaf()))
    for values, expected in ((scene.tri_rho, RHO), (scene.back_rho, RHO), (scene.tri_transmittance, TAU),
                             (scene.back_transmittance, TAU)):
        np.testing.assert_allclose(values, np.broadcast_to(expected, values.shape), rtol=F32)
    assert np.all(scene.tri_specular == 0) and scene.tri_leaf.all() and scene.diffuse_transmission
    assert scene.features["translucent_leaf_triangles"] == scene.triangle_count == 2
    check_patches(scene)


def test_a_leaf_is_not_said_lost_by_the_loader_and_a_legacy_solve_counts_its_transmission():
    """The loader's warning that a BSDF "transmits light ... lost" is for what the diffuse, opaque
    model drops (glass, masks); a leaf's transmission is modelled and the default core carries it,
    yet every leaf scene was told it was lost. The legacy core does drop it: its model error says
    so (tau over rho on this plate, above any tolerance), the hierarchical core's is zero."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = mirad.load_scene(sun_scene(leaf()))
    assert not [w for w in caught if "transmits light" in str(w.message)]
    assert scene.approximations == [] and scene.non_diffuse_shapes == []
    carried = mirad.solve(scene, tolerance=0.1)
    assert carried.stats["leaf_transmission"] == "carried" and carried.stats["model_error"] == 0.0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        legacy = mirad.solve(scene, tolerance=0.1, core="legacy")
    assert legacy.stats["model_error"] > 0.1
    assert any("transmitting BSDFs" in str(w.message) for w in caught)


def test_loader_reads_a_twosided_pair_per_side():
    front, back = leaf([0.05, 0.1, 0.05], [0.04, 0.1, 0.03]), leaf([0.0, 0.0, 0.0], [0.04, 0.1, 0.03])
    scene = load(sun_scene(pair(front, back)))
    np.testing.assert_allclose(scene.tri_rho, [[0.05, 0.1, 0.05]] * 2, rtol=F32)
    np.testing.assert_allclose(scene.back_rho, 0.0, atol=1e-7)
    np.testing.assert_allclose(scene.tri_transmittance, [[0.04, 0.1, 0.03]] * 2, rtol=F32)
    np.testing.assert_allclose(scene.back_transmittance, [[0.04, 0.1, 0.03]] * 2, rtol=F32)
    # the back reflects nothing, but light passes through to it: it has its patches
    assert list(scene.back_triangles) == [0, 1]
    check_patches(scene)


def test_loader_reads_a_blend_of_a_leaf_and_a_one_sided_diffuse():
    """blendbsdf, weight 1/2: front rho (0.2 + 0.6) / 2, back 0.2 / 2 (diffuse is one-sided), tau 0.4 / 2
    both ways. A leaf beside an opaque back in twosided transmits one way only: refused."""
    scene = load(sun_scene({"type": "blendbsdf", "weight": 0.5, "a": {"type": "diffuse", "reflectance": 0.6},
                            "b": leaf([0.2] * 3, [0.4] * 3)}))
    assert scene.tri_leaf.all()
    for values, expected in ((scene.tri_rho, 0.4), (scene.back_rho, 0.1), (scene.tri_transmittance, 0.2),
                             (scene.back_transmittance, 0.2)):
        np.testing.assert_allclose(values, expected, rtol=F32)
    check_patches(scene)
    with pytest.raises(mirad.SceneError, match=r"front side transmits 0\.3 and its back side 0;"):
        load(sun_scene(pair(leaf([0.2] * 3, [0.3] * 3), {"type": "diffuse"})))


def check_patches(scene):
    """patch_opposite pairs the two sides of a triangle; patch_transmittance is the side's own value."""
    P, T = len(scene.patch_tri), scene.triangle_count
    opposite, tau = scene.patch_opposite, scene.patch_transmittance
    assert opposite.shape == (P,) and tau.shape == (P, scene.channels)
    has = opposite >= 0
    assert np.all(opposite[opposite[has]] == np.flatnonzero(has))            # an involution
    assert np.all(scene.patch_tri[opposite[has]] == scene.patch_tri[has])    # same triangle
    assert np.all(scene.patch_side[opposite[has]] != scene.patch_side[has])  # other side
    front, back = np.arange(T), np.arange(T, P)
    np.testing.assert_array_equal(tau[front], np.where(scene.tri_leaf[:, None], scene.tri_transmittance, 0))
    np.testing.assert_array_equal(tau[back], np.where(scene.tri_leaf[:, None], scene.back_transmittance, 0)[
        scene.patch_tri[back]])
    assert np.all(tau[~has] == 0)                               # nothing to hand over without a patch
    assert np.all(scene.patch_rho + tau <= 1 + 1e-6)


def test_loader_reads_a_bitmap_leaf_per_triangle():
    """Two texels, u < 1/2 and u > 1/2 (nearest lookup): each triangle of the rectangle covers 1/4 of
    its uv area with one and 3/4 with the other; the loader's grid of points has a line at u = 1/2,
    so its per-triangle means are exact."""
    rho_texels = np.array([[[0.1, 0.2, 0.3], [0.5, 0.4, 0.2]]], np.float32)
    tau_texels = np.array([[[0.6, 0.5, 0.4], [0.2, 0.3, 0.1]]], np.float32)
    texture = lambda a: {"type": "bitmap", "data": mi.TensorXf(a), "raw": True,  # noqa: E731
                         "filter_type": "nearest"}
    scene = load(sun_scene({"type": "leaf", "reflectance": texture(rho_texels),
                            "transmittance": texture(tau_texels)}))
    uv = scene.vertex_uv[scene.faces]                                      # (T, 3, 2)
    left = np.array([clipped_area(t, 0.5) / clipped_area(t, np.inf) for t in uv])  # share with u < 1/2
    for values, texels in ((scene.tri_rho, rho_texels), (scene.back_rho, rho_texels),
                           (scene.tri_transmittance, tau_texels), (scene.back_transmittance, tau_texels)):
        expected = left[:, None] * texels[0, 0] + (1 - left[:, None]) * texels[0, 1]
        np.testing.assert_allclose(values, expected, rtol=1e-4)
    assert sorted(np.round(left, 6)) == [0.25, 0.75]
    check_patches(scene)


def test_an_8_bit_image_leaf_loads_with_its_linear_values(tmp_path):
    """PNG texels are stored sRGB-encoded (200 of 255); the leaf reads them as Mitsuba looks them up
    (linear 0.578), and the loader refuses the raw reading (0.784) plus 0.3 above 1."""
    path = tmp_path / "rho.png"
    mi.Bitmap(np.full((2, 2, 3), 200, np.uint8)).write(str(path))
    image = {"type": "bitmap", "filename": str(path)}
    scene = load(sun_scene({"type": "leaf", "reflectance": image, "transmittance": 0.3}))
    c = 200 / 255
    np.testing.assert_allclose(scene.tri_rho, ((c + 0.055) / 1.055) ** 2.4, rtol=1e-3)   # sRGB to linear
    with pytest.raises(mirad.SceneError, match=r"front reflectance 0\.784 \+ transmittance 0\.3"):
        load(sun_scene({"type": "leaf", "reflectance": dict(image, raw=True), "transmittance": 0.3}))


def clipped_area(tri: np.ndarray, u_max: float) -> float:
    """Area of the part u < u_max of a uv triangle (3, 2): Sutherland-Hodgman against one line."""
    poly = []
    for a, b in zip(tri, np.roll(tri, -1, axis=0)):
        if a[0] < u_max:
            poly.append(a)
        if (a[0] < u_max) != (b[0] < u_max):
            t = (u_max - a[0]) / (b[0] - a[0])
            poly.append(a + t * (b - a))
    if len(poly) < 3:
        return 0.0
    p = np.array(poly)
    return 0.5 * abs(np.dot(p[:, 0], np.roll(p[:, 1], -1)) - np.dot(p[:, 1], np.roll(p[:, 0], -1)))


def test_other_bsdfs_keep_their_patches_and_transmit_nothing_to_the_other_side():
    """Glass and opaque two-sided surfaces are not leaves: no transmittance handed over, back patches
    as before (back reflectance > 0), and a leaf that transmits nothing is no translucent leaf."""
    glass = load(sun_scene({"type": "thindielectric"}))
    assert glass.tri_transmittance.max() > 0.5 and not glass.tri_leaf.any() and not glass.diffuse_transmission
    np.testing.assert_array_equal(glass.back_triangles, np.flatnonzero(glass.back_rho.max(axis=1) > 0))
    assert np.all(glass.patch_transmittance == 0)
    opaque = load(sun_scene(leaf(tau=[0.0, 0.0, 0.0])))
    assert not opaque.diffuse_transmission and opaque.features["translucent_leaf_triangles"] == 0
    assert opaque.warnings == []                    # a leaf that transmits nothing is exactly diffuse
    cornell_like = load(sun_scene({"type": "twosided", "m": {"type": "diffuse", "reflectance": 0.5}}))
    assert not cornell_like.tri_leaf.any() and np.all(cornell_like.patch_transmittance == 0)
    assert list(cornell_like.patch_opposite) == [2, 3, 0, 1]


def test_a_normal_mapped_leaf_is_measured_by_sampling_not_refused():
    """Under a normal map a leaf's lobes follow the tilted normal, so pi f / cos is no albedo: the
    loader measures it by sampling like any other BSDF (no point-by-point refusal), still as a leaf
    (lobes diffuse, transmittance handed over); a tilted normal only loses light, never adds it."""
    tilted = mi.TensorXf(np.array([[[0.8, 0.5, 0.9]]], np.float32))
    scene = load(sun_scene({"type": "normalmap", "normalmap": {"type": "bitmap", "raw": True, "data": tilted},
                            "bsdf": leaf([0.45] * 3, [0.45] * 3)}))
    assert scene.tri_leaf.all() and scene.diffuse_transmission
    for rho, tau in ((scene.tri_rho, scene.tri_transmittance), (scene.back_rho, scene.back_transmittance)):
        assert np.all((rho > 0.2) & (rho <= 0.45 + 0.01) & (tau > 0.2) & (tau <= 0.45 + 0.01))
    check_patches(scene)


def test_a_grey_leaf_that_transmits_in_colour_is_not_grey():
    assert not load(sun_scene(leaf([0.2] * 3, [0.1, 0.3, 0.1]))).grey
    assert load(sun_scene(leaf([0.2] * 3, [0.3] * 3))).grey


def test_fingerprint_sees_the_transmittance_of_leaves():
    a, b = load(sun_scene(leaf())), load(sun_scene(leaf(tau=[0.3, 0.2, 0.5])))
    assert a.fingerprint != b.fingerprint
    assert a.fingerprint == load(sun_scene(leaf())).fingerprint


# ------------------------------------------------------------------------------------------
# Registration
# ------------------------------------------------------------------------------------------

LEAF_XML = """<scene version="3.0.0">
    <shape type="rectangle" id="blade">
        <bsdf type="twosided">
            <boolean name="allow_transmission" value="true"/>
            <bsdf type="leaf">
                <rgb name="reflectance" value="0.06, 0.12, 0.05"/>
                <rgb name="transmittance" value="0.04, 0.10, 0.03"/>
            </bsdf>
            <bsdf type="leaf">
                <rgb name="reflectance" value="0.10, 0.16, 0.09"/>
                <rgb name="transmittance" value="0.04, 0.10, 0.03"/>
            </bsdf>
        </bsdf>
    </shape>
    <emitter type="directional"><vector name="direction" value="0, 0, -1"/></emitter>
</scene>
"""


def test_a_leaf_scene_file_loads_in_mitsuba_and_in_mirad(tmp_path):
    path = tmp_path / "leaf.xml"
    path.write_text(LEAF_XML)
    mi_scene = mi.load_file(str(path))
    assert np.allclose(pi_radiance(mi_scene, -1.0), [0.04, 0.10, 0.03], rtol=1e-5)  # irradiance 1 through it
    scene = load(path)
    np.testing.assert_allclose(scene.back_rho, [[0.10, 0.16, 0.09]] * 2, rtol=F32)
    np.testing.assert_allclose(scene.patch_transmittance, [[0.04, 0.10, 0.03]] * 4, rtol=F32)


def test_registered_in_every_variant_mirad_sets():
    """``import mirad`` registers ``leaf`` and registers it again after a variant change."""
    import subprocess
    import sys

    code = ("import mirad, mitsuba as mi; d = {'type': 'leaf', 'reflectance': 0.2, 'transmittance': 0.3}; "
            "mi.load_dict(d); mi.set_variant('scalar_rgb'); b = mi.load_dict(d); "
            "mi.set_variant('llvm_ad_rgb'); mi.load_dict(d); print('flags', int(b.flags()))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "flags" in res.stdout


# ------------------------------------------------------------------------------------------
# Refusals
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("rho, tau, match", [
    (0.7, 0.5, r"shape 'blade': leaf BSDF.*reflectance 0\.7 \+ transmittance 0\.5 = 1\.2 > 1.*lower them"),
    ([0.2, 0.6, 0.2], [0.2, 0.5, 0.2], r"= 1\.1 > 1 in the green channel"),
    (-0.1, 0.5, r"shape 'blade': leaf BSDF.*reflectance -0\.1 < 0; give a reflectance between 0 and 1"),
    (0.1, 1.5, r"shape 'blade': leaf BSDF.*transmittance 1\.5 > 1"),
    ([-0.1, 0.2, 0.2], 0.5, r"must be in the range.*give reflectances between 0 and 1"),   # Mitsuba's rgb
])
def test_bad_values_are_refused_naming_the_shape_and_the_fix(rho, tau, match):
    """Plain numbers are the plugin's to check; an ``rgb`` outside [0, 1] Mitsuba refuses itself."""
    value = lambda v: {"type": "rgb", "value": v} if isinstance(v, list) else v  # noqa: E731
    with pytest.raises(mirad.SceneError, match=match):
        mirad.load_scene(sun_scene({"type": "leaf", "reflectance": value(rho), "transmittance": value(tau)}))


def test_missing_or_misspelt_parameters_and_twosided_without_allow_transmission_are_refused():
    with pytest.raises(mirad.SceneError, match="parameter 'transmittance' is missing"):
        mirad.load_scene(sun_scene({"type": "leaf", "reflectance": 0.1}))
    with pytest.raises(mirad.SceneError, match="unknown parameter 'transmitance'"):
        mirad.load_scene(sun_scene({"type": "leaf", "reflectance": 0.1, "transmittance": 0.1, "transmitance": 0.1}))
    with pytest.raises(mirad.SceneError, match="allow_transmission"):
        mirad.load_scene(sun_scene({"type": "twosided", "m": leaf()}))


def test_textures_are_checked_point_by_point():
    """A bitmap plus a constant above 1 is refused by the plugin; two bitmaps whose largest texels add
    above 1 at different places load, and two that do at one place are refused by the loader."""
    bitmap = lambda a: {"type": "bitmap", "data": mi.TensorXf(np.array(a, np.float32)), "raw": True,  # noqa: E731
                        "filter_type": "nearest"}
    with pytest.raises(mirad.SceneError, match="reaches 1.3 > 1"):
        mirad.load_scene(sun_scene({"type": "leaf", "reflectance": bitmap([[[0.2] * 3, [0.8] * 3]]),
                                    "transmittance": 0.5}))
    per_channel = load(sun_scene({"type": "leaf", "reflectance": bitmap([[[0.9, 0.1, 0.1], [0.1] * 3]]),
                                  "transmittance": {"type": "rgb", "value": [0.05, 0.8, 0.8]}}))
    assert np.all(per_channel.tri_rho + per_channel.tri_transmittance <= 1)    # 0.95, 0.9, 0.9 at most
    fine = load(sun_scene({"type": "leaf", "reflectance": bitmap([[[0.2] * 3, [0.8] * 3]]),
                           "transmittance": bitmap([[[0.7] * 3, [0.1] * 3]])}))
    assert np.all(fine.tri_rho + fine.tri_transmittance <= 1)
    with pytest.raises(mirad.SceneError, match=r"shape 'blade': front reflectance 0\.8 \+ transmittance 0\.7 "
                                               r"= 1\.5 > 1 \(at uv"):
        mirad.load_scene(sun_scene({"type": "leaf", "reflectance": bitmap([[[0.2] * 3, [0.8] * 3]]),
                                    "transmittance": bitmap([[[0.1] * 3, [0.7] * 3]])}))


def test_xml_refusal_names_line_and_shape_and_the_cli_says_it_in_one_line(tmp_path):
    bad = tmp_path / "bad.xml"
    bad.write_text(LEAF_XML.replace('value="0.04, 0.10, 0.03"', 'value="0.04, 0.90, 0.03"', 1))
    with pytest.raises(mirad.SceneError) as info:
        mirad.load_scene(bad)
    message = str(info.value)
    assert message.startswith(f"{bad} (line 5): shape 'blade': leaf BSDF") and "\n" not in message
    assert "0.12 + transmittance 0.9 = 1.02 > 1 in the green channel" in message
    res = run_cli("solve", bad, "-o", tmp_path / "x.ply")
    assert res.returncode != 0 and "Traceback" not in res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "shape 'blade'" in lines[0] and "reflectance + transmittance <= 1" in lines[0]
    assert not (tmp_path / "x.ply").exists()


# ------------------------------------------------------------------------------------------
# The hierarchical core carries the transmitted light to the other side
# ------------------------------------------------------------------------------------------

def test_the_hierarchical_core_sends_the_transmitted_light_out_of_the_other_side():
    """Sun on the top of a leaf (nothing below): the top's radiosity is rho H and the
    underside's tau H, exactly (the loader's per-side optics, the solver's transfer)."""
    scene = load(sun_scene(pair(leaf(), leaf([0.2, 0.3, 0.1], TAU))))
    sol = mirad.solve(scene, tolerance=0.05, core="hierarchical", quiet=True)
    h = sol.triangle_irradiance
    np.testing.assert_allclose(h, 2.0, rtol=1e-6)
    np.testing.assert_allclose(sol.triangle_radiosity, np.array(RHO) * h, rtol=1e-6)
    np.testing.assert_allclose(sol.back_radiosity, np.array(TAU) * h, rtol=1e-6)
    assert sol.stats["leaf_transmission"] == "carried" and sol.stats["model_error"] == 0.0


def test_light_through_a_leaf_lights_the_floor_below_as_in_the_path_tracer():
    """A leaf 0.5 m above a white floor under a square lamp: the floor under the leaf gets the
    light the leaf transmits, and the leaf's underside the floor's light plus what passes
    through from the top. Per-shape means against Mitsuba's path tracer with the same leaf."""
    from mirad.reference import triangle_reference

    scene = load({
        "type": "scene",
        "blade": {"type": "rectangle", "to_world": T().translate([0, 0, 0.5]).scale(0.5), "bsdf": leaf()},
        "floor": {"type": "rectangle", "to_world": T().scale(1.5),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.7}}},
        "lamp": {"type": "rectangle", "to_world": T().translate([0, 0, 1.5]).rotate([1, 0, 0], 180).scale(0.5),
                 "bsdf": {"type": "diffuse", "reflectance": 0.0}, "emitter": {"type": "area", "radiance": 1.0}},
    })
    tol = 0.02
    sol = mirad.solve(scene, tolerance=tol, core="hierarchical", quiet=True)
    area = scene.tri_area
    for sid, side in (("floor", "front"), ("blade", "back"), ("blade", "front")):
        tris = np.flatnonzero(scene.tri_shape == scene.shape_index(sid))
        ref = triangle_reference(scene, samples_per_triangle=8192, seed=4, triangles=tris, side=side)
        mine = (sol.back_radiosity if side == "back" else sol.triangle_radiosity)[tris]
        w = area[tris, None]
        mean, mean_ref = (w * mine).sum(0) / w.sum(), (w * ref.radiosity).sum(0) / w.sum()
        noise = np.sqrt((w ** 2 * ref.stderr ** 2).sum(0)) / w.sum()
        assert np.all(np.abs(mean - mean_ref) <= 1.5 * tol * mean_ref + 3 * noise), (sid, side, mean, mean_ref)
