"""Clusters of patches as link sources: the tree, the bound, and agreement with all-pairs linking."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import mirad
from conftest import area_mean, closed_box
from mirad.cluster import build_tree, cluster_boxes, sphere_form_factor_bound
from mirad.formfactor import point_to_polygon


@settings(max_examples=40, deadline=None)
@given(st.integers(min_value=2, max_value=300), st.integers(min_value=0, max_value=2**31))
def test_tree_covers_every_patch_once_and_adds_up_areas(count, seed):
    rng = np.random.default_rng(seed)
    centroid, area = rng.normal(size=(count, 3)), rng.random(count) + 1e-3
    tree = build_tree(centroid, area)
    assert len(tree) == count - 1
    children = tree.children.ravel()
    assert sorted(children[children < count]) == list(range(count))       # each patch once
    child_area = np.where(tree.children < count, area[np.minimum(tree.children, count - 1)],
                          tree.area[np.maximum(tree.children - count, 0)])
    np.testing.assert_allclose(tree.area, child_area.sum(axis=1))          # naive per-node sum
    np.testing.assert_allclose(tree.area[0], area.sum())
    for node in range(len(tree)):                                          # ranges hold the members
        members = set(tree.order[tree.lo[node]:tree.hi[node]])
        for c in tree.children[node]:
            sub = {c} if c < count else set(tree.order[tree.lo[c - count]:tree.hi[c - count]])
            assert sub <= members


@settings(max_examples=60, deadline=None)
@given(st.integers(min_value=0, max_value=2**31))
def test_sphere_bound_contains_the_exact_form_factor_of_a_cluster(seed):
    """The bound holds at every receiver point for the exact form factor of the cluster's patches."""
    rng = np.random.default_rng(seed)
    # a cluster of 6 triangles tiling a square in a random plane (no overlap: the unoccluded
    # sum of their form factors is the square's form factor)
    basis = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    grid = np.array([[i, j] for j in range(3) for i in range(2)], float) * 0.3
    quads = grid[:, None, :] + np.array([[0, 0], [0.3, 0], [0.3, 0.3], [0, 0.3]])[None]
    corners = quads @ basis[:2] * rng.uniform(0.3, 2.0) + rng.normal(size=3) * 2.0
    tris = np.concatenate([corners[:, [0, 1, 2]], corners[:, [0, 2, 3]]])
    tree = build_tree(tris.mean(axis=1), np.ones(len(tris)))
    lo, hi = cluster_boxes(tree, tris)
    centre, radius = 0.5 * (lo[0] + hi[0]), 0.5 * np.linalg.norm(hi[0] - lo[0])
    recv = rng.normal(size=(3, 3)) * 0.3                                    # receiver triangle near 0
    rc = recv.mean(axis=0)
    rr = np.linalg.norm(recv - rc, axis=1).max()
    bound = sphere_form_factor_bound(rc[None], np.array([rr]), centre[None], np.array([radius]))[0]
    normal = np.cross(recv[1] - recv[0], recv[2] - recv[0])
    normal /= np.linalg.norm(normal)
    for w in rng.dirichlet(np.ones(3), size=8):
        x = w @ recv
        exact = sum(point_to_polygon(x, normal, t if np.dot(np.cross(t[1] - t[0], t[2] - t[0]), x - t[0]) > 0
                                     else t[::-1]) for t in tris)
        assert exact <= bound + 1e-9


@pytest.mark.parametrize("tolerance", [0.1, 0.05])
def test_clustered_and_all_pairs_solutions_agree_within_tolerance(cornell, tolerance):
    plain = mirad.solve(cornell, tolerance=tolerance, clustering="off", core="legacy")
    clustered = mirad.solve(cornell, tolerance=tolerance, clustering="on", core="legacy")
    area = cornell.tri_area[:, None]
    reflected = area_mean(np.maximum(plain.triangle_radiosity - cornell.tri_emission, 0), cornell.tri_area).mean()
    diff = (area * np.abs(clustered.triangle_radiosity - plain.triangle_radiosity)).sum() / area.sum() / 3
    assert diff / reflected <= tolerance


@pytest.mark.parametrize("options", [dict(clustering="on", core="legacy"), dict(core="hierarchical")],
                         ids=["legacy", "hierarchical"])
def test_energy_balance_with_clusters(options):
    box = closed_box(0.6, 0.0)
    box["floor"]["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": 1 / np.pi}}
    scene = mirad.load_scene(box)
    sol = mirad.solve(scene, tolerance=0.02, **options)
    absorbed = (sol.triangle_area * (1 - scene.tri_rho[:, 0]) * sol.triangle_irradiance[:, 0]).sum()
    emitted = (sol.triangle_area * scene.tri_emission[:, 0]).sum()
    assert absorbed == pytest.approx(emitted, rel=0.01)


def test_clustering_starts_with_one_link_per_patch():
    from mirad.settings import make_settings
    from mirad.solver import Problem

    scene = mirad.load_scene(closed_box(0.5, 1 / np.pi))
    prob = Problem(scene, make_settings(clustering="on", core="legacy"))
    recv, src = prob.initial_pairs()
    assert len(recv) == len(scene.patch_tri)                 # P links, not P^2
    assert np.all(src == prob.elements.first_cluster)        # all to the root


def test_auto_clustering_switches_on_above_the_threshold(cornell):
    assert mirad.solve(cornell, tolerance=0.1, core="legacy").stats["clusters"] == 0     # 36 patches
    sol = mirad.solve(cornell, tolerance=0.1, cluster_threshold=10, core="legacy")
    assert sol.stats["clusters"] == len(cornell.patch_tri) - 1
