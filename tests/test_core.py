"""The hierarchical core (core.py, nodes.py, refine.py, transfer.py) against closed forms
and invariants; Settings.core selects it (the legacy core stays the default until it
meets its targets, see validation/RESULTS.md)."""

import sys

import numpy as np
import pytest

import mirad
from conftest import CLOSED_FORM_REL, F_PARALLEL, F_PERPENDICULAR, SCENES, area_mean, closed_box, load_script, square
from mirad import core
from mirad.settings import make_settings

HIER = dict(core="hierarchical", quiet=True)


@pytest.mark.parametrize("name, exact, tol", [("parallel-squares", F_PARALLEL, 0.01),
                                              ("perpendicular-squares", F_PERPENDICULAR, 0.01)])
def test_form_factor_closed_forms(name, exact, tol):
    scene = mirad.load_scene(SCENES / "closed-form" / f"{name}.xml")
    sol = mirad.solve(scene, tolerance=tol, **HIER)
    mask = sol.triangle_shape == scene.shape_index("receiver")
    h = area_mean(sol.triangle_irradiance[mask], sol.triangle_area[mask])[0]
    assert sol.stats["core"] == "hierarchical"
    assert h == pytest.approx(exact, rel=CLOSED_FORM_REL)


@pytest.mark.parametrize("rho", [0.5, 0.9])
def test_white_furnace_within_tolerance(rho):
    # B = E / (1 - rho) everywhere; an error in a face cluster's mean is amplified by
    # 1 / (1 - rho), which the estimate must see (it once stopped 5 % low at rho = 0.9)
    tol = 0.05
    sol = mirad.solve(closed_box(rho, 1 / np.pi), tolerance=tol, **HIER)
    b = sol.triangle_radiosity
    err = np.abs(b - 1.0 / (1.0 - rho)).mean() / (1.0 / (1.0 - rho))
    assert err <= tol
    assert sol.stats["estimated_error"] <= tol


def test_final_gather_resolves_the_triangles_under_a_cluster_link():
    """The final gather re-evaluates face-cluster links on every input patch and solves
    again: the floor, one planar group of 1,152 triangles lit through a few cluster links,
    is no longer one flat value, and the light a leaf gathers matches B = E + rho H."""
    scene = mirad.load_scene(SCENES / "cornell-box-fine" / "scene.xml")
    settings = make_settings(tolerance=0.3, quiet=True, core="hierarchical")
    state = core.build(scene, settings)
    core.link(state)
    nodes = state.nodes
    empty = core.SourceState(np.zeros(len(nodes)), np.zeros(len(nodes)), np.zeros(len(nodes)))
    core.refine(state, empty, np.finfo(float).max, 10 ** 7)
    solved = core.solve(state, None)
    gathered = core.final_gather(state, solved)
    pushed = solved.system.gather(solved.b_leaf)
    floor = scene.shape_index("floor")
    on_floor = scene.tri_shape[scene.patch_tri[nodes.patch[solved.leaves]]] == floor
    assert on_floor.sum() == 1152
    open_floor = on_floor & (state.buried[solved.leaves] == 0)     # (buried triangles get no light)
    assert np.ptp(pushed[open_floor, 0]) < 1e-6 * pushed[open_floor, 0].max()
    assert np.ptp(gathered.irradiance[on_floor, 0]) > 0.2 * gathered.irradiance[on_floor, 0].mean()
    assert np.all(gathered.irradiance >= 0) and np.all(gathered.noise_power >= 0)


def test_the_links_planes_show_how_a_box_face_lit_at_its_own_level_varies():
    """After one pass over the fine Cornell box the boxes' faces take their light through links
    on their face clusters, and the solved system pushes each link's mean to every leaf below:
    the faces' children read the same radiosity, and nothing says their light varies. Pushed
    as the links' planes (``core.varied_leaf_radiosity``), the leaves follow the final gather's own
    field (correlation over 0.9), and the faces' children's deviation is within a factor of two of
    the gathered solution's, where the solved means' is nil."""
    scene = mirad.load_scene(SCENES / "cornell-box-fine" / "scene.xml")
    state = core.build(scene, make_settings(tolerance=0.3, quiet=True, core="hierarchical"))
    core.link(state)
    nodes = state.nodes
    empty = core.SourceState(np.zeros(len(nodes)), np.zeros(len(nodes)), np.zeros(len(nodes)))
    core.refine(state, empty, np.finfo(float).max, 10 ** 7)
    solved = core.solve(state, None)
    n, leaves = len(nodes), solved.leaves
    varied = solved.system.pull @ core.varied_leaf_radiosity(state, solved, leaves,
                                                             core.ancestor_matrix(nodes, leaves).T.tocsr())
    gathered = core.final_gather(state, solved)
    system = gathered.system
    b_gathered = (system.pull @ (system.emission + system.scatter(gathered.irradiance)))[:n]
    shape = scene.tri_shape[scene.patch_tri[nodes.patch[leaves]]]
    faces = np.flatnonzero((nodes.children[:n, 0] >= 0) & (nodes.kind[:n] == core.FACE))
    face_shape = scene.tri_shape[scene.patch_tri[state.order[nodes.lo[faces]]]]
    for name in ("large-box", "small-box"):
        k = scene.shape_index(name)
        on = leaves[(shape == k) & (state.buried[leaves] == 0)]
        assert np.corrcoef(varied[on, 0], b_gathered[on, 0])[0, 1] > 0.9, name
        mine = faces[face_shape == k]
        deviation = {key: core.children_deviation(nodes, b, nodes.area)[mine].sum()
                     for key, b in (("solved", solved.b_node), ("varied", varied), ("gathered", b_gathered))}
        assert deviation["solved"] < 1e-6 * deviation["gathered"], (name, deviation)
        assert 0.5 * deviation["gathered"] < deviation["varied"] < 2.0 * deviation["gathered"], (name, deviation)


def test_deterministic():
    scene = mirad.load_scene(SCENES / "cornell-box" / "scene.xml")
    a = mirad.solve(scene, tolerance=0.1, seed=3, **HIER)
    b = mirad.solve(scene, tolerance=0.1, seed=3, **HIER)
    np.testing.assert_array_equal(a.triangle_radiosity, b.triangle_radiosity)


def test_waves_taken_a_chunk_at_a_time_solve_bitwise_the_same(monkeypatch):
    """Refinement waves, the gather's pairs and the linear sources' moments are taken
    GATHER_CHUNK rows at a time to bound their memory: every step is row by row, so chunks of a
    few hundred rows give the very same solution as the default's one chunk."""
    scene = mirad.load_scene(SCENES / "cornell-box" / "scene.xml")
    whole = mirad.solve(scene, tolerance=0.1, seed=1, **HIER)
    monkeypatch.setattr(core, "GATHER_CHUNK", 331)
    chunked = mirad.solve(scene, tolerance=0.1, seed=1, **HIER)
    assert chunked.stats["gather_pairs"] > 10 * 331 and chunked.stats["links"] > 331
    np.testing.assert_array_equal(chunked.triangle_radiosity, whole.triangle_radiosity)
    assert chunked.stats["estimated_error"] == whole.stats["estimated_error"]
    assert chunked.stats["rays"] == whole.stats["rays"]


def test_recorded_waves_solve_bitwise_as_traced_ones_and_a_warm_solve_records_none(monkeypatch, capfd):
    """The transfer waves replay recorded kernels (``transfer.FREEZE_WAVES``): the very solution
    of waves traced anew on every call, and a scene solved again records nothing new (recorded
    anew on each call, as when the numpy buffers handed to Dr.Jit came at varying alignments,
    they would cost more than tracing). Recording says nothing on stderr (Dr.Jit's warning
    about functions recorded many times: each scene records its own)."""
    from mirad import transfer
    scene = mirad.load_scene(SCENES / "cornell-box" / "scene.xml")
    monkeypatch.setattr(transfer, "FREEZE_WAVES", False)
    traced = mirad.solve(scene, tolerance=0.1, seed=2, **HIER)
    monkeypatch.setattr(transfer, "FREEZE_WAVES", True)
    recorded = mirad.solve(scene, tolerance=0.1, seed=2, **HIER)
    count = transfer.wave_recordings()
    again = mirad.solve(scene, tolerance=0.1, seed=2, **HIER)
    assert transfer.wave_recordings() == count > 0
    for sol in (recorded, again):
        np.testing.assert_array_equal(sol.triangle_radiosity, traced.triangle_radiosity)
        assert sol.stats["rays"] == traced.stats["rays"]
    assert "frozen function" not in capfd.readouterr().err


def test_the_one_sided_table_reads_each_hits_bsdf():
    """The buried-surface test reads whether a hit's BSDF scatters on its front only from a table
    by shape id (``transfer.one_sided_table``), not by calling the hit's BSDF: both say the same for
    rays from everywhere, in every direction, among one-sided and two-sided shapes (a two-sided
    floor, one-sided boxes and a one-sided light)."""
    import drjit as dr
    import mitsuba as mi
    from mirad import transfer
    mi_scene = mi.load_dict({
        "type": "scene",
        "floor": {"type": "rectangle", "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse"}},
                  "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(2)},
        "box": {"type": "cube", "bsdf": {"type": "diffuse"},
                "to_world": mi.ScalarTransform4f().translate([0, 0.5, 0]).scale(0.4)},
        "lamp": {"type": "rectangle", "emitter": {"type": "area"},
                 "to_world": mi.ScalarTransform4f().translate([0, 1.5, 0]).rotate([1, 0, 0], 90).scale(0.3)}})
    rng = np.random.default_rng(4)
    n = 4096
    p = transfer.to_vector3(rng.uniform(-1.5, 1.5, (n, 3)) * [1, 0.6, 1] + [0, 0.6, 0])
    w = transfer.to_vector3(rng.normal(size=(n, 3)))
    w = dr.normalize(w)
    table = transfer.one_sided_table(mi_scene)
    got = np.asarray(transfer._meets_back(mi_scene, p, w, w, 1e-4, table).numpy(), bool)
    ray = mi.Ray3f(p + w * 1e-4, w)
    si = mi_scene.ray_intersect(ray)
    back = si.is_valid() & (dr.dot(si.sh_frame.n, w) > 0)
    front_only = (si.bsdf(ray).flags() & int(mi.BSDFFlags.BackSide)) == 0
    expected = np.asarray((back & front_only).numpy(), bool)
    hit_back = np.asarray(back.numpy(), bool)
    np.testing.assert_array_equal(got, expected)
    # (the rays meet backs of both kinds: the two-sided floor's underside, which is not a back to
    # bury under, and the one-sided box's inside, which is)
    assert expected.sum() > 50 and (hit_back & ~expected).sum() > 50


def test_a_wave_recorded_for_some_links_replays_exactly_for_others(monkeypatch):
    """One recording of a wave serves any number of links: waves of 1, 2, 9 and 40 links, in
    that order (three rays a point: a kind of call no other test records), give the per-point
    transfers of waves traced anew, bitwise (a wave of one link once recorded its per-link sums
    as a scalar, and replayed over the next wave's links gave each the first one's visibility)."""
    from mirad import transfer
    scene = mirad.load_scene(SCENES / "wall-pierce" / "scene.xml")
    state = core.build(scene, make_settings(tolerance=0.1, **HIER))
    nodes = state.nodes
    buf = transfer.NodeBuffers.upload(nodes)
    rng = np.random.default_rng(5)
    planar = np.flatnonzero(nodes.kind != core.VOLUME)
    for spread in (False, True):
        for m in (1, 2, 9, 40):
            recv, src = rng.choice(planar, m), rng.choice(len(nodes), m)
            waves = []
            for frozen in (False, True):
                monkeypatch.setattr(transfer, "FREEZE_WAVES", frozen)
                waves.append(transfer.evaluate(scene.mi_scene, buf, recv, src, rays_per_point=3, seed=7,
                                               offset=state.offset, spread=spread))
            traced, recorded = waves
            assert recorded.rays == traced.rays
            for name in ("g", "gv", "gv_point", "gv_square"):
                np.testing.assert_array_equal(getattr(recorded, name), getattr(traced, name), err_msg=f"{name} m={m}")


def test_a_scene_solved_again_starts_from_its_kept_tree():
    """The node tree (and its buried shares) depends on the scene and the seed alone: the
    first solve keeps it on the scene and the next ones start from a copy, bitwise as if
    built again; another seed, or a scene changed in place where the tree reads it (the
    floor darker and emitting, the light switched off), gets a tree built again, and a copy
    of the scene keeps nothing."""
    import dataclasses

    path = SCENES / "cornell-box" / "scene.xml"
    scene = mirad.load_scene(path)
    a = mirad.solve(scene, tolerance=0.2, seed=5, **HIER)
    kept_nodes = scene.prepared[core.KEPT_TREE][1]
    b = mirad.solve(scene, tolerance=0.2, seed=5, **HIER)
    np.testing.assert_array_equal(a.triangle_radiosity, b.triangle_radiosity)
    assert scene.prepared[core.KEPT_TREE][1] is kept_nodes      # (the solve grew its own copy)
    other = mirad.solve(scene, tolerance=0.2, seed=6, **HIER)
    np.testing.assert_array_equal(other.triangle_radiosity,
                                  mirad.solve(mirad.load_scene(path), tolerance=0.2, seed=6, **HIER).triangle_radiosity)
    assert scene.prepared[core.KEPT_TREE][1] is not kept_nodes  # (one tree a scene: the last seed's)
    # in place: the tree's reflectance bounds and emitting flags change with the scene
    dark = scene.shape_index("floor")
    lit = scene.tri_emission.max(axis=1) > 0
    fresh = mirad.load_scene(path)
    for s in (scene, fresh):
        s.tri_rho[s.tri_shape == dark] *= 0.25
        s.tri_emission[lit] = 0.0
        s.tri_emission[s.tri_shape == dark] = 1.0
    c = mirad.solve(scene, tolerance=0.2, seed=5, **HIER)
    d = mirad.solve(fresh, tolerance=0.2, seed=5, **HIER)
    np.testing.assert_array_equal(c.triangle_radiosity, d.triangle_radiosity)
    assert not np.array_equal(c.triangle_radiosity, a.triangle_radiosity)
    assert dataclasses.replace(scene).prepared == {}


def _square_grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ((n + 1)^2, 3) and triangles (2 n^2, 3) of the square [-1, 1]^2 at z = 0 as an
    n x n grid of squares, each cut into two triangles."""
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    verts = np.stack([-1 + 2 * i.ravel() / n, -1 + 2 * j.ravel() / n, np.zeros((n + 1) ** 2)], 1)
    a, b = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    v00, v10, v11, v01 = (a * (n + 1) + b).ravel(), ((a + 1) * (n + 1) + b).ravel(), \
        ((a + 1) * (n + 1) + b + 1).ravel(), (a * (n + 1) + b + 1).ravel()
    faces = np.concatenate([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)])
    return verts, faces


def _tessellated_furnace(tmp_path, n: int, rho: float) -> dict:
    """The closed furnace cube with every face an n x n grid of squares (2 n^2 triangles):
    its face clusters are the median-split pieces of the grids, some of them not rectangles."""
    import mitsuba as mi
    import trimesh

    verts, faces = _square_grid(n)
    path = tmp_path / "grid.ply"
    trimesh.Trimesh(verts, faces, process=False).export(path)
    T = mi.ScalarTransform4f
    sides = {"floor": T().translate([0, 0, -1]), "ceiling": T().translate([0, 0, 1]).rotate([1, 0, 0], 180),
             "xp": T().translate([1, 0, 0]).rotate([0, 1, 0], -90), "xm": T().translate([-1, 0, 0]).rotate([0, 1, 0], 90),
             "yp": T().translate([0, 1, 0]).rotate([1, 0, 0], 90), "ym": T().translate([0, -1, 0]).rotate([1, 0, 0], -90)}
    scene = {"type": "scene"}
    for name, to_world in sides.items():
        scene[name] = {"type": "ply", "filename": str(path), "to_world": to_world, "id": name, "face_normals": True,
                       "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": rho}},
                       "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1 / np.pi}}}
    return scene


def test_tessellated_furnace_every_triangle_within_tolerance(tmp_path):
    """B = E / (1 - rho) on every one of 3,072 triangles: face clusters whose rectangles only
    bound them (fill < 1) once overhung their neighbours and put patches near them 14 % high."""
    tol = 0.05
    sol = mirad.solve(_tessellated_furnace(tmp_path, 16, 0.5), tolerance=tol, **HIER)
    b = sol.triangle_radiosity[:, 0]
    assert len(b) == 6 * 2 * 16 * 16
    rel = np.abs(b - 2.0) / 2.0
    assert rel.max() <= tol
    assert abs(b.mean() / 2.0 - 1.0) <= 0.01


def test_split_triangles_keep_their_parents_buried_share():
    """A triangle split from one that a box stands on measures its buried share from its input
    triangle's density of points (a quarter of the triangle, a quarter of the points): over the
    leaves below it, by area, the share is the parent's, within the sampling error of two
    measurements at 1,024 points over the whole triangle (five standard deviations), one and
    two levels down."""
    scene = mirad.load_scene(SCENES / "cornell-box" / "scene.xml")
    state = core.build(scene, make_settings(tolerance=0.1, quiet=True, core="hierarchical"))
    nodes = state.nodes
    parents = np.flatnonzero((nodes.kind == core.TRIANGLE) & (state.buried > 0.05) & (state.buried < 0.95))
    assert len(parents)
    sigma = np.sqrt(state.buried[parents] * (1 - state.buried[parents]) / core.BURIED_POINTS)
    split = parents
    for _ in range(2):
        core.split_leaves(state, split)
        leaves = nodes.leaves
        below = core.ancestor_matrix(nodes, leaves).T @ (nodes.area[leaves] * state.buried[leaves])
        share = below[parents] / nodes.area[parents]
        assert np.all(np.abs(share - state.buried[parents]) <= 5 * np.sqrt(2) * sigma), \
            (share, state.buried[parents], sigma)
        kids = nodes.children[split].ravel()
        split = kids[(state.buried[kids] > 0) & (state.buried[kids] < 1)]


def test_linear_fit_reproduces_a_linear_field_and_measures_curvature():
    """The final gather's fit over a face cluster's points: a linear field comes back exactly
    (no residual), a curved one leaves a residual of the curvature's size."""
    from mirad.nodes import RECEIVER_POINTS

    scene = mirad.load_scene(SCENES / "cornell-box-fine" / "scene.xml")
    state = core.build(scene, make_settings(tolerance=0.1, quiet=True, core="hierarchical"))
    nodes = state.nodes
    faces = np.flatnonzero(nodes.kind == core.FACE)[:50]
    pts = nodes.recv_pts[faces].astype(np.float64)
    rng = np.random.default_rng(1)
    grad = rng.normal(size=(len(faces), 3))
    grad -= np.einsum("mc,mc->m", grad, nodes.normal[faces])[:, None] * nodes.normal[faces]
    linear = 2.0 + np.einsum("mkc,mc->mk", pts, grad)
    x0, a, g, rms = core.linear_fit(nodes, faces, linear)
    assert pts.shape[1] == RECEIVER_POINTS
    assert np.allclose(a + np.einsum("mc,mc->m", g, pts[:, 0] - x0), linear[:, 0], atol=1e-9)
    assert rms.max() < 1e-9
    curved = linear + np.linalg.norm(pts - pts.mean(axis=1, keepdims=True), axis=2) ** 2
    assert (core.linear_fit(nodes, faces, curved)[3] > 1e-4).all()


