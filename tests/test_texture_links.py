"""Shadow-texture links inside the hierarchical solver (shadows.py through solver.texture_links_wave)."""

import numpy as np

import mirad
from conftest import SCENES
from mirad import shadows as S
from mirad.arrays import to_bool, to_float, to_uint
from mirad.solver import TEXTURED


def test_texture_links_replace_rays_without_changing_the_answer():
    """Under a table with thin legs, links from the light that would split carry a texture
    instead; the per-triangle solution agrees with the ray-traced one within 1 % (L1)."""
    scene = mirad.load_scene(SCENES / "shadow-cases" / "table.xml")
    rays = mirad.solve(scene, tolerance=0.01, quiet=True)
    tex = mirad.solve(scene, tolerance=0.01, shadow_textures=True, quiet=True)
    assert tex.stats["texture_links"] > 0 and rays.stats["texture_links"] == 0
    a = scene.tri_area
    diff = np.abs(tex.triangle_radiosity - rays.triangle_radiosity).sum(1) @ a
    assert diff / (rays.triangle_radiosity.sum(1) @ a) < 0.01
    assert tex.stats["elements"] <= rays.stats["elements"]


def test_textured_links_keep_their_transfer_through_the_fresh_re_estimate():
    """The final fresh-sample pass traces no rays for textured links and restores the texture's
    transfer: F = F_unoccluded * mean visibility, strictly between 0 and F_unoccluded."""
    from mirad.settings import make_settings
    from mirad.solver import Problem, restore_textures, texture_links_wave

    scene = mirad.load_scene(SCENES / "shadow-cases" / "table.xml")
    prob = Problem(scene, make_settings(shadow_textures=True, quiet=True))
    recv, src = prob.initial_pairs()
    prob.links = prob.evaluate(recv, src, prob.geometry())
    fresh = np.arange(len(prob.links))
    error = np.full(len(fresh), np.inf)
    b = np.ones((len(prob.elements), prob.channels)) * 1e-3
    b[prob.patch_emission.max(1) > 0] = 10.0
    texture_links_wave(prob, fresh, error, 1e30, b)
    textured = prob.links.vclass == TEXTURED
    assert textured.any()
    before = prob.links.ff[textured].copy()
    rays_before = prob.rays
    again = prob.evaluate(prob.links.recv, prob.links.src, prob.geometry(), stream=1, vclass=prob.links.vclass)
    prob.links = again
    restore_textures(prob)
    np.testing.assert_array_equal(prob.links.ff[textured], before)
    assert np.all((prob.links.vis[textured] > 0) & (prob.links.vis[textured] < 1))
    assert prob.rays > rays_before          # the other links were traced again


def _points_on_leaf(sol, leaf: int, count: int, seed: int = 0):
    """Uniform points (count, 3) on a leaf, their (u, v) parameters and the leaf's normal."""
    rng = np.random.default_rng(seed)
    uv = rng.random((count, 2))
    flip = uv.sum(1) > 1
    uv[flip] = 1 - uv[flip]
    v = sol.leaf_vertices[leaf]
    p = v[0] + uv[:, :1] * (v[1] - v[0]) + uv[:, 1:] * (v[2] - v[0])
    n = np.cross(v[1] - v[0], v[2] - v[0])
    return p, uv, n / np.linalg.norm(n)


def test_shadow_detail_shows_the_shadow_inside_coarse_leaves():
    """A solution's textured leaves carry their shadow: radiosity_at (leaf value + texture
    detail) follows a ray-traced gather at points inside the leaf (L1 at least 3x below the
    flat leaf value's), and the detail averages to zero over the leaf (no energy moved)."""
    scene = mirad.load_scene(SCENES / "shadow-cases" / "table.xml")
    sol = mirad.solve(scene, tolerance=0.01, shadow_textures=True, quiet=True)
    rows = sol.detail_leaves
    assert len(rows) > 0 and sol.stats["detail_leaves"] == len(rows)
    rho = 0.5                                                     # the floor's reflectance
    for leaf in rows[:3]:
        p, uv, n = _points_on_leaf(sol, int(leaf), 300)
        ref = rho * sol.irradiance_at(p, np.repeat(n[None], len(p), 0), rays=64)[:, 0]
        flat = sol.leaf_radiosity[leaf, 0]
        shown = sol.radiosity_at(np.full(len(p), leaf), uv)[:, 0]
        err_flat, err_shown = np.abs(flat - ref).mean(), np.abs(shown - ref).mean()
        assert err_shown < err_flat / 3, (leaf, err_shown, err_flat)
        # zero mean over the texel centres inside the leaf (the quadrature of the link's transfer)
        u, v = S.texel_uv(sol.leaf_detail.shape[1])
        inside = (u + v <= 1.0).ravel()
        texels = np.stack([u.ravel(), v.ravel()], 1)[inside]
        detail = sol.detail_at(np.full(len(texels), leaf), texels)[:, 0]
        assert abs(detail.mean()) < 1e-5 * np.abs(detail).max()


