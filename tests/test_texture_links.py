"""Shadow-texture links inside the hierarchical solver (shadows.py through solver._texture_links)."""

import numpy as np

import mirad
from conftest import SCENES
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
    from mirad.solver import Problem, _restore_textures, _texture_links

    scene = mirad.load_scene(SCENES / "shadow-cases" / "table.xml")
    prob = Problem(scene, make_settings(shadow_textures=True, quiet=True))
    recv, src = prob.initial_pairs()
    prob.links = prob.evaluate(recv, src, prob.geometry())
    fresh = np.arange(len(prob.links))
    error = np.full(len(fresh), np.inf)
    b = np.ones((len(prob.elements), prob.channels)) * 1e-3
    b[prob.patch_emission.max(1) > 0] = 10.0
    _texture_links(prob, fresh, error, 1e30, b)
    textured = prob.links.vclass == TEXTURED
    assert textured.any()
    before = prob.links.ff[textured].copy()
    rays_before = prob.rays
    again = prob.evaluate(prob.links.recv, prob.links.src, prob.geometry(), stream=1, vclass=prob.links.vclass)
    prob.links = again
    _restore_textures(prob)
    np.testing.assert_array_equal(prob.links.ff[textured], before)
    assert np.all((prob.links.vis[textured] > 0) & (prob.links.vis[textured] < 1))
    assert prob.rays > rays_before          # the other links were traced again