def test_a_partly_shadowed_link_is_never_fitted():
    """A plane through a receiver's seven points says nothing of a penumbra between them:
    ``smooth_links`` fits a link only where every point saw the whole source. Links on face
    clusters from a far one, their values exactly linear over each receiver: seen whole, each
    is fitted; the same fields with every point seeing part of the source (as a ray to each of
    its points measures it), none is. (Fitted, the fine Cornell box's floor beside the boxes
    read the light's direct share +-10 % in bands a cluster wide at tolerance 0.3, 8.2 % L1
    over the floor against a brute-force quadrature of that light.)"""
    from mirad.refine import centre_distance

    scene = mirad.load_scene(SCENES / "cornell-box-fine" / "scene.xml")
    state = core.build(scene, make_settings(tolerance=0.3, quiet=True, core="hierarchical"))
    nodes = state.nodes
    faces = np.flatnonzero(nodes.kind == core.FACE)
    src = faces[np.argsort(nodes.area[faces])[len(faces) // 2]]
    far = faces[centre_distance(nodes, faces, np.full(len(faces), src)) > 2.0 * (nodes.radius[faces] + nodes.radius[src])]
    recv = far[~core.unfittable(nodes, far, np.full(len(far), src))][:50]
    assert len(recv) == 50
    pts = nodes.recv_pts[recv].astype(np.float64)
    rng = np.random.default_rng(2)
    grad = rng.normal(size=(len(recv), 3)) * 0.1
    g = (1.0 + np.einsum("mkc,mc->mk", pts - pts.mean(axis=1, keepdims=True), grad)).astype(np.float32)
    assert (g > 0).all()
    src_ids, b_src, h = np.full(len(recv), src), np.ones(len(recv)), np.ones(len(recv))
    for seen_share, fitted in ((1.0, True), (0.6, False)):
        smooth, _, _, _, rms = core.smooth_links(nodes, recv, src_ids, g, g * np.float32(seen_share), b_src, h, 0.3)
        assert rms.max() < 1e-5
        assert (smooth == fitted).all()


def test_weighted_fit_keeps_the_quadrature_mean():
    """The fits the final gather reads at the patches' centroids (``smooth_links``) are weighted
    by the receiver points' quadrature weights and centred on their weighted mean: a curved
    field's fit then has the quadrature's mean there, where the plain fit's intercept is off by
    the curvature, light lost or made at every fitted link. (A triangle's 7 Dunavant points
    weigh unequally; a face cluster's area-stratified points equally.)"""
    scene = mirad.load_scene(SCENES / "cornell-box-fine" / "scene.xml")
    state = core.build(scene, make_settings(tolerance=0.1, quiet=True, core="hierarchical"))
    nodes = state.nodes
    faces = np.flatnonzero(nodes.kind == core.TRIANGLE)[:50]
    pts = nodes.recv_pts[faces].astype(np.float64)
    w = nodes.recv_w[faces].astype(np.float64)
    w = w / w.sum(axis=1, keepdims=True)
    curved = 1.0 + np.linalg.norm(pts - pts.mean(axis=1, keepdims=True), axis=2) ** 2 / nodes.radius[faces, None] ** 2
    quadrature = (w * curved).sum(axis=1)
    x0, a, _, _ = core.linear_fit(nodes, faces, curved, weighted=True)
    np.testing.assert_allclose(a, quadrature, rtol=1e-9)
    np.testing.assert_allclose(x0, np.einsum("mk,mkc->mc", w, pts), atol=1e-9)
    plain = core.linear_fit(nodes, faces, curved)[1]
    assert np.abs(plain / quadrature - 1).max() > 1e-3


def test_curved_field_reproduces_a_quadratic_field_and_keeps_the_plane_sum():
    """``curved_field`` through a quadratic field over face clusters' 7 points gives the field
    back at the points (6 terms through 7 points, no residual), and its area sum over any points
    is the plane's there (the shift that keeps the transfer the points measured), with no
    correction to the plane beyond the plane's largest miss at the points."""
    scene = mirad.load_scene(SCENES / "cornell-box-fine" / "scene.xml")
    state = core.build(scene, make_settings(tolerance=0.1, quiet=True, core="hierarchical"))
    nodes = state.nodes
    faces = np.flatnonzero(nodes.kind == core.FACE)[:50]
    pts = nodes.recv_pts[faces].astype(np.float64)
    centre = pts.mean(axis=1, keepdims=True)
    field = 1.0 + np.linalg.norm(pts - centre, axis=2) ** 2 / nodes.radius[faces, None] ** 2 + \
        0.3 * (pts - centre)[..., 0] / nodes.radius[faces, None]
    owner = np.repeat(np.arange(len(faces)), pts.shape[1])
    w = nodes.recv_w[faces].astype(np.float64).ravel()
    x0, a, g, _ = core.linear_fit(nodes, faces, field, weighted=True)
    plane = a[owner] + np.einsum("pc,pc->p", g[owner], pts.reshape(-1, 3) - x0[owner])
    at_points = plane.reshape(field.shape)
    curved = core.curved_field(nodes, faces, field, at_points, owner, pts.reshape(-1, 3), w, plane)
    np.testing.assert_allclose(curved, field.ravel(), rtol=1e-6)
    assert np.abs(plane - field.ravel()).max() > 1e-2
    # at other points (the centroids of the points' neighbours), the plane's area sum is kept
    at = (pts + np.roll(pts, 1, axis=1)).reshape(-1, 3) / 2
    plane_at = a[owner] + np.einsum("pc,pc->p", g[owner], at - x0[owner])
    curved_at = core.curved_field(nodes, faces, field, at_points, owner, at, w, plane_at)
    np.testing.assert_allclose(np.bincount(owner, weights=w * curved_at), np.bincount(owner, weights=w * plane_at),
                               rtol=1e-9)
    miss = np.abs(field - at_points).max(axis=1)[owner]
    assert (np.abs(curved_at - plane_at) <= 2 * miss + 1e-12).all()


def _floor_under_a_square_light(tmp_path, n: int, height: float, half: float) -> tuple[dict, np.ndarray]:
    """A 2 x 2 m floor as an n x n grid (rho 0.5) under a black square light (radiance 1, half
    size ``half``, facing down at ``height``), and the floor triangles' exact mean irradiance:
    the polygon form factor (no clipping: the light is above the whole floor) over 4 x 7 points
    a triangle."""
    import mitsuba as mi
    import trimesh
    from mirad.nodes import DUNAVANT7_BARY, DUNAVANT7_WEIGHT

    verts, faces = _square_grid(n)
    trimesh.Trimesh(verts, faces, process=False).export(tmp_path / "floor.ply")
    T = mi.ScalarTransform4f
    centre = np.array([0.3, 0.2, height])
    scene = {"type": "scene",
             "floor": {"type": "ply", "filename": str(tmp_path / "floor.ply"), "id": "floor", "face_normals": True,
                       "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}}},
             "light": square(T().translate(centre.tolist()).rotate([1, 0, 0], 180).scale(half), rho=0.0,
                             radiance=1.0, sid="light")}
    corners = centre + half * np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]])
    tv = verts[faces]                                                       # (T, 3, 3)
    mid = (tv + np.roll(tv, -1, axis=1)) / 2                                # edge midpoints 01, 12, 20
    quarters = np.stack([np.stack([tv[:, 0], mid[:, 0], mid[:, 2]], 1), np.stack([mid[:, 0], tv[:, 1], mid[:, 1]], 1),
                         np.stack([mid[:, 2], mid[:, 1], tv[:, 2]], 1), np.stack([mid[:, 1], mid[:, 2], mid[:, 0]], 1)], 1)
    x = np.einsum("kv,tqvc->tqkc", DUNAVANT7_BARY, quarters)                # (T, 4, 7, 3)
    r = corners[:, None, None, None, :] - x[None]                           # (4 corners, T, 4, 7, 3)
    c = np.cross(r, np.roll(r, -1, axis=0))
    cn = np.linalg.norm(c, axis=-1)
    ff = (np.arctan2(cn, (r * np.roll(r, -1, axis=0)).sum(-1)) * c[..., 2] / cn).sum(axis=0) / (2 * np.pi)
    exact = np.pi * np.abs(np.einsum("k,tqk->t", DUNAVANT7_WEIGHT, ff)) / 4
    return scene, exact


def test_curved_fits_follow_the_fall_off_under_a_light(tmp_path, monkeypatch):
    """A finely meshed floor under a square light: at tolerance 0.2 its face clusters take the
    light in a few links, which the final gather fits over their points. Read from the fit at
    each triangle, the plane through the points missed the fall-off's curvature (2.7 % per
    triangle against the exact irradiance, above the 2.5 % the solve estimated); the quadratic
    (``core.CURVED_FITS``, 1.2 %) must halve that and stay within the estimate. Where every
    point saw the whole light, each triangle takes the exact form factor at its own points
    instead (``core.EXACT_FIT_LEAVES``, the default): exact to float precision."""
    scene, exact = _floor_under_a_square_light(tmp_path, 32, 0.6, 0.25)
    loaded = mirad.load_scene(scene)
    result = {}
    for exact_leaves, curved in ((False, False), (False, True), (True, True)):
        monkeypatch.setattr(core, "EXACT_FIT_LEAVES", exact_leaves)
        monkeypatch.setattr(core, "CURVED_FITS", curved)
        sol = mirad.solve(loaded, tolerance=0.2, **HIER)
        h = sol.triangle_radiosity[:len(exact), 0] / 0.5
        result[exact_leaves, curved] = (float(np.abs(h - exact).sum() / exact.sum()), sol.stats["estimated_error"])
    assert result[False, True][0] <= result[False, False][0] / 2, result
    assert result[False, True][0] <= result[False, True][1], result
    assert result[True, True][0] <= 1e-4, result


def test_a_refined_white_furnace_keeps_its_light():
    """rho = 0.9 and tolerance 0.03 refine the box's faces into ~1,600 leaves under face
    clusters whose links the gather fits: B = E / (1 - rho) within 0.5 % on average and 1 % on
    every triangle (unweighted fits read 1.1 % dark on every triangle: row sums 0.1 % short,
    times 1 / (1 - rho))."""
    rho = 0.9
    sol = mirad.solve(closed_box(rho, 1 / np.pi), tolerance=0.03, **HIER)
    rel = sol.triangle_radiosity[:, 0] * (1.0 - rho) - 1.0
    assert sol.stats["leaves"] > 1000
    assert abs(np.average(rel, weights=sol.triangle_area)) <= 0.005
    assert np.abs(rel).max() <= 0.01


def _box_on_floor(floor_with_hole: bool) -> dict:
    """A cube standing on a 2 m floor under a square light; the cube covers the floor's
    (+x, +y) quadrant. The floor either runs on under the cube (two triangles, each a
    quarter under it) or leaves that quadrant out (three rectangles)."""
    import mitsuba as mi

    T = mi.ScalarTransform4f
    scene = {"type": "scene",
             "light": square(T().translate([0, 0, 1.5]).scale(0.4).rotate([1, 0, 0], 180), rho=0.0, radiance=10.0,
                             sid="light"),
             "box": {"type": "cube", "id": "box", "to_world": T().translate([0.5, 0.5, -0.5]).scale(0.5),
                     "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.7}}}}
    if floor_with_hole:
        for k, (x, y) in enumerate([(-0.5, -0.5), (0.5, -0.5), (-0.5, 0.5)]):
            scene[f"floor{k}"] = square(T().translate([x, y, -1]).scale(0.5), rho=0.7, sid=f"floor{k}")
    else:
        scene["floor"] = square(T().translate([0, 0, -1]), rho=0.7, sid="floor")
    return scene


def test_a_floor_running_under_a_box_sends_the_light_of_its_visible_part():
    """The part of a floor under a box is seen from nowhere: the box's sides must get the
    same light whether the floor runs on under the box or has a hole there."""
    from mirad.reference import triangle_reference

    tol = 0.05
    full = mirad.load_scene(_box_on_floor(False))
    hole = mirad.load_scene(_box_on_floor(True))
    state = core.build(full, make_settings(tolerance=tol, **HIER))
    floor = np.flatnonzero(state.nodes.kind[: len(full.tri_area)] == core.TRIANGLE)
    floor = floor[full.tri_shape[full.patch_tri[floor]] == full.shape_index("floor")]
    # the share of each floor triangle under the box, from 16 stratified points, against
    # dense sampling of the triangle
    u = np.random.default_rng(0).random((100_000, 2))
    u[u.sum(1) > 1] = 1 - u[u.sum(1) > 1]
    for t in floor:
        v = full.tri_vertices[full.patch_tri[t]]
        p = v[0] + u[:, :1] * (v[1] - v[0]) + u[:, 1:] * (v[2] - v[0])
        under = np.mean((p[:, 0] > 0) & (p[:, 1] > 0))
        assert abs(state.buried[t] - under) <= 0.1, (state.buried[t], under)
    # the box's triangles on its sides that face the floor, in either scene against the path
    # tracer (without the buried share they read 17-29 % low: the floor's light was spread
    # over the part under the box too), each the mean of four seeds: one solve's sampling
    # noise on one of these small triangles is 1-6 % at this tolerance (the estimate bounds
    # the error over the whole area), and each link samples its source afresh. (Compared with
    # each other they differ by up to 5.5 %: the floor's gradient next to the box overshoots
    # by up to 3.9 % where the floor is cut in squares, the full floor's reads 2 % low)
    for scene in (full, hole):
        box = np.flatnonzero(scene.tri_shape == scene.shape_index("box"))
        n = scene.tri_normal[box]
        side = box[(n[:, 0] < -0.5) | (n[:, 1] < -0.5)]
        got = np.mean([mirad.solve(scene, tolerance=tol, seed=s, **HIER).triangle_radiosity[side, 0]
                       for s in range(4)], 0)
        ref = triangle_reference(scene, samples_per_triangle=1 << 16, seed=3, triangles=side)
        assert np.all(np.abs(got / ref.radiosity[:, 0] - 1) < tol), got / ref.radiosity[:, 0]


def test_an_emitter_running_under_a_box_sends_only_from_its_visible_part():
    """A floor emitting E = 1 W/m^2 runs on under a black cube standing on it: its buried
    part sends nothing (pulled by area with it, the floor's nodes over the cube's edges read
    up to 1.6 E and the cube's sides were up to 8 % high). Each side triangle's irradiance against the exact form factor
    (Lambert's point-to-polygon formula, clipped, integrated over the triangle by a dense
    rule)."""
    import mitsuba as mi
    from mirad.formfactor import point_to_polygon

    T = mi.ScalarTransform4f
    scene = mirad.load_scene({
        "type": "scene",
        "floor": square(T().translate([0, 0, -1]), rho=0.0, radiance=1 / np.pi, sid="floor"),
        "box": {"type": "cube", "id": "box", "to_world": T().translate([0.1, 0.2, -0.7]).scale(0.3),
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}}}})
    sol = mirad.solve(scene, tolerance=0.05, **HIER)
    box = np.flatnonzero(scene.tri_shape == scene.shape_index("box"))
    sides = box[np.abs(scene.tri_normal[box, 2]) < 0.5]
    assert len(sides) == 8
    floor = [[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1]]
    g = np.polynomial.legendre.leggauss(24)
    s_, t_ = np.meshgrid((g[0] + 1) / 2, (g[0] + 1) / 2, indexing="ij")
    w = np.outer(g[1], g[1]) * s_                               # (the square mapped onto the triangle)
    for t in sides:
        v = scene.tri_vertices[t]
        nrm = scene.tri_normal[t]
        p = v[0] + s_[..., None] * (v[1] - v[0]) + (s_ * t_)[..., None] * (v[2] - v[1])
        ff = np.array([point_to_polygon(q + 1e-9 * nrm, nrm, floor) for q in p.reshape(-1, 3)]).reshape(s_.shape)
        exact = float((w * ff).sum() / w.sum())
        assert sol.triangle_irradiance[t, 0] == pytest.approx(exact, rel=CLOSED_FORM_REL), t