def test_shadow_detail_is_shown_by_render_and_kept_by_save(tmp_path):
    """The display's Dr.Jit lookup of the detail equals the numpy one; .npz keeps it."""
    import drjit as dr
    import mitsuba as mi

    from mirad.shading import Shading

    scene = mirad.load_scene(SCENES / "shadow-cases" / "table.xml")
    sol = mirad.solve(scene, tolerance=0.01, shadow_textures=True, quiet=True)
    leaf = int(sol.detail_leaves[0])
    p, uv, n = _points_on_leaf(sol, leaf, 200, seed=1)
    shading = Shading(sol)
    shape = int(sol.leaf_shape[leaf])
    found_leaf, found_uv, found = shading.locate(
        mi.Point3f(*(to_float(p[:, i]) for i in range(3))), mi.Vector3f(*(to_float(np.full(len(p), n[i])) for i in range(3))),
        dr.zeros(mi.Bool, len(p)), to_uint(np.full(len(p), shape)), to_bool(np.ones(len(p), bool)))
    assert np.all(found_leaf.numpy() == leaf)
    detail, textured = shading.detail_radiance(found_leaf, found_uv, found)
    assert np.all(textured.numpy())
    np.testing.assert_allclose(detail[0].numpy() * np.pi, sol.detail_at(np.full(len(p), leaf), uv)[:, 0],
                               atol=1e-4 * sol.leaf_radiosity.max())
    path = sol.save(tmp_path / "table.npz")
    again = mirad.load_solution(path, scene)
    np.testing.assert_array_equal(again.detail_leaves, sol.detail_leaves)
    np.testing.assert_array_equal(again.radiosity_at(np.full(len(p), leaf), uv), sol.radiosity_at(np.full(len(p), leaf), uv))


def test_lightmap_shows_the_texture_shadow_and_keeps_the_mean():
    """The floor's lightmap of a textured solution has the table's umbra at its centre and
    the same mean as the floor's radiosity (the detail moves no energy)."""
    from mirad.export import bake_lightmaps

    scene = mirad.load_scene(SCENES / "shadow-cases" / "table.xml")
    sol = mirad.solve(scene, tolerance=0.01, shadow_textures=True, quiet=True)
    floor = bake_lightmaps(sol, resolution=64)["floor"][..., 0]
    mean = sol.shape_radiosity("floor")[0]
    assert abs(floor.mean() - mean) < 0.01 * mean
    centre = floor[28:36, 28:36].mean()                # under the table top (umbra)
    assert centre < 0.2 * mean


def test_vertex_radiosity_carries_the_detail_at_textured_corners():
    """PLY vertex colours: at floor corners inside textured leaves the vertex radiosity holds the
    texture's fall-off, closer to a ray-traced gather there than the triangles' mean."""
    scene = mirad.load_scene(SCENES / "shadow-cases" / "table.xml")
    sol = mirad.solve(scene, tolerance=0.05, shadow_textures=True, quiet=True)
    n_vert = len(sol.vertices)
    textured = np.flatnonzero(np.abs(sol.vertex_detail).sum(1) > 0)
    assert len(textured)
    faces, area = sol.faces, sol.triangle_area
    mean = np.bincount(faces.ravel(), weights=np.repeat(area * sol.triangle_radiosity[:, 0], 3), minlength=n_vert)
    mean = (mean / np.maximum(np.bincount(faces.ravel(), weights=np.repeat(area, 3), minlength=n_vert), 1e-300))
    pts = sol.vertices[textured] * 0.999                       # just inside the floor
    ref = 0.5 * sol.irradiance_at(pts, np.tile([0.0, 0.0, 1.0], (len(pts), 1)), rays=64)[:, 0]
    shown = sol.vertex_radiosity[textured, 0]
    assert np.all(shown >= 0)
    assert np.all(np.abs(shown - ref) < np.abs(mean[textured] - ref))


def test_plugin_with_shadow_textures_shows_the_shadow():
    """<boolean name="shadow_textures" value="true"/> in the radiosity integrator solves with
    texture links, and its image of the table is closer to Mitsuba's path tracer (image L1)
    than the ray-only solution's at the same tolerance, whose coarse floor smooths the umbra
    away (measured 2026-11-23: 4.5 % against 15.6 %)."""
    import mitsuba as mi

    from mirad.reference import reference_image

    scene = mirad.load_scene(SCENES / "shadow-cases" / "table.xml")
    integrator = mi.load_dict({"type": "radiosity", "tolerance": 0.05, "shadow_textures": True})
    assert "shadow_textures=True" in str(integrator)
    image = np.array(mi.render(scene.mi_scene, integrator=integrator, spp=4))[..., 0]
    sol = integrator.solution(scene.mi_scene)
    assert sol.stats["texture_links"] > 0 and len(sol.detail_leaves) > 0
    plain = mirad.render(scene, mirad.solve(scene, tolerance=0.05, quiet=True), spp=4)[..., 0]
    ref = reference_image(scene, spp=64).image[..., 0]
    l1 = lambda x: np.abs(x - ref).sum() / ref.sum()  # noqa: E731
    assert l1(image) < 0.5 * l1(plain)
