"""Convolution soft shadows (mirad/shadows.py) against closed forms and shadow rays."""

from __future__ import annotations

import numpy as np
import pytest

import mirad  # noqa: F401
import mitsuba as mi

from mirad import shadows as S

T = mi.ScalarTransform4f


def rect(to_world, *, emit=False):
    d = {"type": "rectangle", "to_world": to_world, "bsdf": {"type": "diffuse"}}
    if emit:
        d["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}
    return d


def square(half, z, *, down=True):
    """(4, 3) corners of an axis-aligned square in the plane z, facing -z (down) or +z."""
    c = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]], float)
    return c[::-1] if down else c


# parallel planes: source of width s at height D, occluder of width w at height D - a
S_HALF, W_HALF, D, A = 0.2, 0.3, 2.0, 0.8
B = D - A
RES = 64


@pytest.fixture(scope="module")
def parallel():
    scene = mi.load_dict({"type": "scene", "occ": rect(T().translate([0, 0, B]).scale(W_HALF))}, optimize=False)
    receiver = square(1.5, 0.0, down=False)
    tex = S.shadow_texture(scene, square(S_HALF, D), receiver, RES, weighting="uniform")
    return scene, receiver, tex


def closed_form_visibility(x, y):
    """Exact visible fraction of the square source from (x, y, 0): the occluded part of the
    source is the product of two interval overlaps (rays x_s -> y cross the occluder plane at
    (b x_s + a y) / (a + b), section 5.1)."""
    def overlap(t):
        lo = (-(A + B) * W_HALF - A * t) / B
        hi = ((A + B) * W_HALF - A * t) / B
        return np.clip(np.minimum(hi, S_HALF) - np.maximum(lo, -S_HALF), 0, None) / (2 * S_HALF)
    return 1.0 - overlap(x) * overlap(y)