@pytest.mark.parametrize("gap", [0.3, 0.005])
def test_a_ceiling_above_a_hung_lamp_is_not_taken_as_enclosed(gap):
    """A one-sided lamp facing down shows the ceiling above it its back. The ceiling's ray
    along its normal meets that back, which alone made the part above the lamp "buried"
    (inside closed geometry: no light, seen from nowhere), and a ceiling over a lamp hung 0.3
    below it read 11 % dark. Hung there, the rays spread around the ceiling's points find the
    room and none of it is buried; flush under it (5 mm) the part above the lamp is enclosed:
    its buried share is the lamp's footprint. Either way the ceiling's radiosity is Mitsuba's
    path tracer's within the tolerance."""
    import mitsuba as mi
    from mirad.reference import triangle_reference

    T = mi.ScalarTransform4f
    tol = 0.05
    box = closed_box(rho=0.5, radiance=0.0)
    box["lamp"] = square(T().translate([0, 0, 1 - gap]).scale(0.5).rotate([1, 0, 0], 180), rho=0.0, radiance=10.0,
                         sid="lamp")
    scene = mirad.load_scene(box)
    ceiling = np.flatnonzero(scene.tri_shape == scene.shape_index("ceiling"))
    state = core.build(scene, make_settings(tolerance=tol, **HIER))
    nodes = np.flatnonzero(np.isin(scene.patch_tri[state.nodes.patch], ceiling) & (state.nodes.kind == core.TRIANGLE))
    # (the lamp covers a quarter of the ceiling, half of it over each of its two triangles)
    footprint = 0.0 if gap > 0.1 else 0.25
    assert np.abs(state.buried[nodes] - footprint).max() <= 0.05, state.buried[nodes]
    ref = triangle_reference(scene, samples_per_triangle=1 << 16, seed=1, triangles=ceiling)
    sol = mirad.solve(scene, tolerance=tol, **HIER)
    area = scene.tri_area[ceiling]
    mean, ref_mean = (float((area * b[:, 0]).sum() / area.sum()) for b in (sol.triangle_radiosity[ceiling], ref.radiosity))
    noise = 3 * float(np.sqrt((area ** 2 * ref.stderr[:, 0] ** 2).sum()) / area.sum())
    assert abs(mean - ref_mean) <= tol * ref_mean + noise, (mean, ref_mean, noise)


def test_a_row_of_small_lamps_over_a_wall_lights_it_as_the_closed_form_says():
    """Twenty 1 cm lamps facing down, 3 cm in front of a black 2 m wall and 2 mm below its top
    edge: the power the wall absorbs against the lamps' exact form factors to it. The light
    peaks on a strip a few cm wide that the wall's triangles' points do not see: the gather
    once took it 49 % short (clusters of lamps read at the points of the wall's two
    triangles, and the lamps' own transfers at points far from the strip), with the estimate
    at 12 %; it now splits those leaves and opens those clusters."""
    import mitsuba as mi
    from mirad.formfactor import point_to_polygon

    T = mi.ScalarTransform4f
    tol = 0.05
    xs = (np.arange(20) + 0.5) / 20 * 2 - 1
    scene = {"type": "scene", "wall": square(T().rotate([1, 0, 0], -90), rho=0.0, sid="wall")}
    for i, x in enumerate(xs):
        scene[f"lamp-{i}"] = square(T().translate([float(x), 0.03, 0.998]).scale(0.005).rotate([1, 0, 0], 180),
                                    rho=0.0, radiance=1.0, sid=f"lamp-{i}")
    scene = mirad.load_scene(scene)
    wall = np.flatnonzero(scene.tri_shape == scene.shape_index("wall"))
    # each lamp sends pi L A = pi 1e-4 W; its form factor to the wall from 4 x 4 points on it
    corners = [[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]]
    sub = (np.arange(4) + 0.5) / 4 * 0.01 - 0.005
    exact = np.pi * 1e-4 * sum(point_to_polygon([x + dx, 0.03 + dy, 0.998], [0, 0, -1], corners) / 16
                               for x in xs for dx in sub for dy in sub)
    sol = mirad.solve(scene, tolerance=tol, **HIER)
    absorbed = float((sol.triangle_area[wall] * sol.triangle_irradiance[wall, 0]).sum())
    assert absorbed == pytest.approx(exact, rel=tol), (absorbed, exact)
    assert sol.stats["estimated_error"] >= abs(absorbed / exact - 1) / 2


def test_a_shadow_across_a_large_black_triangle_is_resolved_by_the_gather():
    """A black floor of two triangles under a square light, a blocker's shadow across one
    of them: nothing reflects, so no refinement pass sees the floor, and its seven points
    per triangle missed the shadow's edge (6.5 % off while the estimate said 2.1 %). The
    final gather splits the shadowed triangle where its points' visibilities spread.
    Each triangle's irradiance against a Monte Carlo integral of the direct light with an
    exact ray-rectangle blocker test (0.2 % standard error)."""
    import mitsuba as mi

    T = mi.ScalarTransform4f
    tol = 0.05
    scene = mirad.load_scene({
        "type": "scene",
        "floor": square(T(), rho=0.0, sid="floor"),
        "light": square(T().translate([0, 0, 1.5]).scale(0.25).rotate([1, 0, 0], 180), rho=0.0, radiance=10.0,
                        sid="light"),
        "blocker": square(T().translate([0.35, 0.25, 0.6]).scale(0.3), rho=0.0, sid="blocker")})
    floor = np.flatnonzero(scene.tri_shape == scene.shape_index("floor"))
    rng = np.random.default_rng(1)
    m = 400_000
    exact = []
    for t in floor:
        v = scene.tri_vertices[t]
        u = rng.random((m, 2))
        u[u.sum(1) > 1] = 1 - u[u.sum(1) > 1]
        x = v[0] + u[:, :1] * (v[1] - v[0]) + u[:, 1:] * (v[2] - v[0])
        y = np.column_stack([rng.uniform(-0.25, 0.25, m), rng.uniform(-0.25, 0.25, m), np.full(m, 1.5)])
        d = y - x
        r2 = (d * d).sum(1)
        p = x + ((0.6 - x[:, 2]) / d[:, 2])[:, None] * d
        blocked = (np.abs(p[:, 0] - 0.35) < 0.3) & (np.abs(p[:, 1] - 0.25) < 0.3)
        exact.append(10.0 * 0.25 * np.mean(d[:, 2] ** 2 / r2 ** 2 * ~blocked))
    exact = np.array(exact)
    sol = mirad.solve(scene, tolerance=tol, **HIER)
    h = sol.triangle_irradiance[floor, 0]
    assert np.all(np.abs(h / exact - 1) <= tol), h / exact - 1
    measured = float(np.abs(h - exact) @ scene.tri_area[floor] / (exact @ scene.tri_area[floor]))
    assert sol.stats["estimated_error"] >= 0.5 * measured
    assert sol.stats["within_tolerance"]
    # asked for far more than one pass can give: it says so, in a warning and in the stats
    with pytest.warns(UserWarning, match="above the tolerance"):
        short = mirad.solve(scene, tolerance=1e-4, max_refine_passes=1, **HIER)
    assert not short.stats["within_tolerance"] and short.stats["estimated_error"] > 1e-4


def test_volume_cluster_links_carry_the_light_of_their_nearby_triangles():
    """Chair legs standing on the furnished room's floor get much of their light through
    links to volume clusters nearby. The clusters' Monte Carlo transfer once used a point
    kernel bounded near the receiver (A cos cos / (pi r^2 + A / S)): it took too little of
    the nearby triangles' light, and the legs read 7.2 % low over all 256 of their triangles
    at tolerance 0.1, a one-sided bias that no seed averages out. Each sample is now the
    exact form factor of its triangle over the probability of drawing it (unbiased).
    Against a path-traced reference of those triangles (0.09 % standard error), the legs'
    signed error must stay well inside the tolerance."""
    from mirad.reference import triangle_reference

    tol = 0.1
    scene = mirad.load_scene(SCENES / "furnished-room" / "scene.xml")
    floor = scene.tri_shape == scene.shape_index("floor")
    up = scene.tri_normal[floor].mean(0)
    up /= np.linalg.norm(up)
    chairs = np.isin(scene.tri_shape, [scene.shape_index(f"chair-{i}") for i in range(1, 9)])
    legs = np.flatnonzero(chairs & (scene.tri_vertices.min(1) @ up < 0.01) & (np.abs(scene.tri_normal @ up) < 0.5))
    assert len(legs) == 256
    ref = triangle_reference(scene, samples_per_triangle=4096, seed=3, triangles=legs)
    sol = mirad.solve(scene, tolerance=tol, **HIER)
    a = scene.tri_area[legs][:, None]
    signed = float((a * (sol.triangle_radiosity[legs] - ref.radiosity)).sum() / (a * ref.radiosity).sum())
    assert abs(signed) <= tol / 4, signed


def test_volume_samples_split_their_waves_transfer_by_triangle():
    """``transfer.evaluate(samples=True)``: each link's arriving volume-cluster samples,
    weighted by their receiver point's weight over the rays per point, sum to the link's
    transfer, each on a triangle inside the link's volume cluster; asking for them changes
    neither the transfers nor the rays."""
    from mirad.transfer import NodeBuffers, evaluate

    scene = mirad.load_scene(SCENES / "furnished-room" / "scene.xml")
    state = core.build(scene, make_settings(tolerance=0.1, quiet=True, core="hierarchical"))
    nodes = state.nodes
    rng = np.random.default_rng(2)
    recv = rng.choice(np.flatnonzero(nodes.kind == core.TRIANGLE), 300)
    src = rng.choice(np.flatnonzero(nodes.kind == core.VOLUME), 300)
    buf = NodeBuffers.upload(nodes)
    for rays in (1, 4):
        pt = evaluate(scene.mi_scene, buf, recv, src, rays_per_point=rays, seed=7, offset=state.offset)
        with_samples = evaluate(scene.mi_scene, buf, recv, src, rays_per_point=rays, seed=7, offset=state.offset,
                                samples=True)
        link, point, tri, value, _ = with_samples.samples
        transfer = (nodes.recv_w[recv] * pt.gv).sum(axis=1)
        split = np.bincount(link, weights=nodes.recv_w[recv[link], point] * value / rays, minlength=len(recv))
        assert (transfer > 0).sum() > 100
        np.testing.assert_allclose(split, transfer, rtol=1e-5, atol=1e-9)
        assert with_samples.rays == pt.rays and pt.samples is None
        np.testing.assert_array_equal(with_samples.gv, pt.gv)
        assert (nodes.kind[tri] == core.TRIANGLE).all()
        ancestor = tri.copy()
        for _ in range(core.tree_depth(nodes)):
            ancestor = np.where(ancestor == src[link], ancestor, np.maximum(nodes.parent[ancestor], 0))
        assert (ancestor == src[link]).all()


def _room_shelves_signed(monkeypatch, flag: str, tol: float) -> dict:
    """{False: (2,), True: (2,)}: the furnished room's two shelves' signed relative error (their
    summed radiosity over a 1,024-path reference's, minus one) solved at ``tol`` (seed 0) with
    ``core.<flag>`` off and on."""
    from mirad.reference import triangle_reference

    scene = mirad.load_scene(SCENES / "furnished-room" / "scene.xml")
    shelves = [np.flatnonzero(scene.tri_shape == scene.shape_index(f"shelf-{i}")) for i in (1, 2)]
    tris = np.concatenate(shelves)
    ref = triangle_reference(scene, samples_per_triangle=1024, seed=3, triangles=tris).radiosity
    signed = {}
    for on in (False, True):
        monkeypatch.setattr(core, flag, on)
        sol = mirad.solve(scene, tolerance=tol, seed=0, **HIER)
        out = []
        for shelf in shelves:
            a, r = scene.tri_area[shelf][:, None], ref[np.searchsorted(tris, shelf)]
            out.append(float((a * (sol.triangle_radiosity[shelf] - r)).sum() / (a * r).sum()))
        signed[on] = np.array(out)
    return signed


def test_volume_cluster_transfers_bring_their_triangles_own_radiosity(monkeypatch):
    """core.OWN_RADIOSITY (on by default; here off against on): a gathered transfer from a
    volume cluster brings each sampled triangle's radiosity, not the cluster's mean. At a
    tolerance that stops the furnished room early, its shelves take their light from clusters
    that hold the ceiling lamp: with the mean they read +115 % and +69 % (the lamp's share of
    the cluster brought as if it were spread over all of it), with their own triangles +2 % and
    -11 %. Against a path-traced reference of the shelves, each within a third of the tolerance."""
    tol = 0.9
    signed = _room_shelves_signed(monkeypatch, "OWN_RADIOSITY", tol)
    assert np.abs(signed[True]).max() <= tol / 3, signed
    assert np.abs(signed[False]).max() > tol / 3, signed


def test_near_receivers_judge_a_source_by_the_range_of_its_leaves(monkeypatch):
    """core.NEAR_SOURCE_RANGE (on by default; here off against on): a receiver inside its
    source's bounding sphere judges the source's unevenness by the range of its leaves'
    radiosities (``core.seen_variation``), not by its children's means alone. The furnished
    room's shelves stand 2 cm from a wall with their compartments open towards it: their
    faces see the wall's dark strip behind them, which no child of the wall shows. At tolerance
    0.3 the shelves read +9.5 % and +7.6 % with the children's means, +5.2 % and +2.8 % with the
    range (seed 0; +7.0-7.8 % and +1.1-2.4 % at seeds 1-2), against a path-traced reference:
    the mean excess over both must fall by a third at least."""
    tol = 0.3
    excess = _room_shelves_signed(monkeypatch, "NEAR_SOURCE_RANGE", tol)
    assert np.mean(excess[True]) < 2 / 3 * np.mean(excess[False]), excess
    assert np.abs(excess[True]).max() <= tol / 3, excess


def test_fits_read_a_near_sources_range_from_the_links_planes(monkeypatch):
    """core.NEAR_RANGE_VARIED (on; here off against on): a fit's leaves judge a near source by
    the range of its leaves' radiosities with the links' planes pushed down, not the solved
    means, flat below a link on an inner node. The fine Cornell box's back wall takes the lamp's
    light on large clusters; its top row is half as bright as its middle, and the ceiling's row
    along it sees mostly that row. At tolerance 0.15 (seed 0) that ceiling row reads +16.3 % with
    the solved means, +8.4 % with the planes, against a path-traced reference (2^14 paths a
    triangle): its excess must fall by a third at least."""
    from mirad.reference import triangle_reference

    scene = mirad.load_scene(SCENES / "cornell-box-fine" / "scene.xml")
    centroid = scene.tri_vertices.mean(axis=1)
    row = np.flatnonzero((scene.tri_shape == scene.shape_index("ceiling")) & (centroid[:, 2] < -1 + 1 / 12))
    assert len(row) == 48
    ref = triangle_reference(scene, samples_per_triangle=1 << 14, seed=5, triangles=row).radiosity
    a = scene.tri_area[row, None]
    excess = {}
    for on in (False, True):
        monkeypatch.setattr(core, "NEAR_RANGE_VARIED", on)
        b = mirad.solve(scene, tolerance=0.15, seed=0, **HIER).triangle_radiosity[row]
        excess[on] = float((a * (b - ref)).sum() / (a * ref).sum())
    assert excess[False] > 0.05 and excess[True] < 2 / 3 * excess[False], excess


@pytest.mark.parametrize("tol", [
    # (the estimate reads 2.6 times the measured error here since linear_sources stopped taking
    # back what its gradients move out of the open box: the error fell from 1.05 % to 0.64 % of
    # the reflected light, the estimate stayed at 1.65 %, most of it the pairs' visibility noise,
    # taken as that of independent rays while the spread rays are a stratified set)
    # (2026-11-29: the error 0.28 % of the reflected light, the estimate 0.86 %, 3.1 times, most of
    # it the bounds of the links kept on leaves and the sources' means; the gathered noise counted
    # per triangle, ``core.triangle_noise``, where it read 5.7 times summed leaf by leaf)
    pytest.param(0.05, marks=pytest.mark.xfail(strict=True, reason="estimate 3.1x the measured error")),
    # (2.3-3.3 times here until the gathered noise was counted per triangle: 0.43 % for 0.27 %)
    0.03])
def test_the_estimate_is_within_twice_the_measured_error_on_the_cornell_box(tol):
    """Issue 16's error control: the output estimate (irradiance errors over the mean
    irradiance) within a factor 2 of the measured area-weighted L1 of the reflected
    radiosity B - E (which is rho H) per triangle, against a path-traced reference of the
    36-triangle box (262,144 paths per triangle, noise 0.07 %). Measured 1.25 and 1.1; the
    links the final gather replaces carry its pairs' source terms, not their own (it was 1.4)."""
    from mirad.reference import triangle_reference

    scene = mirad.load_scene(SCENES / "cornell-box" / "scene.xml")
    ref = triangle_reference(scene, samples_per_triangle=262_144, seed=12345).radiosity
    sol = mirad.solve(scene, tolerance=tol, **HIER)
    a = scene.tri_area[:, None]
    reflected = np.maximum(ref - scene.tri_emission, 0.0)
    measured = float((a * np.abs(sol.triangle_radiosity - ref)).sum() / (a * reflected).sum())
    assert 0.5 <= sol.stats["estimated_error"] / measured <= 2.0, (sol.stats["estimated_error"], measured)
    assert measured <= tol


def test_linear_sources_bring_the_corners_closer(tmp_path, monkeypatch):
    """core.LINEAR_SOURCES (on by default; here off against on): a near source's radiosity
    gradient sent with the pair's first moment. On the corner room at tolerance
    0.03 the triangles next to the 90-degree corners were up to 8-9 % high with it off (the
    walls' mean radiosity over cells that darken towards the corner); on, the worst of them
    against a path-traced reference (65,536 paths per triangle) must come down by a third."""
    sys.path.insert(0, str(SCENES / "hard-cases"))
    sys.path.insert(0, str(SCENES.parent / "tests"))
    import cases
    from test_hard_cases import _near_corner_triangles
    from mirad.reference import triangle_reference

    scene = mirad.load_scene(cases.corner_room(tmp_path))
    tris = _near_corner_triangles(scene)[::3]
    ref = triangle_reference(scene, samples_per_triangle=1 << 16, seed=5, triangles=tris).radiosity[:, 0]
    worst = {}
    for on in (False, True):
        monkeypatch.setattr(core, "LINEAR_SOURCES", on)
        sol = mirad.solve(scene, tolerance=0.03, **HIER)
        worst[on] = np.abs(sol.triangle_radiosity[tris, 0] / ref - 1).max()
    assert worst[True] < 2 / 3 * worst[False], worst


def test_a_ceiling_beside_a_wall_takes_the_walls_dark_top(tmp_path, monkeypatch):
    """core.SPREAD_OF_EVERY_TRANSFER: a source's gradient is fitted to its leaves' light at their
    points from every transfer they take. The corner room's walls darken towards the ceiling
    (the lamp hangs just under it), and a ceiling triangle with an edge on a wall sees mostly
    that dark top. Where the wall's leaves took the lamp's light through the passes' links, the
    fit saw no spread and those triangles read 2-3 % high against the path tracer (65,536
    paths per triangle), their neighbours away from the wall as much low; the edge triangles'
    mean over four seeds must come within 1 %. (One seed's mean strays by up to 0.7 points from
    the four's: +1.17 / +0.07 / +0.33 / +0.45 % at seeds 0-3, +0.51 % over the four, +1.51 %
    without the spread, since partly hidden sources count their deviation at first order,
    ``core.mean_error_order``, which brought the whole ceiling from -0.56 to -0.01 % at seed 0
    and the edge triangles with it.)"""
    sys.path.insert(0, str(SCENES / "hard-cases"))
    import cases
    from mirad.reference import triangle_reference

    scene = mirad.load_scene(cases.corner_room(tmp_path))
    tv = scene.tri_vertices
    ceiling = scene.tri_shape == scene.shape_index("ceiling")
    on_wall = ((np.abs(tv[:, :, :2]) < 1e-6) | (np.abs(tv[:, :, :2] - 2.0) < 1e-6)).sum(axis=1).max(axis=1) >= 2
    tris = np.flatnonzero(ceiling & on_wall)                        # an edge (two corners) on a wall
    assert len(tris) == 14
    ref = triangle_reference(scene, samples_per_triangle=1 << 16, seed=5, triangles=tris).radiosity[:, 0]
    mean = {}
    for on in (False, True):
        monkeypatch.setattr(core, "SPREAD_OF_EVERY_TRANSFER", on)
        mean[on] = float(np.mean([mirad.solve(scene, tolerance=0.03, seed=seed, **HIER).triangle_radiosity[tris, 0]
                                  / ref - 1 for seed in range(4)]))
    assert mean[False] > 0.01 and abs(mean[True]) < 0.01, mean


def test_a_closed_furnished_room_absorbs_the_power_it_emits(monkeypatch):
    """Energy: the furnished room is closed (its path-traced reference absorbs what it emits
    within 0.07 %), so the power its surfaces absorb, (1 - rho) H A summed, is what its lamp and
    window emit. A transfer all of whose shadow rays met an occluder was taken as wholly hidden,
    with no error, and nothing evaluated it again (``refine.noise_visibility``): a chair seat's
    underside read the floor's form factor as 0 where it is 0.80, and at tolerance 0.15 the room
    absorbed 0.75 % less than it emits (red). Counting the noise of such transfers, 0.36 %
    (0.13 % at 0.1), and with the volume clusters' samples weighed by their kernels
    (``transfer.KERNEL_WEIGHTED_VOLUMES``) 0.09 %. The face clusters' partly hidden pairs taking
    their triangles' own radiosity (``core.FACE_SAMPLES``) then showed the fitted leaves' checks
    taking too much (the room absorbed 0.8 % more than it emits, -0.8 % lost), until those were
    held together to the leaf's share (``core.check_rays``, ``CHECK_AS_BIAS``): 0.00-0.27 %. Within half a
    percent in every channel. With the checks held to the noise's allowance the room absorbs more
    than it emits in every channel: 0.8 % until near receivers judged their sources by the range
    of the leaves' light (``core.NEAR_SOURCE_RANGE``, which sends the fits' nearest leaves to
    their own points), 0.27-0.36 % since. The checks starting at the leaf's points in turn
    (``core.CHECKS_FROM_POINTS``) find the shadows over part of a leaf that the centroid's rays
    missed and take most of that excess away by themselves (0.04-0.17 % held as bias, 0.15-0.25 %
    as noise): the contrast undoes both."""
    from mirad import export, refine

    scene = mirad.load_scene(SCENES / "furnished-room" / "scene.xml")
    emitted = (scene.tri_area[:, None] * scene.tri_emission).sum(axis=0)
    lost = {}
    for mended in ("none undone", "blocked taken as certain", "checks held as noise"):
        monkeypatch.setattr(refine, "BLOCKED_NOT_CERTAIN", mended != "blocked taken as certain")
        monkeypatch.setattr(core, "CHECK_AS_BIAS", mended != "checks held as noise")
        monkeypatch.setattr(core, "CHECKS_FROM_POINTS", mended != "checks held as noise")
        sol = mirad.solve(scene, tolerance=0.15, seed=0, **HIER)
        lost[mended] = 1.0 - export.triangle_table(sol)["absorbed"].sum(axis=0) / emitted
    assert np.abs(lost["none undone"]).max() < 0.005, lost
    assert np.all(lost["checks held as noise"] < -0.002), lost
    # (taken as certain, the blocked transfers lose light in every channel: 0.3-0.5 % more)
    assert np.all(lost["blocked taken as certain"] > lost["none undone"] + 0.002), lost


@pytest.mark.parametrize("mirrored", ["receiver", "light", "both"])
def test_mirrored_shapes_receive_and_send_as_unmirrored(mirrored):
    """A negative-determinant transform turns Mitsuba's geometric normal against the side it
    lights (its shading normal); the core's buried-surface rays once took the geometric one,
    read the floor under a mirrored light as inside closed geometry and gave it B = 0."""
    import mitsuba as mi

    T = mi.ScalarTransform4f
    flip = T().scale([-1, 1, 1])
    down = T().translate([0, 0, 1]).rotate([1, 0, 0], 180)

    def floor_radiosity(floor_xf, light_xf):
        scene = mirad.load_scene({"type": "scene", "floor": square(floor_xf, rho=0.5, sid="floor"),
                                  "light": square(down @ light_xf, rho=0.0, radiance=1.0, sid="light")})
        return mirad.solve(scene, tolerance=0.05, **HIER).shape_radiosity("floor")[0]

    plain = floor_radiosity(T(), T())
    assert plain > 0.3
    xf = {"receiver": (flip, T()), "light": (T(), flip), "both": (flip, flip)}[mirrored]
    assert floor_radiosity(*xf) == pytest.approx(plain, rel=0.01)



def test_a_thousand_small_lights_open_only_near_their_receivers(tmp_path):
    """A volume cluster holding emitters opens for the receivers within its bounding
    sphere's diameter and is bounded like any other cluster elsewhere: with every lit
    cluster opened for every receiver, this room linked each wall to each of the 2,000
    lamp triangles (2.56 M links, 18 s at tolerance 0.2)."""
    sys.path.insert(0, str(SCENES / "hard-cases"))
    import cases

    scene = mirad.load_scene(cases.many_lights_room(tmp_path, count=1000))
    emitted = (scene.tri_area * scene.tri_emission[:, 0]).sum()
    sol = mirad.solve(scene, tolerance=0.2, **HIER)
    absorbed = (sol.triangle_area * (1 - scene.tri_rho[:, 0]) * sol.triangle_irradiance[:, 0]).sum()
    assert sol.stats["links"] < 300_000
    # every watt ends on a front side (the black ceiling's irradiance counts in the estimate:
    # with errors weighted by reflectance it did not, and 6 % went missing)
    assert absorbed == pytest.approx(emitted, rel=0.02)


def test_a_light_a_millionth_of_the_room_lights_it(tmp_path):
    """The solve's tolerance is relative to the reflected light, not to the emission: with
    the emission's norm, a light of 1e-6 of the room's area (and 1e6 times its radiance)
    made the warm start look converged with no reflected light at all, the estimate read
    1e297 and refinement ran to 659 k links (16 s) at tolerance 0.03."""
    from mirad.reference import triangle_reference

    sys.path.insert(0, str(SCENES / "hard-cases"))
    import cases

    scene = mirad.load_scene(cases.tiny_light_room(tmp_path))
    sol = mirad.solve(scene, tolerance=0.03, **HIER)
    assert sol.stats["estimated_error"] <= 0.03 and sol.stats["links"] < 10_000
    ref = triangle_reference(scene, samples_per_triangle=1 << 12, seed=8)
    for sid in ("floor", "ceiling", "wall-x0", "wall-y1"):
        mask = scene.tri_shape == scene.shape_index(sid)
        b = area_mean(sol.triangle_radiosity[mask], scene.tri_area[mask])[0]
        r = area_mean(ref.radiosity[mask], scene.tri_area[mask])[0]
        assert b == pytest.approx(r, rel=0.03), sid


def test_solves_compile_their_kernels_without_fast_math(monkeypatch):
    """The scale and translation test below failed on CUDA (up to 0.7 % per triangle) until
    the solve's kernels were compiled without Dr.Jit's fast math, whose approximate division
    and square roots round differently in a scaled or moved copy (``_runtime.exact_arithmetic``):
    every wave of a solve runs with the flag off, and the caller's flag is back afterwards."""
    import drjit as dr

    seen = []
    evaluate = core.evaluate

    def spy(*args, **kwargs):
        seen.append(dr.flag(dr.JitFlag.FastMath))
        return evaluate(*args, **kwargs)

    monkeypatch.setattr(core, "evaluate", spy)
    before = dr.flag(dr.JitFlag.FastMath)
    with dr.scoped_set_flag(dr.JitFlag.FastMath, True):
        mirad.solve(mirad.load_scene(SCENES / "cornell-box" / "scene.xml"), tolerance=0.3, **HIER)
        assert dr.flag(dr.JitFlag.FastMath)
    assert dr.flag(dr.JitFlag.FastMath) == before
    assert seen and not any(seen), seen


@pytest.mark.parametrize("scale, shift", [(1e3, (0.0, 0.0, 0.0)), (1024.0, (0.0, 0.0, 0.0)), (1.0, (5.0, -3.0, 11.0))],
                         ids=["scale-1e3", "scale-1024", "translate"])
def test_scaled_and_moved_scene_solves_the_same(tmp_path, scale, shift):
    """Ties in the median splits (exact in the input, broken differently by the float32
    rounding of moved vertices) once gave other trees and up to 10 % per triangle; the plane
    fits in metres rounded differently under power-of-two scaling. Same elements, radiosity
    within 1e-6 (bitwise under a power of two).

    Under translation the vertices themselves round differently in float32 (by ~1e-6 m
    here): a shadow ray that passes that close to an occluder's edge can be blocked in one
    scene and not in the other. One such ray (of the 1.3 M) turns over here, on a link of
    one ray per point: 1/7 of that link's light, 3.6e-4 of the triangle it lands on and
    ~1e-6 of the others after interreflection. So: the same elements, most triangles within
    a few 1e-6, none beyond what one turned-over ray can move (1e-3), where a change of
    structure moved them by percents."""
    sys.path.insert(0, str(SCENES / "hard-cases"))
    import cases
    from meshgen import rotation

    xform = np.eye(4)
    xform[:3, :3] = scale * rotation((1, 2, 3), 0.0)
    xform[:3, 3] = shift
    base = mirad.solve(mirad.load_scene(cases.sheet_room(tmp_path / "base")), **HIER)
    moved = mirad.solve(mirad.load_scene(cases.sheet_room(tmp_path / "moved", xform=xform)), **HIER)
    assert moved.stats["elements"] == base.stats["elements"]
    if scale == 1024.0:
        assert np.array_equal(moved.triangle_radiosity, base.triangle_radiosity)
    rel = np.abs(moved.triangle_radiosity - base.triangle_radiosity) / base.triangle_radiosity
    if any(shift):
        assert np.median(rel) <= 1e-5 and rel.max() <= 1e-3, (np.median(rel), rel.max())
    else:
        assert rel.max() <= 1e-6


def test_a_narrow_spot_on_a_large_floor_is_found_and_resolved():
    """A 20 degree spot 1 m above a 4 x 4 m floor of two triangles: 16 stratified points per
    triangle all missed its cone (2.5 % of the floor), the estimate saw zero variance and the
    floor read B = 0. The points' worst case (emitters.delta_light_bound over the strata)
    now counts as error: the floor's power is the cone's, I 2 pi (1 - cos 20 deg), and
    the leaves resolve the cone (lit under it, dark outside) for display."""
    import mitsuba as mi

    T = mi.ScalarTransform4f
    intensity, cutoff = 10.0, 20.0
    scene = mirad.load_scene({
        "type": "scene",
        "floor": {"type": "rectangle", "id": "floor", "to_world": T().scale(2.0),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}}},
        "spot": {"type": "spot", "intensity": {"type": "rgb", "value": intensity}, "cutoff_angle": cutoff,
                 "beam_width": cutoff, "to_world": T().look_at(origin=[0, 0, 1], target=[0, 0, 0], up=[0, 1, 0])}})
    tol = 0.03
    sol = mirad.solve(scene, tolerance=tol, **HIER)
    power = float((sol.triangle_area * sol.triangle_irradiance[:, 0]).sum())
    assert power == pytest.approx(intensity * 2 * np.pi * (1 - np.cos(np.radians(cutoff))), rel=tol)
    assert sol.stats["estimated_error"] <= tol
    centre = sol.leaf_vertices.mean(axis=1)
    r = np.linalg.norm(centre[:, :2], axis=1)
    reach = np.linalg.norm(sol.leaf_vertices[:, :, :2] - centre[:, None, :2], axis=2).max(axis=1)
    inside = r + reach < np.tan(np.radians(cutoff)) * 0.9
    outside = r - reach > np.tan(np.radians(cutoff)) * 1.1
    assert inside.any() and outside.any()
    h = sol.leaf_irradiance[:, 0]
    # under the cone H = I cos^3 / h^2 (1 m high), within the leaf's spread; nothing outside
    assert np.all(h[inside] > 0.5 * intensity * np.cos(np.radians(cutoff)) ** 3)
    assert np.all(h[outside] == 0.0)