def test_parallel_planes_closed_form(parallel):
    _, receiver, tex = parallel
    v = tex.texture[0]
    pts = S.receiver_points(receiver[None], RES)[0]
    exact = closed_form_visibility(pts[..., 0], pts[..., 1])
    texel = 3.0 / RES
    # texel-wise: within the rasterisation of the occluder edge (half a texel of the penumbra)
    penumbra = 2 * S_HALF * B / A                                   # s b / a = 0.6 m
    assert np.abs(v - exact).max() <= 0.5 * texel / penumbra + 0.01
    assert np.abs(v - exact).mean() < 0.005
    # penumbra width and umbra extent along the centre row
    row = v[:, RES // 2]
    x = pts[:, RES // 2, 0]
    umbra = x[row < 1e-3]
    umbra_half = W_HALF * D / A - S_HALF * B / A                    # 0.75 - 0.3 = 0.45
    assert abs((umbra.max() - umbra.min() + texel) / 2 - umbra_half) <= texel
    pen = x[(row > 1e-3) & (row < 1 - 1e-3) & (x > 0)]
    assert abs(pen.max() - pen.min() + texel - penumbra) <= 1.5 * texel
    # a single depth, parallel planes: nothing to predict wrong
    assert tex.layers[0] == 1
    assert tex.predicted_error[0] < 1e-3


def test_texels_match_shadow_rays(parallel):
    scene, receiver, tex = parallel
    pts = S.receiver_points(receiver[None], RES)[0].reshape(-1, 3)
    normals = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    v_ray, se = S.ray_visibility(scene, square(S_HALF, D), pts, normals, rays=256, weighting="uniform")
    diff = tex.texture[0].ravel() - v_ray
    # texel-wise within the rays' noise (plus the mask's half-texel edge rasterisation)
    assert np.mean(np.abs(diff) <= 3 * se + 0.02) > 0.99
    assert abs(diff.mean()) < 0.002


def test_texture_energy_matches_ray_form_factor():
    """mean(F_unocc V) of a texture link against the ray-sampled form factor with visibility,
    with a tilted occluder (several depth layers of one object) and kernel weighting."""
    occ = T().translate([0.1, 0, 1.0]).rotate([0, 1, 0], 35).scale(0.25)
    scene = mi.load_dict({"type": "scene", "occ": rect(occ)}, optimize=False)
    source, receiver = square(0.15, 2.0), square(1.0, 0.0, down=False)
    tex = S.shadow_texture(scene, source, receiver, 48)
    assert 0.3 < tex.mean_visibility[0] < 0.95
    assert tex.ff[0] == pytest.approx(tex.ff_unoccluded[0] * tex.mean_visibility[0], rel=1e-9)
    # reference: random receiver points, Lambert's unoccluded F times kernel-weighted ray visibility
    rng = np.random.default_rng(3)
    uv = rng.random((4096, 2))
    pts = receiver[0] + uv[:, :1] * (receiver[1] - receiver[0]) + uv[:, 1:] * (receiver[3] - receiver[0])
    normals = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    vis, _ = S.ray_visibility(scene, source, pts, normals, rays=64)
    f_point = S.point_form_factor(pts, normals, np.repeat(source[None], len(pts), 0))
    ff_ray = np.mean(f_point * vis)
    se = np.std(f_point * vis) / np.sqrt(len(pts))
    # energy error of the texture link within its own predicted (mean visibility) error
    assert abs(tex.ff[0] - ff_ray) < 3 * se + tex.ff_unoccluded[0] * tex.predicted_error[0]
    # the unoccluded part against Lambert at the same points
    assert tex.ff_unoccluded[0] == pytest.approx(f_point.mean(), rel=0.02)


def test_depth_layers_fall_back_to_rays():
    """Two occluders at very different depths each hide one half of the source from the
    receiver centre (where the truth is V = 0 and a two-layer product would say 1/4): the
    depth spread and layer-combination terms predict an error above tolerance and the
    decision goes to rays. One occluder alone keeps the texture."""
    near_src = rect(T().translate([-0.5, 0, 1.6]).scale([0.5, 1.0, 1.0]))   # hides x_s < 0 from the origin
    near_rcv = rect(T().translate([0.5, 0, 0.4]).scale([0.5, 1.0, 1.0]))    # hides x_s > 0
    source, receiver = square(0.2, 2.0), square(0.5, 0.0, down=False)
    both = mi.load_dict({"type": "scene", "a": near_src, "b": near_rcv}, optimize=False)
    tex = S.shadow_texture(both, source, receiver, 32)
    assert tex.layers[0] >= 2
    pts = S.receiver_points(receiver[None], 32)[0].reshape(-1, 3)
    v_ray, _ = S.ray_visibility(both, source, pts, np.tile([0.0, 0.0, 1.0], (len(pts), 1)), rays=64)
    err = np.abs(tex.texture[0].ravel() - v_ray).mean()
    tolerance = 0.05
    # the prediction (depth spread + layer combination) is conservative and above tolerance
    assert tex.predicted_error[0] >= err
    assert tex.predicted_error[0] > tolerance
    assert tex.combination_error[0] > 0.0
    assert not S.prefer_texture(tex.predicted_error, tolerance)[0]
    # one occluder, one depth: the texture is kept and agrees with the rays to their noise
    one = mi.load_dict({"type": "scene", "a": near_src}, optimize=False)
    single = S.shadow_texture(one, source, receiver, 32)
    v_one, se = S.ray_visibility(one, source, pts, np.tile([0.0, 0.0, 1.0], (len(pts), 1)), rays=64)
    assert single.layers[0] == 1
    assert S.prefer_texture(single.predicted_error, tolerance)[0]
    assert np.abs(single.texture[0].ravel() - v_one).mean() < 2 * se.mean() + 0.005


def test_texture_links_lookup_and_irradiance(parallel):
    _, _, tex = parallel
    r = RES
    links = S.TextureLinks(np.array([0], np.int32), np.array([1], np.int32), tex.texture, tex.point_ff,
                           tex.inside, tex.ff_unoccluded, tex.ff, tex.predicted_error, tex.penumbra)
    u, v = S.texel_uv(r)
    uv = np.stack([u.ravel(), v.ravel()], 1)
    assert np.allclose(links.visibility_at(np.zeros(len(uv), int), uv), tex.texture[0].ravel(), atol=1e-6)
    b = np.array([[0.0, 0.0], [2.0, 1.0]])
    h = links.irradiance(b)
    assert h.shape == (1, r, r, 2)
    assert np.allclose(h[0].mean(axis=(0, 1)), links.mean_irradiance(b)[0], rtol=1e-5)


def test_batch_equals_single_links(parallel):
    """Links of different sizes in one call (one mask launch, one FFT stack, a common margin)
    give the textures of separate calls."""
    scene, receiver, _ = parallel
    small = square(0.4, 0.0, down=False) + np.array([0.6, 0.2, 0.0])
    tilted_src = square(S_HALF, D)
    tilted_src[:, 2] += np.array([0.0, 0.1, 0.1, 0.0])
    src = np.stack([square(S_HALF, D), tilted_src])
    rcv = np.stack([receiver, small])
    batch = S.shadow_textures(scene, src, rcv, 32)
    for k in range(2):
        one = S.shadow_texture(scene, src[k], rcv[k], 32)
        assert np.allclose(batch.texture[k], one.texture[0], atol=1e-4)
        assert batch.ff[k] == pytest.approx(one.ff[0], rel=1e-4)


def test_apply_texture_links_on_a_problem():
    """The solver glue: texture links for the partly visible light -> floor links of the table
    scene (triangle receivers), each link's transfer against a ray-sampled form factor."""
    from conftest import SCENES
    from mirad.settings import Settings
    from mirad.solver import Problem

    scene = mirad.load_scene(SCENES / "shadow-cases" / "table.xml")
    prob = Problem(scene, Settings())
    recv, src = prob.initial_pairs()
    prob.links = prob.evaluate(recv, src, prob.geometry())
    links, e = prob.links, prob.elements
    lit = prob.patch_emission[e.patch[links.src]].max(axis=1) > 0
    mask = lit & (links.vis > 0) & (links.vis < 1)
    tl, accepted = S.apply_texture_links(prob, mask, resolution=32, tolerance=0.05)
    assert accepted.sum() == len(tl) > 0
    assert np.all(accepted <= mask)
    rng = np.random.default_rng(5)
    for k in range(len(tl)):
        tri, light = e.verts[tl.recv[k]], e.verts[tl.src[k]]
        a, b = rng.random((2, 2048))
        flip = a + b > 1
        a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
        pts = tri[0] + a[:, None] * (tri[1] - tri[0]) + b[:, None] * (tri[2] - tri[0])
        normals = np.repeat(prob.normals(tl.recv[k:k + 1]), len(pts), 0)
        vis, _ = S.ray_visibility(scene.mi_scene, light, pts, normals, rays=32, seed=k)
        g = S.point_form_factor(pts, normals, np.repeat(light[None], len(pts), 0)) * vis
        se = g.std() / np.sqrt(len(g))
        assert abs(tl.ff[k] - g.mean()) < 3 * se + tl.ff_unoccluded[k] * tl.predicted_error[k]
    # the matrix carries the mean transfers
    m = tl.matrix(len(e))
    assert np.isclose(m.sum(), tl.ff.sum())