def test_opening_volume_clusters_inside_a_canopy_does_not_inflate_the_estimate():
    """A leaf inside a canopy is within the bounding sphere of the clusters around it, where
    each child's bounding-sphere form factor is about as large as its parent's: summed per
    link, opening a cluster doubled the estimate (0.53 -> 190 over 11 passes at tolerance
    0.1, 454 k links, 7.8 s). A receiver's form factors sum to at most 1, so its cluster
    links share min(1, sum of their bounds): the estimate falls as clusters open."""
    scene = mirad.load_scene(SCENES / "plant-canopy" / "scene.xml")
    sol = mirad.solve(scene, tolerance=0.1, **HIER)
    history = np.array(sol.stats["estimate_history"])
    rising = np.diff(history) > 0
    assert not (rising[:-2] & rising[1:-1] & rising[2:]).any()      # (it rose 10 passes in a row)
    assert sol.stats["links"] < 50_000 and sol.stats["estimated_error"] <= 0.1


def test_furnace_with_occluders_every_triangle_within_tolerance():
    """A closed furnace with a floating box and a tilted slab inside, every surface emitting
    and reflecting alike: B = E / (1 - rho) everywhere, so at every point the visible form
    factors must sum to 1 whatever hides what (an error in the visibility of a partly hidden
    source shows here as an error in B)."""
    import mitsuba as mi

    T = mi.ScalarTransform4f
    rho, tol = 0.5, 0.05

    def surface(to_world, kind="rectangle", sid=""):
        return {"type": kind, "id": sid, "to_world": to_world,
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": rho}},
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1 / np.pi}}}

    sides = {"floor": T().translate([0, 0, -1]), "ceiling": T().translate([0, 0, 1]).rotate([1, 0, 0], 180),
             "xp": T().translate([1, 0, 0]).rotate([0, 1, 0], -90), "xm": T().translate([-1, 0, 0]).rotate([0, 1, 0], 90),
             "yp": T().translate([0, 1, 0]).rotate([1, 0, 0], 90), "ym": T().translate([0, -1, 0]).rotate([1, 0, 0], -90)}
    scene = {"type": "scene", **{k: surface(v, sid=k) for k, v in sides.items()},
             "box": surface(T().translate([0.4, 0.3, -0.45]).scale([0.3, 0.4, 0.4]), "cube", "box"),
             "slab": surface(T().translate([-0.4, -0.2, 0.3]).rotate([1, 0, 0], 20).scale([0.35, 0.35, 0.02]),
                             "cube", "slab")}
    sol = mirad.solve(scene, tolerance=tol, seed=0, **HIER)
    b = sol.triangle_radiosity[:, 0]
    exact = 1.0 / (1.0 - rho)
    assert np.abs(b / exact - 1).max() <= tol
    assert abs(np.average(b, weights=sol.triangle_area) / exact - 1) <= 0.005
    assert sol.stats["estimated_error"] <= tol


def _plant_canopy_cluster_links(kind: int, rays_per_point: int, picked) -> list:
    """Links from the plant canopy's smaller volume clusters to up to 400 random nodes of
    ``kind`` that picked(gap) keeps (gap (M,): from the receiver's centre to the cluster's
    sphere, in its radii), evaluated at 12 seeds: the Links of each."""
    from mirad.refine import link_values
    from mirad.transfer import NodeBuffers, evaluate

    scene = mirad.load_scene(SCENES / "plant-canopy" / "scene.xml")
    state = core.build(scene, make_settings(tolerance=0.1, **HIER))
    nodes = state.nodes
    vol = np.flatnonzero(nodes.kind == core.VOLUME)
    rng = np.random.default_rng(3)
    recv = rng.choice(np.flatnonzero(nodes.kind == kind), 4000)
    src = rng.choice(vol[nodes.radius[vol] < 0.5 * nodes.radius[vol].max()], 4000)
    chosen = np.flatnonzero(picked(core.distance_to_source(nodes, recv, src) / nodes.radius[src]))[:400]
    recv, src = recv[chosen], src[chosen]
    rays = np.full(len(recv), rays_per_point, np.int16)
    buffers = NodeBuffers.upload(nodes)
    return [link_values(nodes, recv, src, evaluate(scene.mi_scene, buffers, recv, src, rays_per_point=rays_per_point,
                                                   seed=seed, offset=state.offset), rays)
            for seed in range(12)]


def _predicted_over_spread(runs: list, predicted: np.ndarray) -> float:
    """The predicted standard errors (M,) of the links of ``runs`` (one Links per seed) against
    the spread of their transfers over the seeds, pooled over the links that got light."""
    ff = np.array([r.ff for r in runs], np.float64)
    seen = ff.mean(axis=0) > 0
    assert seen.sum() > 50
    return float(np.sqrt(np.mean(predicted[seen] ** 2) / np.mean(ff[:, seen].var(axis=0, ddof=1))))


@pytest.mark.parametrize("rays_per_point,where", [(4, "far"), (16, "far"), (4, "near"), (16, "near")])
def test_volume_cluster_links_know_their_sampling_error(rays_per_point, where):
    """A link from a volume cluster is a Monte Carlo transfer; its standard error
    (refine.volume_transfer_std) must match the spread of the transfer over independent
    seeds. Each link draws its own points on the source, so the seeds' mean converges to one
    value and the spread follows the ray count. The receiver's points aim their rays at the
    link's 16 targets: with 16 rays a point every point uses all of them, and the error
    taken as if its 112 samples were independent read half the spread (ratio 0.53). Near the
    cluster too, within its sphere's diameter but outside the sphere, where since 2026-11-29 the
    passes take this error rather than the spheres' bound (``refine.NEAR_CLUSTER_GAP``): the
    samples, weighted by the kernel, know their error there as well."""
    runs = _plant_canopy_cluster_links(core.TRIANGLE, rays_per_point,
                                       lambda gap: gap > 2.0 if where == "far" else (gap > 0.0) & (gap <= 2.0))
    # (pooled over the links: the predicted standard errors against the seeds' spread; the pooled
    # variance counts the light's spread over the receiver as noise: conservative)
    ratio = _predicted_over_spread(runs, np.mean([r.vis_std for r in runs], axis=0))
    assert 0.8 < ratio < 3.0, ratio


def test_volume_cluster_links_on_face_clusters_count_their_samples_in_the_mean():
    """On a face cluster a link's transfer is the mean of its points; the final gather
    evaluates the link again on every leaf below with rays of its own, so the passes'
    sampling error reaches the output only through the light the cluster reflects: it is the
    error of the mean (``err_ff``, ``face_mean_errors``: the larger of the samples' own error and
    the points' stratified estimate, which alone read a third of the spread inside the
    cluster's sphere), not visibility noise on the output (``vis_std``, counted at full weight).
    Counted as noise, a 1,000-leaf canopy's passes at 0.1 made 219,604 links and 65.9 M rays for
    0.65 % per leaf in 11.6 s; as the mean's error, 130,485 links and 39.5 M rays for 0.72 % in
    7.0 s. Outside the sphere the mean's error reads 1.6-2.0 times the seeds' spread."""
    runs = _plant_canopy_cluster_links(core.FACE, 4, lambda gap: gap > 0.0)
    assert all((r.vis_std == 0).all() for r in runs)
    ratio = _predicted_over_spread(runs, np.mean([r.err_ff for r in runs], axis=0))
    assert 0.8 < ratio < 3.0, ratio


def test_clusters_around_a_leaf_open_down_the_chain_in_one_pass(monkeypatch):
    """A leaf inside nested volume clusters keeps their spheres' bound when one of them opens:
    the child holding it takes it over. Refinement opened such a chain a level a pass (the
    plant canopy at 0.2: 12 passes, the 1,000-leaf canopy 14); each cluster of the chain whose
    bound is over the threshold now opens at once (``refine.holding_chains_opened``). The
    same links are made, so the solution is the one the passes reached, within its estimate."""
    scene = mirad.load_scene(SCENES / "plant-canopy" / "scene.xml")
    chained = mirad.solve(scene, tolerance=0.2, seed=0, **HIER)
    monkeypatch.setattr(core, "OPEN_HOLDING_CHAINS", False)
    by_pass = mirad.solve(scene, tolerance=0.2, seed=0, **HIER)
    assert chained.stats["refine_passes"] <= by_pass.stats["refine_passes"] // 2, \
        (chained.stats["refine_passes"], by_pass.stats["refine_passes"])
    area = scene.tri_area[:, None]
    apart = float((area * np.abs(chained.triangle_radiosity - by_pass.triangle_radiosity)).sum() /
                  (area * by_pass.triangle_radiosity).sum())
    assert apart <= min(chained.stats["estimated_error"], by_pass.stats["estimated_error"]), apart


def test_children_deviation_weighs_the_childrens_visible_areas():
    """A node's children's deviation from its mean (core.children_deviation): the visible-area
    weighted mean of |B_child - B_node| over its children, brightest channel, 0 on leaves."""
    scene = mirad.load_scene(SCENES / "cornell-box" / "scene.xml")
    state = core.build(scene, make_settings(tolerance=0.1, **HIER))
    nodes = state.nodes
    rng = np.random.default_rng(5)
    b = rng.random((len(nodes), 3))
    visible = rng.random(len(nodes)) + 0.1
    dev = core.children_deviation(nodes, b, visible)
    inner = np.flatnonzero(nodes.children[:, 0] >= 0)
    assert np.all(dev[nodes.children[:, 0] < 0] == 0)
    for k in inner[:20]:
        kids = nodes.children[k][nodes.children[k] >= 0]
        expect = np.sum(visible[kids] * np.abs(b[kids] - b[k]).max(axis=1)) / visible[kids].sum()
        assert dev[k] == pytest.approx(expect, rel=1e-12)


def test_a_small_lamp_near_a_large_wall_is_resolved(tmp_path):
    """A 4 cm lamp 10 cm in front of a white 2 m wall of 8 x 8 cells lights a spot about as
    wide as that distance, and the floor sees the wall's light. A link from the lamp to a
    wall cluster took the spot from the cluster's seven points, which can all miss it (the
    floor read 69 % high at tolerance 0.1 while the estimate said 7 %); such links now
    check their receiver-side mean against the transfer summed over the lamp's own points
    (refine.unresolved, refine.reciprocal_error) and refine until the two agree. Against
    Mitsuba's path tracer per triangle."""
    from mirad.reference import triangle_reference

    sys.path.insert(0, str(SCENES / "hard-cases"))
    import cases

    h = 0.02
    parts = {
        "wall": cases.part(cases.grid((0, 0, 0), (0, 2, 0), (0, 0, 2), 8, 8), 0.8),                 # x = 0, facing +x
        "floor": cases.part(cases.grid((0, 0, 0), (2, 0, 0), (0, 2, 0), 4, 4), 0.5),                # z = 0, facing up
        "lamp": cases.part(cases.grid((0.1, 1 - h, 1.8 - h), (0, 0, 2 * h), (0, 2 * h, 0), 1, 1), 0.0, 100.0),
    }
    scene = mirad.load_scene(cases.to_dict(tmp_path, parts))
    ref = triangle_reference(scene, samples_per_triangle=1 << 13, seed=3)
    sol = mirad.solve(scene, tolerance=0.1, **HIER)
    floor = scene.tri_shape == scene.shape_index("floor")
    lit = ~(scene.tri_shape == scene.shape_index("lamp"))
    a = scene.tri_area
    assert np.average(sol.triangle_radiosity[floor, 0], weights=a[floor]) == pytest.approx(
        np.average(ref.radiosity[floor, 0], weights=a[floor]), rel=0.1)
    l1 = (a[lit] * np.abs(sol.triangle_radiosity[lit, 0] - ref.radiosity[lit, 0])).sum() / \
        (a[lit] * ref.radiosity[lit, 0]).sum()
    assert l1 <= 0.1


def test_linear_sources_send_a_bright_wall_top_where_its_light_goes(tmp_path, monkeypatch):
    """A thousand 1 cm lamps under a black ceiling light the walls' tops in a strip a few
    centimetres high, and the floor sees the walls through links the final gather
    interpolates over their face clusters, each with the wall's mean radiosity: the floor
    read 8.7 % high at tolerance 0.2 while the estimate said 2.2 %. With linear sources on
    those links too (the walls' gradients, sent with each transfer's first moment, near or
    far) the floor's error against the path tracer must fall by more than half, and no
    light is made: absorbed stays within 2 % of emitted (corrections that only near
    receivers took made 0.7 % more). The counterfactual takes the walls' means alone: without the
    gradients, and without the fits' source splits judged from the links' planes
    (``SPLIT_UNEVEN_FIT_SOURCES``, ``VARIED_SOURCES``), which mend part of the same bias (7.5 %
    -> 5.3 % without the gradients, 2.6 % with them)."""
    from mirad.reference import triangle_reference

    sys.path.insert(0, str(SCENES / "hard-cases"))
    import cases

    scene = mirad.load_scene(cases.many_lights_room(tmp_path, count=1000))
    floor = np.flatnonzero(scene.tri_shape == scene.shape_index("floor"))
    ref = triangle_reference(scene, samples_per_triangle=1 << 12, seed=12, triangles=floor).radiosity[:, 0]
    a = scene.tri_area[floor]
    emitted = (scene.tri_area * scene.tri_emission[:, 0]).sum()
    off_on = {}
    for on in (False, True):
        for flag in ("LINEAR_SOURCES", "SPLIT_UNEVEN_FIT_SOURCES", "VARIED_SOURCES"):
            monkeypatch.setattr(core, flag, on)
        sol = mirad.solve(scene, tolerance=0.2, **HIER)
        off_on[on] = abs(np.average(sol.triangle_radiosity[floor, 0], weights=a) / np.average(ref, weights=a) - 1)
        absorbed = (sol.triangle_area * (1 - scene.tri_rho[:, 0]) * sol.triangle_irradiance[:, 0]).sum()
        assert absorbed == pytest.approx(emitted, rel=0.02)
    assert off_on[True] < 0.5 * off_on[False], off_on


def test_linear_sources_see_which_part_of_a_source_is_hidden():
    """The Cornell box's lamp hangs 1 cm under the ceiling: the ceiling's coarse leaves that reach
    under it are dark there, and the receivers' rays see only their bright rest. The linear
    sources' first moment over a source's four parts takes each part's own visibility from each
    receiver point (``core._part_moments``); taking the transfer's mean visibility over all parts,
    it sent the ceiling's mean where its exposed part is brighter, and the 36-triangle box's
    reflected light read -0.80 % (two seeds) at tolerance 0.05, now -0.35 %: a bias within a
    tenth of the tolerance, against the path tracer (2^16 paths a triangle)."""
    from mirad.reference import triangle_reference

    tol = 0.05
    scene = mirad.load_scene(SCENES / "cornell-box" / "scene.xml")
    ref = triangle_reference(scene, samples_per_triangle=1 << 16, seed=12345).radiosity
    a = scene.tri_area[:, None]
    reflected = float((a * np.maximum(ref - scene.tri_emission, 0.0)).sum())
    signed = [float((a * (mirad.solve(scene, tolerance=tol, seed=seed, **HIER).triangle_radiosity - ref)).sum())
              / reflected for seed in (0, 1)]
    assert abs(np.mean(signed)) <= 0.1 * tol, signed


@pytest.mark.parametrize("tol", [0.1, 0.05])
def test_the_error_map_integrates_to_the_estimate_in_its_norm(tol):
    """The hierarchical core bounds irradiance errors (refine.ERRORS_OF) and maps them as
    radiosity errors, rho times the irradiance error per triangle and channel
    (``Solution.triangle_error``; the channels share a leaf's error as they share its light):
    over each channel's reflectance that map, integrated over the area and the channels and
    divided by the same integral of the irradiance, is the estimate (the coloured walls of the
    Cornell box put the reflected-radiosity norm 24 % away from it)."""
    scene = mirad.load_scene(SCENES / "cornell-box" / "scene.xml")
    sol = mirad.solve(scene, tolerance=tol, **HIER)
    a = sol.triangle_area[:, None]
    rho = scene.tri_rho
    assert np.all(rho > 0)
    irradiance_error = sol.triangle_error / rho
    integral = float((a * irradiance_error).sum() / (a * sol.triangle_irradiance).sum())
    assert np.all(sol.triangle_error >= 0) and integral > 0
    assert integral == pytest.approx(sol.stats["estimated_error"], rel=0.05)


def test_options_only_the_legacy_core_reads_are_refused_or_said_on_the_hierarchical_core():
    """The hierarchical core reads neither shaft culling nor the clustering switches, the link
    error scale or the element cap: asked for with core='hierarchical' they were silently
    ignored (culling 'on' traced the same 120,313 rays as without it). Now refused, naming the
    option and the fix; left at their defaults they pass. Shadow textures and the bf oracle
    run the solve on the legacy core, and now say so."""
    from mirad.errors import SettingsError

    for option in (dict(shaft_culling="on"), dict(clustering="off"), dict(cluster_threshold=10),
                   dict(link_error_scale=2.0), dict(max_elements=1000)):
        with pytest.raises(SettingsError, match=rf"{next(iter(option))}=.*only the legacy core.*core='legacy'"):
            make_settings(core="hierarchical", **option)
        make_settings(core="legacy", **option)
    make_settings(core="hierarchical", shaft_culling="auto", clustering="auto")
    # a solve that runs on the legacy core anyway (the bound oracle, shadow textures) takes them:
    # with the hierarchical core the default, oracle='bound' with an element cap was refused
    make_settings(oracle="bound", max_elements=5000)
    make_settings(shadow_textures=True, clustering="on")
    scene = mirad.load_scene(SCENES / "cornell-box" / "scene.xml")
    with pytest.warns(UserWarning, match="oracle='bf' runs on the legacy core only"):
        sol = mirad.solve(scene, tolerance=0.3, oracle="bf", **HIER)
    assert sol.stats["core"] == "legacy"


def test_the_gathers_splits_keep_the_direct_lights_error(monkeypatch):
    """Leaves the final gather splits for a shadow take more sun and sky points until the direct
    light's summed error is back where the passes left it (``core.resample_split_direct``): at
    the parent's density (a quarter each) the summed per-leaf error doubles at every split, after
    the last pass that could resample it. A 1,000-leaf canopy at tolerance 0.02 then ended at
    2.17 % (the passes' 1.79 %, the direct light's share 0.66 % -> 2.09 %), above the tolerance
    whatever tolerance was asked; here the share was 2.7x the passes'."""
    import tempfile
    from pathlib import Path

    make = load_script(SCENES / "canopy-scale" / "make.py", "canopy_make")
    seen = {}
    original = core.output_estimate

    def spy(state, est, gathered):
        out = original(state, est, gathered)
        seen.update(passes=float(est.direct.sum()), output=float(out.direct.sum()),
                    split=len(out.direct) - len(est.direct))
        return out

    monkeypatch.setattr(core, "output_estimate", spy)
    with tempfile.TemporaryDirectory() as folder:
        path = make.make_canopy(Path(folder), plants=4, leaves_per_plant=60, seed=1)
        sol = mirad.solve(path, tolerance=0.03, seed=0, **HIER)
    assert seen["split"] > 100, seen                            # the gather split leaves
    assert seen["output"] <= 1.25 * seen["passes"], seen
    assert sol.stats["estimated_error"] <= 0.03


def test_a_gather_that_ends_above_a_met_tolerance_says_so(monkeypatch):
    """When the passes met the tolerance and only the final gather's estimate is above it, the
    warning says that, not 'raise max_refine_passes' (which was no limit there)."""
    from dataclasses import replace

    original = core.output_estimate

    def above(state, est, gathered):
        out = original(state, est, gathered)
        return replace(out, relative=2.0 * state.settings.tolerance)

    monkeypatch.setattr(core, "output_estimate", above)
    with pytest.warns(UserWarning, match=r"refinement met the tolerance 0\.1 after \d+ passes .* final gather is 0\.2000") as caught:
        mirad.solve(closed_box(0.5, 1 / np.pi), tolerance=0.1, **HIER)
    assert not any("max_refine_passes" in str(w.message) for w in caught)


def test_the_gathers_allowances_count_the_sun_and_sky_light(tmp_path):
    """The final gather's noise and fit allowances are shares of a receiver's whole irradiance
    (``core.direct_node_irradiance`` adds the point/spot/sun/sky light to its links'): on a
    sunlit canopy the links alone are a fraction of it, and an allowance over them held every
    leaf's gather to that fraction (the 1,000-leaf translucent canopy traced 16.0 M rays at
    tolerance 0.1, now 11.9 M, at the same error). A node's value is the area mean of the
    leaves below it."""

    make = load_script(SCENES / "canopy-scale" / "make.py", "canopy_make")
    path = make.make_canopy(tmp_path, plants=2, leaves_per_plant=20, seed=1)
    state = core.build(mirad.load_scene(str(path)), make_settings(tolerance=0.1, **HIER))
    nodes = state.nodes
    leaves = nodes.leaves
    core.direct(state, leaves, 64)
    below = core.ancestor_matrix(nodes, leaves).T.tocsr()
    h = core.direct_node_irradiance(state, below, leaves)
    own = state.direct[leaves].max(axis=1)
    assert own.max() > 0
    np.testing.assert_allclose(h[leaves], own, rtol=1e-12)
    for node in (state.root, *np.flatnonzero(nodes.kind == core.FACE)[:20]):
        under = below[node].indices
        area = nodes.area[leaves[under]]
        assert h[node] == pytest.approx(float((area * own[under]).sum() / area.sum()), rel=1e-12)


def test_the_tolerance_over_some_shapes_holds_on_them_and_the_estimate_says_so():
    """``error_shapes``: the estimate is relative to the named shapes' light, and counts the
    other shapes' errors by the share of their reflected light that reaches them
    (``core.output_weights``). On the 36-triangle box with the two boxes named, their measured
    error (reflected radiosity per triangle, against 262,144 paths per triangle) is within the
    tolerance and the estimate is not under it (measured 1.6 %, estimated 5.4 % at 0.1).
    Naming every shape is the plain solve, bit for bit; the list form is the string's."""
    from mirad.reference import triangle_reference

    scene = mirad.load_scene(SCENES / "cornell-box" / "scene.xml")
    ref = triangle_reference(scene, samples_per_triangle=262_144, seed=12345).radiosity
    tol = 0.1
    sol = mirad.solve(scene, tolerance=tol, error_shapes="*-box", **HIER)
    assert sol.stats["error_shapes"] == ["large-box", "small-box"]
    assert "% of mean(H) over large-box, small-box (tolerance" in sol.summary()
    boxes = np.isin(np.asarray(scene.shape_ids)[scene.tri_shape], ["large-box", "small-box"])
    a = scene.tri_area[boxes, None]
    reflected = np.maximum(ref - scene.tri_emission, 0.0)[boxes]
    measured = float((a * np.abs(sol.triangle_radiosity[boxes] - ref[boxes])).sum() / (a * reflected).sum())
    assert measured <= tol
    assert sol.stats["estimated_error"] >= measured, (sol.stats["estimated_error"], measured)
    assert sol.stats["estimated_error"] <= tol
    listed = mirad.solve(scene, tolerance=tol, error_shapes=["large-box", "small-box"], **HIER)
    assert listed.stats["estimated_error"] == sol.stats["estimated_error"]
    every = mirad.solve(scene, tolerance=tol, error_shapes="*", **HIER)
    plain = mirad.solve(scene, tolerance=tol, **HIER)
    assert every.stats["error_shapes"] is None
    np.testing.assert_array_equal(every.triangle_radiosity, plain.triangle_radiosity)
    assert every.stats["estimated_error"] == plain.stats["estimated_error"]


def test_the_gather_evaluates_no_pair_only_to_split_its_source(monkeypatch):
    """A face-cluster source whose rectangle overhangs its triangles near the receiver is split
    by the final gather whatever its rays say (``core.overhangs``): such pairs descend to
    sources that fit, or that hold few enough triangles to be summed exactly
    (``core.EXACT_FACE_TRIANGLES``), before any is evaluated (``core.overhang_descent``; the
    furnished room at tolerance 0.05 traced 29.7 M rays, then 24.1 M, at 0.84 -> 0.82 % L1)."""
    first = []
    original = core._evaluate_pairs

    def spy(state, solved, patch, src, rays, found=None):
        if not first:
            first.append((state, patch.copy(), src.copy()))
        return original(state, solved, patch, src, rays, found)

    monkeypatch.setattr(core, "_evaluate_pairs", spy)
    mirad.solve(SCENES / "furnished-room" / "scene.xml", tolerance=0.2, **HIER)
    state, patch, src = first[0]
    nodes = state.nodes
    assert len(patch)
    summed = core.summed_sources(state, src)
    fits = ~(core.overhangs(nodes, patch, src) & (nodes.children[src, 0] >= 0) & ~summed)
    assert fits.all()
    assert (core.overhangs(nodes, patch, src) & summed).any()      # (the room has such sources)
    # and the descent keeps the pairs whose sources fit as they were
    kept, kept_src, _ = core.overhang_descent(nodes, patch, src, np.ones(len(patch), np.int64),
                                              summed=np.diff(core.summed_faces(state).indptr) > 0)
    assert len(kept) == len(patch)


def test_over_a_canopys_leaves_the_estimate_covers_their_error(tmp_path):
    """A small canopy over a ground (40 two-sided leaves): both sides' radiosity on the leaf
    triangles against the path tracer (16,384 paths per triangle side). Over every shape the
    estimate (1.5 %) is a third of the leaves' measured error (4.9 %): the ground's area dilutes
    it. Over the leaves (``error_shapes="plant-*"``) it is above their measured error and within
    2x of it (2.2 % against 1.4 % at tolerance 0.1). The leaves' 1.4 % (3.1 % before the direct
    light's points were balanced against the gather's error, ``core.balance_direct``) holds the
    reference's own noise (0.5 %) and the undersides' +2 % bias, which the estimate now counts
    (``core.own_deviation``)."""

    from mirad.reference import triangle_reference

    make = load_script(SCENES / "canopy-scale" / "make.py", "canopy_make")
    scene = mirad.load_scene(str(make.make_canopy(tmp_path, plants=2, leaves_per_plant=20, seed=1)))
    leafy = np.flatnonzero(np.asarray(scene.shape_ids)[scene.tri_shape] != "ground")
    ref = np.concatenate([triangle_reference(scene, samples_per_triangle=16384, seed=3, triangles=leafy,
                                             side=side).radiosity for side in ("front", "back")])
    area = np.concatenate([scene.tri_area[leafy]] * 2)[:, None]

    def measured(sol):
        b = np.concatenate([sol.triangle_radiosity[leafy], sol.back_radiosity[leafy]])
        return float((area * np.abs(b - ref)).sum() / (area * ref).sum())

    tol = 0.1
    every = mirad.solve(scene, tolerance=tol, seed=0, **HIER)
    assert every.stats["estimated_error"] < 0.5 * measured(every)
    leaves = mirad.solve(scene, tolerance=tol, seed=0, error_shapes="plant-*", **HIER)
    err = measured(leaves)
    assert err <= leaves.stats["estimated_error"] <= 2.0 * err, (leaves.stats["estimated_error"], err)
    assert err <= tol
    assert err < 0.02


def test_a_receiver_whose_points_miss_a_source_in_front_of_part_of_it_takes_the_reciprocal_transfer(tmp_path):
    """A ground under a canopy straddles every tilted leaf's plane; where all of the ground
    cluster's points lie behind a leaf, its part in front still sees it. That missed transfer is
    now taken from the leaf's side (A_s / A_r sum_k w_k F(y_k -> ground), exact point-to-polygon
    form factors): by reciprocity at most A_s / A_r, and an estimate of the unoccluded mean
    (here against a sampled double integral), where the bounding spheres' form factor, in its
    place before, was 1 for every leaf inside the ground's sphere (its links held 50 times the
    tolerance's budget on a 1,000-leaf canopy, each the ground's area times the leaf's radiosity)."""

    from mirad.refine import unseen_in_front

    make = load_script(SCENES / "canopy-scale" / "make.py", "canopy_make")
    scene = mirad.load_scene(make.make_canopy(tmp_path, plants=1, leaves_per_plant=60, seed=2))
    state = core.build(scene, make_settings(tolerance=0.1, **HIER))
    nodes = state.nodes
    ground_patch = np.flatnonzero(scene.tri_shape[scene.patch_tri] == scene.shape_index("ground"))
    ground = ground_patch[0]
    while nodes.parent[ground] >= 0 and nodes.kind[nodes.parent[ground]] == core.FACE:
        ground = nodes.parent[ground]
    leaves = np.flatnonzero((nodes.kind == core.TRIANGLE) & (scene.tri_shape[scene.patch_tri[nodes.patch]]
                                                              != scene.shape_index("ground")))
    links = core.evaluate_links(state, np.full(len(leaves), ground), leaves, np.ones(len(leaves), np.int16))
    unseen = np.flatnonzero(unseen_in_front(nodes, links.recv, links.src, links.ff_unocc))
    assert len(unseen) >= 5
    ratio = nodes.area[links.src[unseen]] / nodes.area[ground]
    assert np.all(links.err_ff[unseen] <= ratio * (1 + 1e-4))
    # the unoccluded mean transfer ground <- leaf, sampled: the estimate is of its size, not a bound
    rng = np.random.default_rng(0)
    g_tri = nodes.poly[ground_patch, :3]
    g_area = nodes.area[ground_patch]
    m = 400_000
    pick = rng.choice(len(ground_patch), m, p=g_area / g_area.sum())
    u, v = np.sqrt(rng.random(m)), rng.random(m)
    x = g_tri[pick, 0] * (1 - u)[:, None] + g_tri[pick, 1] * (u * (1 - v))[:, None] + g_tri[pick, 2] * (u * v)[:, None]
    nx = nodes.normal[ground_patch[pick]]
    checked = 0
    for i in unseen[np.argsort(-links.err_ff[unseen])][:5]:
        s = links.src[i]
        a, b = np.sqrt(rng.random(m)), rng.random(m)
        t = nodes.poly[s, :3]
        y = t[0] * (1 - a)[:, None] + t[1] * (a * (1 - b))[:, None] + t[2] * (a * b)[:, None]
        d = y - x
        r2 = np.einsum("mc,mc->m", d, d)
        cos_x = np.einsum("mc,mc->m", d, nx) / np.sqrt(r2)
        cos_y = -np.einsum("mc,c->m", d, nodes.normal[s]) / np.sqrt(r2)
        sampled = np.mean(np.where((cos_x > 0) & (cos_y > 0), cos_x * cos_y / (np.pi * r2), 0.0)) * nodes.area[s]
        assert 0.5 * sampled <= links.err_ff[i] <= 2.0 * sampled + 1e-9, (links.err_ff[i], sampled)
        checked += 1
    assert checked == 5


def test_a_gathered_pair_that_found_nothing_is_sampled_again_only_where_what_it_may_bring_counts(monkeypatch):
    """A volume-cluster pair all of whose rays were blocked reads 0 with a noise floor, the
    light of the one ray that might have turned over (``refine.volume_transfer_std``). Its
    allowance is shared by that floor (``core.plausible_transfer``), not by its estimate of 0,
    which no number of rays meets: on the furnished room at tolerance 0.1 such pairs took 3.2 M
    of the solve's 7.7 M rays, 79 % of them to find nothing again. A faint one is kept as it
    is; one whose floor is a large share of the receiver's light is sampled again."""
    from types import SimpleNamespace
    calls = []

    def evaluate(state, solved, patch, src, rays, found=None):
        calls.append(patch.copy())
        m = len(patch)
        return np.zeros(m), var[patch], np.zeros(m), 0.0, np.zeros((m, core.RECEIVER_POINTS), np.float32)

    monkeypatch.setattr(core, "_evaluate_pairs", evaluate)
    monkeypatch.setattr(core, "output_share", lambda state, ids: np.ones(len(ids)))
    tol, h, b = 0.1, 1.0, 0.5
    floor = np.array([1e-4, 0.5]) * h              # the floors' light: faint, and half the receiver's
    var = floor ** 2
    node, src = np.array([0, 1]), np.array([0, 0])
    rays = np.ones(2, np.int64)
    state = SimpleNamespace(settings=SimpleNamespace(tolerance=tol))
    core._resample_noisy(state, None, node, src, rays, np.zeros(2), var.copy(), np.zeros(2),
                         np.zeros((2, core.RECEIVER_POINTS), np.float32), np.full(1, b), np.full(2, h))
    assert rays[0] == 1 and not any(0 in c for c in calls)
    assert rays[1] == core.GATHER_MAX_RAYS


def test_a_shadow_that_all_of_a_fitted_receivers_points_missed_stays_dark(tmp_path):
    """A 10 cm black plate 10 cm over a finely meshed floor, under a 20 cm square light 2 m up:
    its umbra is a 9.5 cm square that the light's link on a floor cluster can miss with all of its
    points, each of whose one ray arrived; the plane fitted through them then lit every umbra
    triangle (up to 0.78 of the floor's mean). No light reaches the umbra (the plate is black, the
    scene open): each leaf below such a fit checks it with a ray of its own
    (``core.CHECK_FITTED_SHADOWS``), and the umbra's triangles take the link at their own points."""
    sys.path.insert(0, str(SCENES / "hard-cases"))
    sys.path.insert(0, str(SCENES / "_tools"))
    import cases
    from meshgen import grid

    parts = {"floor": cases.part(grid((0, 0, 0), (2, 0, 0), (0, 2, 0), 60, 60), 0.5),
             "plate": cases.part(grid((0.2, 0.2, 0.1), (0, 0.1, 0), (0.1, 0, 0), 1, 1), 0.0, twosided=True),
             "light": cases.part(grid((0.9, 0.9, 2.0), (0, 0.2, 0), (0.2, 0, 0), 1, 1), 0.0, 10.0)}
    scene = mirad.load_scene(cases.to_dict(tmp_path, parts))
    sol = mirad.solve(scene, tolerance=0.1, **HIER)
    # the umbra: the points every line to the light from which crosses the plate (the plate's edges
    # projected onto the floor from the light's nearer edge, at 0.9 m, and its farther one, at 1.1 m)
    k = 2.0 / (2.0 - 0.1)
    lo, hi = 0.9 + (0.2 - 0.9) * k, 1.1 + (0.3 - 1.1) * k
    floor = sol.triangle_shape == scene.shape_index("floor")
    v = scene.tri_vertices
    umbra = floor & np.all((v[..., :2] >= lo) & (v[..., :2] <= hi), axis=(1, 2))
    assert umbra.sum() >= 8
    h = sol.triangle_irradiance[:, 0]
    assert h[umbra].max() <= 1e-3 * h[floor].mean()


def _visible_light(x: np.ndarray, light: tuple, plate: tuple, z_light: float, z_plate: float) -> np.ndarray:
    """(M,) the form factor from upward floor points x (M, 3) to the part of a square light
    (corners light = (lo, hi) in x and y, at height z_light, facing down) that a square plate
    (plate = (lo, hi) (2,) each, at z_plate, parallel to both) leaves visible: the light's
    polygon less its intersection with the plate's projection from the point onto the light's
    plane (a rectangle), each by Lambert's formula."""
    def polygon(at, q):                 # points (M, 3) and the convex polygons (M, V, 3) they face
        r = q - at[:, None]
        r /= np.linalg.norm(r, axis=2, keepdims=True)
        nxt = np.roll(r, -1, axis=1)
        cross = np.cross(r, nxt)
        angle = np.arccos(np.clip((r * nxt).sum(axis=2), -1.0, 1.0))
        return np.abs((angle * cross[..., 2] / np.maximum(np.linalg.norm(cross, axis=2), 1e-300)).sum(axis=1)) / (2 * np.pi)

    def rectangle(lo, hi):              # (M, 2) corners -> (M, 4, 3) at the light's height
        q = np.full((len(lo), 4, 3), z_light)
        q[:, 0, :2], q[:, 2, :2] = lo, hi
        q[:, 1, 0], q[:, 1, 1], q[:, 3, 0], q[:, 3, 1] = hi[:, 0], lo[:, 1], lo[:, 0], hi[:, 1]
        return q

    m = len(x)
    full = polygon(x, rectangle(np.full((m, 2), light[0]), np.full((m, 2), light[1])))
    scale = z_light / z_plate
    lo = np.maximum(x[:, :2] + (plate[0] - x[:, :2]) * scale, light[0])
    hi = np.minimum(x[:, :2] + (plate[1] - x[:, :2]) * scale, light[1])
    hidden = np.zeros(m)
    cut = np.all(hi > lo, axis=1)
    if cut.any():
        hidden[cut] = polygon(x[cut], rectangle(lo[cut], hi[cut]))
    return full - hidden


def test_check_rays_are_the_fewest_that_bound_a_penumbras_excess():
    """``core.check_rays``: k rays a leaf, the fewest for which the largest expected excess of a
    leaf that all k rays passed, max over p of p^k (1 - p) F B (at p = k / (k + 1)), is within
    GATHER_SHARE tol sqrt(H F B / n), n the transfers that share the leaf's checks, or
    SOURCE_POINTS where that is not enough; at least one. The excesses are biases of one sign:
    summed over n transfers that split a leaf's light H at random, they stay within
    GATHER_SHARE tol H wherever no transfer is at the cap."""
    rng = np.random.default_rng(3)
    m = 2000
    h = 10.0 ** rng.uniform(-3, 3, m)
    fb = h * 10.0 ** rng.uniform(-4, 0, m)
    b = 10.0 ** rng.uniform(-2, 2, m)
    tol = 10.0 ** rng.uniform(-1.5, -0.3, m)
    n = rng.integers(1, 50, m).astype(np.float64)
    k = np.concatenate([core.check_rays(fb[i:i + 1] / b[i], b[i:i + 1], h[i:i + 1], float(tol[i]), n[i:i + 1])
                        for i in range(m)])

    def excess(rays, light):
        p = rays / (rays + 1.0)
        return p ** rays * (1.0 - p) * light

    allowed = core.GATHER_SHARE * tol * np.sqrt(h * fb / n)
    assert k.min() >= 1 and k.max() <= core.SOURCE_POINTS
    assert np.all((excess(k, fb) <= allowed * (1 + 1e-9)) | (k == core.SOURCE_POINTS))
    # (and the fewest: one ray fewer would not do, where there are more than one)
    assert np.all((k == 1) | (excess(k - 1, fb) > allowed))
    assert 1 < np.median(k) < core.SOURCE_POINTS
    assert core.check_rays(np.zeros(1), np.ones(1), np.zeros(1), 0.1)[0] == 1     # (no light, nothing too much)
    # a leaf's light split among n fitted transfers: their summed excess within the budget
    for _ in range(200):
        count = int(rng.integers(1, 40))
        light = rng.dirichlet(np.full(count, 0.3)) * 7.0
        t = float(10.0 ** rng.uniform(-1.2, -0.3))
        rays = core.check_rays(light, np.ones(count), np.full(count, 7.0), t, np.full(count, float(count)))
        capped = rays == core.SOURCE_POINTS
        assert excess(rays, light)[~capped].sum() <= core.GATHER_SHARE * t * 7.0 * (1 + 1e-9)


def test_fitted_leaves_in_a_penumbra_take_no_more_than_their_share(tmp_path):
    """A 50 cm black plate 60 cm over a finely meshed floor, under a 40 cm square light 2 m up: a
    penumbra ring of 838 floor triangles around the umbra. A link fitted over a floor cluster whose
    points all saw the whole light brought its unshadowed field to every leaf below it whose one
    check ray arrived: a leaf that sees a share p of the light passes with probability p and then
    takes 1 / p times its light. The penumbra's power read +13.9 % (its triangles 20 % L1) at
    tolerance 0.1, estimated 1.1 %. Each leaf checks with ``core.check_rays`` rays, so that its
    expected excess stays within its share of the tolerance. Against the exact visible light
    (Lambert's formula over the light less the plate's projection, at 112 points a triangle)."""
    sys.path.insert(0, str(SCENES / "hard-cases"))
    sys.path.insert(0, str(SCENES / "_tools"))
    import cases
    from meshgen import grid
    from mirad.nodes import DUNAVANT7_BARY, DUNAVANT7_WEIGHT

    z_light, z_plate, radiance, tol = 2.0, 0.6, 10.0, 0.1
    light, plate = (0.8, 1.2), (np.array([0.75, 0.75]), np.array([1.25, 1.25]))
    parts = {"floor": cases.part(grid((0, 0, 0), (2, 0, 0), (0, 2, 0), 60, 60), 0.5),
             "plate": cases.part(grid((0.75, 0.75, z_plate), (0, 0.5, 0), (0.5, 0, 0), 1, 1), 0.0, twosided=True),
             "light": cases.part(grid((0.8, 0.8, z_light), (0, 0.4, 0), (0.4, 0, 0), 1, 1), 0.0, radiance)}
    scene = mirad.load_scene(cases.to_dict(tmp_path, parts))
    floor = np.flatnonzero(scene.tri_shape == scene.shape_index("floor"))
    tri = scene.tri_vertices[floor].astype(np.float64)
    # each triangle's mean: 16 midpoint sub-triangles, 7 points each
    for _ in range(2):
        a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
        ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
        tri = np.concatenate([np.stack(q, axis=1) for q in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    points = np.einsum("kj,mjc->mkc", DUNAVANT7_BARY, tri).reshape(-1, 3)
    seen = (_visible_light(points, light, plate, z_light, z_plate).reshape(-1, 7) * DUNAVANT7_WEIGHT).sum(axis=1)
    exact = np.pi * radiance * seen.reshape(16, len(floor)).mean(axis=0)
    centre = scene.tri_vertices[floor].mean(axis=1)
    unshadowed = np.pi * radiance * _visible_light(centre, light, (plate[0] + 9, plate[1] + 9), z_light, z_plate)
    penumbra = (exact > 0.02 * unshadowed) & (exact < 0.98 * unshadowed)
    assert penumbra.sum() > 500
    sol = mirad.solve(scene, tolerance=tol, seed=0, **HIER)
    h = sol.triangle_irradiance[floor, 0]
    area = scene.tri_area[floor][penumbra]
    power = float((area * exact[penumbra]).sum())
    assert abs(float((area * (h[penumbra] - exact[penumbra])).sum())) <= core.GATHER_SHARE * tol * power
    assert float((area * np.abs(h[penumbra] - exact[penumbra])).sum()) <= tol * power


def test_a_volume_clusters_transfer_is_drawn_by_what_its_parts_send(tmp_path):
    """A 10 cm plate 20 cm over a 40 cm floor and a 4 m emitter 20 m up: the root volume
    cluster holds all three. Drawn by area, its triangles would almost never be the plate's
    (0.06 % of the area, most of the transfer): the floor's transfer from it read 73 % low at a
    ray to each of the source's 16 points from each of its 7 points, the plate never drawn. Drawn
    by what each child may send to the point (``transfer.source_point``; the floor's own cluster,
    in the point's plane, sends nothing) it is within 10 % of the exact sum of the triangles'
    point-to-polygon form factors."""
    from mirad.formfactor import point_to_polygon

    sys.path.insert(0, str(SCENES / "hard-cases"))
    sys.path.insert(0, str(SCENES / "_tools"))
    import cases
    from meshgen import grid

    parts = {"floor": cases.part(grid((-0.2, -0.2, 0), (0.4, 0, 0), (0, 0.4, 0), 1, 1), 0.5),
             "plate": cases.part(grid((-0.05, -0.05, 0.2), (0, 0.1, 0), (0.1, 0, 0), 1, 1), 0.5),
             "sky": cases.part(grid((-2, -2, 20), (0, 4, 0), (4, 0, 0), 1, 1), 0.5, 1.0)}
    scene = mirad.load_scene(cases.to_dict(tmp_path, parts))
    state = core.build(scene, make_settings(tolerance=0.1, **HIER))
    nodes = state.nodes
    root = np.flatnonzero((nodes.parent < 0) & (nodes.kind == core.VOLUME))
    assert len(root) == 1
    triangle = np.flatnonzero(nodes.kind == core.TRIANGLE)
    on_floor = scene.tri_shape[scene.patch_tri[nodes.patch[triangle]]] == scene.shape_index("floor")
    floor, others = triangle[on_floor], triangle[~on_floor]
    links = core.evaluate_links(state, floor, np.full(len(floor), root[0]), np.full(len(floor), 16, np.int16))
    for r, sampled in zip(floor, links.ff_unocc):
        exact = sum(nodes.recv_w[r, k] * point_to_polygon(nodes.recv_pts[r, k], nodes.recv_nrm[r, k], nodes.poly[t, :3])
                    for k in range(core.RECEIVER_POINTS) for t in others
                    if nodes.normal[t] @ (nodes.recv_pts[r, k] - nodes.poly[t, 0]) > 0)
        assert sampled == pytest.approx(exact, rel=0.1)


def test_receivers_behind_their_source_get_exactly_nothing_from_it():
    """``core.behind_source`` (the final gather leaves such pairs out, unevaluated) claims only
    pairs whose exact unoccluded transfer is zero at every receiver point: evaluated anyway,
    each of the room's triangles it claims against each planar source reads 0."""
    from mirad.transfer import NodeBuffers, evaluate

    scene = mirad.load_scene(SCENES / "furnished-room" / "scene.xml")
    state = core.build(scene, make_settings(tolerance=0.1, quiet=True, core="hierarchical"))
    nodes = state.nodes
    rng = np.random.default_rng(3)
    recv = rng.choice(np.flatnonzero(nodes.kind == core.TRIANGLE), 4000)
    src = rng.choice(np.flatnonzero(nodes.kind != core.VOLUME), 4000)
    behind = core.behind_source(nodes, recv, src)
    pt = evaluate(scene.mi_scene, NodeBuffers.upload(nodes), recv, src, rays_per_point=1, seed=7, offset=state.offset)
    zero = (pt.g == 0).all(axis=1)
    assert behind.sum() > 500
    assert zero[behind].all()
    # and more than half of the triangles whose corners are all behind or in the plane (the
    # sphere bounds the triangle: it leaves out those in the source's own plane; 60 % here)
    height = np.einsum("mc,mkc->mk", nodes.normal[src], nodes.poly[recv, :3] - nodes.poly[src, 0][:, None])
    corners_behind = height.max(axis=1) <= 0.0
    assert zero[corners_behind].all() and behind.sum() >= 0.5 * corners_behind.sum()
    # volume clusters are never claimed (their samples are drawn on their triangles)
    vol = np.flatnonzero(nodes.kind == core.VOLUME)
    assert not core.behind_source(nodes, recv[:len(vol)], vol[:len(recv)]).any()


def test_a_leaf_system_gathers_through_its_trimmed_matrices_bitwise():
    """``LeafSystem.gather`` runs over push, links and pull trimmed to the nodes that receive or
    send a link (``LeafSystem.trimmed``): the same sums as the full products, bitwise, for a
    pass's system and the final one, and a system whose links change is trimmed again."""
    import scipy.sparse as sp

    captured = []
    original = core.solve_system

    def spy(system, x0, **kw):
        captured.append(system)
        return original(system, x0, **kw)

    core.solve_system = spy
    try:
        mirad.solve(SCENES / "cornell-box" / "scene.xml", tolerance=0.1, **HIER)
    finally:
        core.solve_system = original
    rng = np.random.default_rng(4)
    for system in (captured[1], captured[-1]):
        b = rng.random((system.push.shape[0], 3))
        full = system.push @ (system.links @ (system.pull @ b))
        np.testing.assert_array_equal(system.gather(b), full)
        push, links, pull = system.trimmed()
        assert links.nnz == system.links.nnz and pull.shape[0] < system.pull.shape[0]
    other = captured[1]
    other.links = sp.csr_matrix(other.links.shape)
    assert not other.gather(rng.random((other.push.shape[0], 3))).any()


def test_sources_deviation_is_computed_where_the_links_read_it():
    """``source_state`` measures a node's deviation and brightest leaf below over the pull's rows
    of the links' sources only: there they equal the whole pull's values."""
    captured = {}
    original = core.source_state

    def spy(state, solved):
        out = original(state, solved)
        captured.update(state=state, solved=solved, out=out)
        return out

    core.source_state = spy
    try:
        mirad.solve(SCENES / "cornell-box" / "scene.xml", tolerance=0.1, **HIER)
    finally:
        core.source_state = original
    state, solved, out = captured["state"], captured["solved"], captured["out"]
    pull = solved.system.pull
    rows = np.repeat(np.arange(pull.shape[0]), np.diff(pull.indptr))
    deviation = core.channel_max(np.abs(solved.b_leaf[pull.indices] - solved.b_node[rows]))
    measured = np.bincount(rows, weights=pull.data * deviation, minlength=pull.shape[0])
    senders = np.unique(state.links.src)
    np.testing.assert_array_equal(out.dev[senders], measured[senders])
    below = np.zeros(pull.shape[0])
    np.maximum.at(below, rows, core.channel_max(solved.b_leaf)[pull.indices])
    np.testing.assert_array_equal(out.b_max_below[senders], below[senders])


def test_a_cluster_draws_a_coarse_grounds_triangles_by_what_they_send(tmp_path):
    """A small black plate faces down 1 m over a sunlit ground of 32 large triangles (8 m x
    8 m): it gathers the ground's light from the root volume cluster, which holds the ground
    and the plate. Drawn by area inside the ground's face cluster, the triangle below the
    plate, which sends a sixth of its light, came one time in 32, and the estimate's standard
    deviation over seeds was 22 % at four rays a point (the plate's own cluster, next to its
    points and sending nothing to them, took half the draws above). Drawn by what each part
    may send (``transfer.source_point``) at the face clusters' levels too, the estimate stays
    unbiased (its mean over 64 seeds within four standard errors of the sum of the exact form
    factors of the cluster's triangles) and its deviation is under 15 %."""
    import mitsuba as mi
    import trimesh
    from mirad.transfer import NodeBuffers, evaluate

    verts, faces = _square_grid(4)
    path = tmp_path / "ground.ply"
    trimesh.Trimesh(verts, faces, process=False).export(path)
    T = mi.ScalarTransform4f
    sun = np.radians(30.0)
    scene = mirad.load_scene({
        "type": "scene",
        "ground": {"type": "ply", "filename": str(path), "to_world": T().scale([4, 4, 1]), "id": "ground",
                   "face_normals": True, "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}}},
        "plate": square(T().translate([0.2, -0.1, 1.0]).rotate([1, 0, 0], 180).scale(0.05), rho=0.0, sid="plate"),
        "sun": {"type": "directional", "direction": [np.sin(sun), 0.0, -np.cos(sun)],
                "irradiance": {"type": "rgb", "value": 1.0}}})
    state = core.build(scene, make_settings(tolerance=0.1, quiet=True))
    nodes = state.nodes
    buf = NodeBuffers.upload(nodes)
    plate = scene.shape_index("plate")
    recv = np.flatnonzero((nodes.kind == core.TRIANGLE) & (scene.tri_shape[scene.patch_tri[nodes.patch]] == plate))[:1]
    root = np.flatnonzero((nodes.parent < 0) & (nodes.kind == core.VOLUME))
    assert len(recv) == 1 and len(root) == 1
    w = nodes.recv_w[recv[0]].astype(np.float64)
    below = core.ancestor_matrix(nodes, nodes.leaves).T.tocsr()
    parts = nodes.leaves[below[root[0]].indices]
    whole = evaluate(scene.mi_scene, buf, np.full(len(parts), recv[0]), parts, rays_per_point=1, seed=0,
                     offset=state.offset)
    exact = float((w * whole.g.astype(np.float64)).sum())
    drawn = np.array([float((w * evaluate(scene.mi_scene, buf, recv, root, rays_per_point=4, seed=seed,
                                          offset=state.offset).gv[0].astype(np.float64)).sum())
                      for seed in range(64)])
    assert 0.9 < exact < 1.0
    assert abs(drawn.mean() - exact) <= 4 * drawn.std() / np.sqrt(len(drawn)), (drawn.mean(), exact)
    assert drawn.std() <= 0.15 * exact, drawn.std() / exact


def test_a_pairs_rays_each_aim_at_a_target_of_their_own():
    """The fine Cornell box's floor triangles (9 cm) take the light's triangles, some partly
    hidden by the boxes. With sixteen rays a point every point aiming at the same sixteen
    targets, a small receiver's points see much the same quadrature of the source, and their
    mean is hardly better than one point's. With each ray at a target of its own (``spread``)
    the transfer stays unbiased (its mean over 32 seeds within four standard errors of the
    shared targets' on every partly hidden pair, the two estimating the same transfer) and its
    deviation over the seeds is under 0.7 of the shared targets' on the median such pair."""
    from mirad.transfer import NodeBuffers, evaluate

    scene = mirad.load_scene(SCENES / "cornell-box-fine" / "scene.xml")
    state = core.build(scene, make_settings(tolerance=0.1, quiet=True))
    nodes = state.nodes
    tri_shape = scene.tri_shape[scene.patch_tri[nodes.patch]]
    leaf = nodes.kind == core.TRIANGLE
    floor = np.flatnonzero(leaf & (tri_shape == scene.shape_index("floor")))
    light = np.flatnonzero(leaf & (tri_shape == scene.shape_index("light")))
    recv, src = np.repeat(floor, len(light)), np.tile(light, len(floor))
    buf = NodeBuffers.upload(nodes)
    w = nodes.recv_w[recv].astype(np.float64)

    def transfers(spread: bool) -> np.ndarray:
        return np.array([(w * evaluate(scene.mi_scene, buf, recv, src, rays_per_point=16, seed=seed,
                                       offset=state.offset, spread=spread).gv.astype(np.float64)).sum(axis=1)
                         for seed in range(32)])

    shared, spread = transfers(False), transfers(True)
    unoccluded = (w * evaluate(scene.mi_scene, buf, recv, src, rays_per_point=1, seed=0,
                               offset=state.offset).g.astype(np.float64)).sum(axis=1)
    partly = (shared.mean(axis=0) < 0.95 * unoccluded) & (shared.mean(axis=0) > 0.05 * unoccluded)
    assert partly.sum() >= 20
    error = np.sqrt((shared.var(axis=0, ddof=1) + spread.var(axis=0, ddof=1)) / 32)
    assert np.all(np.abs(spread.mean(axis=0) - shared.mean(axis=0))[partly] <= 4 * error[partly])
    ratio = spread.std(axis=0)[partly] / shared.std(axis=0)[partly]
    assert np.median(ratio) < 0.7, np.quantile(ratio, [0.1, 0.5, 0.9])


def test_a_leaf_under_a_sunlit_leaf_gets_the_light_of_its_shadowed_part(tmp_path, monkeypatch):
    """Two leaves 3 cm apart in the sun (elevation 50 degrees): the upper one's shadow falls on
    the lower one, and the upper leaf's underside faces the lower one's shadowed part most. A
    source that sends its mean radiosity sends that part's light as if it were lit: the
    underside read +12 % against the path tracer (2^20 paths) at tolerance 0.03. The direct
    light's variation over a source leaf (``core.own_deviation``) is now in refinement's source
    term (``core.OWN_SOURCE_DEVIATION``), which splits the lower leaf where its shadow matters:
    within 2 % (measured +0.2 %)."""
    import trimesh

    from mirad.reference import triangle_reference

    corners = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.03, 0.09, 0.0]])
    for name, height in (("lower", 0.0), ("upper", 0.03)):
        trimesh.Trimesh(corners + [0.0, 0.0, height], [[0, 1, 2]], process=False).export(tmp_path / f"{name}.ply")
    shapes = "".join(f'<shape type="ply" id="{name}"><string name="filename" value="{name}.ply"/>'
                     f'<boolean name="face_normals" value="true"/><ref id="leaf"/></shape>' for name in ("lower", "upper"))
    (tmp_path / "scene.xml").write_text(
        '<scene version="3.0.0"><integrator type="path"/>'
        '<bsdf type="leaf" id="leaf"><rgb name="reflectance" value="0.3"/><rgb name="transmittance" value="0"/></bsdf>'
        '<emitter type="directional"><vector name="direction" value="-0.454519478, 0.454519478, -0.766044443"/>'
        f'<rgb name="irradiance" value="600"/></emitter>{shapes}</scene>')
    scene = mirad.load_scene(tmp_path / "scene.xml")
    upper = np.flatnonzero(np.asarray(scene.shape_ids)[scene.tri_shape] == "upper")
    ref = triangle_reference(scene, samples_per_triangle=1 << 20, seed=1, triangles=upper, side="back").radiosity
    sol = mirad.solve(scene, tolerance=0.03, seed=0, error_shapes="upper", **HIER)
    assert abs(sol.back_radiosity[upper, 0] / ref[:, 0] - 1.0).max() < 0.02, (sol.back_radiosity[upper], ref)
    monkeypatch.setattr(core, "OWN_SOURCE_DEVIATION", False)
    before = mirad.solve(scene, tolerance=0.03, seed=0, error_shapes="upper", **HIER)
    assert (before.back_radiosity[upper, 0] / ref[:, 0] - 1.0).min() > 0.08


def test_a_leafs_shadow_checks_start_at_its_points_not_its_centre(tmp_path):
    """``transfer.leaves_blocked`` with ``from_points`` (``core.CHECKS_FROM_POINTS``): the shadow
    checks of a fitted leaf start at its points in turn. A panel hung 2 cm before a wall hides
    the ceiling lamp from the wall's strip behind it; a wall triangle whose centre lies outside
    that strip but some of whose points lie in it passes any number of checks from its centre,
    and took the whole unshadowed light (the fine box at 0.15: 0.968 -> 0.951 % L1 with the
    checks from the points). From its points its rays meet the panel."""
    sys.path.insert(0, str(SCENES / "hard-cases"))
    import cases
    from meshgen import grid
    from mirad import transfer

    parts = cases.room_parts(cells=4)
    parts["panel"] = cases.part(grid((0.02, 0.7, 0.7), (0, 0, 0.6), (0, 0.6, 0), 2, 2), 0.6)
    scene = mirad.load_scene(cases.to_dict(tmp_path, parts))
    state = core.build(scene, make_settings(tolerance=0.1, **HIER))
    nodes = state.nodes
    tri = np.flatnonzero(nodes.kind == core.TRIANGLE)
    shape = scene.tri_shape[state.patch_tri[nodes.patch[tri]]]
    lamp = tri[shape == scene.shape_index("light")][0]
    wall = tri[shape == scene.shape_index("wall-x0")]
    pts = nodes.recv_pts[wall].astype(np.float64)
    behind = ((pts[:, :, 1] > 0.7) & (pts[:, :, 1] < 1.3) & (pts[:, :, 2] > 0.7) & (pts[:, :, 2] < 1.3)).any(axis=1)
    centroid = nodes.poly[wall, :3].astype(np.float64).mean(axis=1)
    centre_out = ~((centroid[:, 1] > 0.7) & (centroid[:, 1] < 1.3) & (centroid[:, 2] > 0.7) & (centroid[:, 2] < 1.3))
    edge = np.flatnonzero(behind & centre_out)
    clear = np.flatnonzero(~behind & (centroid[:, 2] < 0.6))
    assert len(edge) and len(clear)
    ids = np.concatenate([edge, clear])
    args = (scene.mi_scene, core.NodeBuffers.upload(nodes), centroid[ids], nodes.normal[wall[ids]].astype(np.float64),
            wall[ids], np.full(len(ids), lamp), 7, state.offset, 16)
    from_centre = transfer.leaves_blocked(*args)
    from_points = transfer.leaves_blocked(*args, from_points=True)
    missed = np.flatnonzero(~from_centre[:len(edge)])     # (a centre's rays may cross the panel too)
    assert len(missed) >= 3 and from_points[missed].all(), (from_centre, from_points)
    assert not from_points[len(edge):].any() and not from_centre[len(edge):].any()


def _barycentric(corners: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(S, 3) coordinates of points (S, 3) on triangles corners (S, 3, 3) (in their planes)."""
    e1, e2, d = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0], points - corners[:, 0]
    d11, d12, d22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    b1, b2 = (d * e1).sum(1), (d * e2).sum(1)
    den = d11 * d22 - d12 * d12
    beta, gamma = (d22 * b1 - d12 * b2) / den, (d11 * b2 - d12 * b1) / den
    return np.stack([1.0 - beta - gamma, beta, gamma], 1)


def test_a_source_sample_is_credited_to_the_leaf_that_holds_it():
    """The final gather credits a source's sample to the leaf below its triangle that holds it
    (``nodes.leaf_holding``, from where ``transfer.source_point`` put it): drawn on every node of a
    scene whose triangles were split three levels down (slivers halved, the others quartered),
    each point lies in the leaf found, and with a node limit in a node made before it."""
    import mitsuba as mi
    from mirad.nodes import leaf_holding
    from mirad.transfer import NodeBuffers, source_point

    T = mi.ScalarTransform4f
    scene = mirad.load_scene({"type": "scene", "sliver": square(T().scale([10.0, 0.5, 1.0]), sid="sliver"),
                              "plate": square(T().translate([0, 0, 2]).rotate([1, 0, 0], 180), radiance=1.0,
                                              sid="plate")})
    state = core.build(scene, make_settings(tolerance=0.1, quiet=True, core="hierarchical"))
    nodes = state.nodes
    limits = []
    for _ in range(3):
        limits.append(len(nodes))
        core.split_leaves(state, nodes.leaves[nodes.kind[nodes.leaves] == core.TRIANGLE])
    split = np.flatnonzero((nodes.kind == core.TRIANGLE) & (nodes.children[:, 0] >= 0))
    assert (nodes.children[split, 3] >= 0).any() and (nodes.children[split, 2] < 0).any()   # both kinds
    count = 64
    src = np.repeat(np.arange(len(nodes)), count)
    y, _, tri, _, place = source_point(NodeBuffers.upload(nodes), mi.UInt32(src), mi.UInt32(np.tile(np.arange(count),
                                       len(nodes))), count, mi.UInt32(0x51ED))
    y = np.stack([np.asarray(c.numpy(), np.float64) for c in (y.x, y.y, y.z)], 1)
    tri, place = np.asarray(tri.numpy(), np.int64), np.asarray(place.numpy(), np.uint32)
    for limit in (None, limits[-1]):
        bound = len(nodes) if limit is None else limit
        # (the triangles made before the limit, as the gather's sources are)
        mine = tri < bound
        leaf = leaf_holding(nodes, tri[mine], place[mine], limit)
        assert np.all(leaf < bound)
        # (a leaf, or a node whose children were made at or after the limit)
        assert np.all((nodes.children[leaf, 0] < 0) | (nodes.children[leaf, 0] >= bound))
        bary = _barycentric(nodes.poly[leaf, :3].astype(np.float64), y[mine])
        assert bary.min() >= -1e-3, bary.min()
        assert (leaf != tri[mine]).any()      # (points drawn on split triangles went down)



def _receiver_over_an_l_shaped_light(tmp_path):
    """An L-shaped light (three unit squares, six triangles in one plane: a face cluster whose
    bounding rectangle overhangs it by a quarter) facing up, and a 5 cm square receiver (rho 0.5)
    facing down 12 cm over the square the L leaves out, by its inner corner. Returns the loaded
    scene, the receiver's triangles and their exact mean irradiance per unit radiance (pi times
    the squares' polygon form factors, over 4 x 7 points a triangle)."""
    import mitsuba as mi
    import trimesh
    from mirad.formfactor import point_to_polygon
    from mirad.nodes import DUNAVANT7_BARY, DUNAVANT7_WEIGHT

    corners = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    squares = [corners + [dx, dy, 0] for dx, dy in ((0, 0), (1, 0), (0, 1))]
    faces = np.concatenate([[[4 * i, 4 * i + 1, 4 * i + 2], [4 * i, 4 * i + 2, 4 * i + 3]] for i in range(3)])
    trimesh.Trimesh(np.concatenate(squares), faces, process=False).export(tmp_path / "light.ply")
    T = mi.ScalarTransform4f
    scene = mirad.load_scene({
        "type": "scene",
        "light": {"type": "ply", "filename": str(tmp_path / "light.ply"), "id": "light", "face_normals": True,
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}},
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}},
        "receiver": square(T().translate([1.06, 1.04, 0.12]).rotate([1, 0, 0], 180).scale(0.025), rho=0.5,
                           sid="receiver")})
    mine = np.flatnonzero(np.asarray(scene.shape_ids)[scene.tri_shape] == "receiver")
    tv = scene.to_user(scene.tri_vertices[mine])                            # (2, 3, 3)
    mid = (tv + np.roll(tv, -1, axis=1)) / 2
    quarters = np.stack([np.stack([tv[:, 0], mid[:, 0], mid[:, 2]], 1), np.stack([mid[:, 0], tv[:, 1], mid[:, 1]], 1),
                         np.stack([mid[:, 2], mid[:, 1], tv[:, 2]], 1), np.stack([mid[:, 1], mid[:, 2], mid[:, 0]], 1)], 1)
    x = np.einsum("kv,tqvc->tqkc", DUNAVANT7_BARY, quarters)                # (2, 4, 7, 3)
    ff = np.array([[[sum(point_to_polygon(p, [0, 0, -1], sq) for sq in squares) for p in q] for q in t] for t in x])
    return scene, mine, np.pi * np.einsum("k,tqk->t", DUNAVANT7_WEIGHT, ff) / 4


def test_a_near_overhanging_source_is_summed_over_its_triangles(tmp_path, monkeypatch):
    """A receiver 12 cm over the square an L-shaped light leaves out: the light's face cluster
    (six triangles) overhangs it right there, so its rectangle times its fill would bring 46 %
    too much. At tolerance 0.5 the passes link the receiver to the whole light, and the final
    gather takes that source as the sum of its triangles' exact form factors
    (``core.EXACT_FACE_TRIANGLES``): 28 pairs where gathering from its pieces one by one took 36
    (``core.EXACT_FACE_TRIANGLES`` = 0); both match the closed form."""
    scene, mine, exact = _receiver_over_an_l_shaped_light(tmp_path)
    summed = mirad.solve(scene, tolerance=0.5, seed=1, **HIER)
    monkeypatch.setattr(core, "EXACT_FACE_TRIANGLES", 0)
    pieces = mirad.solve(scene, tolerance=0.5, seed=1, **HIER)
    for sol in (summed, pieces):
        np.testing.assert_allclose(sol.triangle_radiosity[mine], np.broadcast_to(0.5 * exact[:, None], (2, 3)),
                                   rtol=5e-3)
    assert summed.stats["gather_pairs"] < pieces.stats["gather_pairs"]
    # (and the rectangle times its fill is far off there: the case is the overhang's)
    from mirad.formfactor import point_to_polygon
    rect = 0.75 * np.pi * point_to_polygon([1.06, 1.04, 0.12], [0, 0, -1], [[0, 0, 0], [2, 0, 0], [2, 2, 0], [0, 2, 0]])
    assert abs(rect / exact.mean() - 1.0) > 0.2
