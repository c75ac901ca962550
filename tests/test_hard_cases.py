"""Numerical hard cases (THEORY.md §8, issue 7) against Mitsuba path tracing, closed forms and invariants.

Scenes come from ``scenes/hard-cases/cases.py`` (PLY files written to a temporary folder). Per-element
comparisons use input triangles: mirad's triangle radiosity is the area mean of its leaves, the
reference (``mirad.reference``, B = pi L_o at uniform points) estimates the same mean. Where a test
compares per element against 3 %, the reference runs enough paths that its standard error is at most
a fifth of that (checked), and the criterion is |B - B_ref| <= 3 % B_ref + 3 sigma_ref.
"""

import sys
import warnings

import numpy as np
import pytest

import mirad
from conftest import SCENES, area_mean, closed_box
from mirad.reference import triangle_reference
from mirad.settings import Settings, make_settings
from mirad.solver import Problem

sys.path.insert(0, str(SCENES / "hard-cases"))
import cases  # noqa: E402

#: Issue 7: per-element and per-shape agreement with the path-traced reference.
REF_REL = 0.03


def _within(b, ref, rel=REF_REL):
    """(K,) bool: |B - B_ref| <= rel B_ref + 3 sigma_ref (first channel; the scenes are grey)."""
    return np.abs(b[:, 0] - ref.radiosity[:, 0]) <= rel * ref.radiosity[:, 0] + 3 * ref.stderr[:, 0]


def _shape_mean(sol, scene, sid, values=None):
    mask = sol.triangle_shape == scene.shape_index(sid)
    values = sol.triangle_radiosity if values is None else values
    return area_mean(values[mask], sol.triangle_area[mask])


@pytest.fixture(scope="module")
def corner(tmp_path_factory):
    scene = mirad.load_scene(cases.corner_room(tmp_path_factory.mktemp("corner")))
    return scene, mirad.solve(scene)


# --- 1. adjacent polygons: shared edges, 90 degree corners, a 10 degree wedge ---------------------

def test_adjacent_polygons_form_factors_and_row_sums_stay_bounded(corner):
    scene, _ = corner
    prob = Problem(scene, make_settings(clustering="off", core="legacy"))
    prob.elements.split(prob.elements.leaves)          # one level below the patches: 4x the edges
    prob.update_direct(np.arange(len(prob.elements)))
    leaves = prob.elements.leaves
    recv, src = np.repeat(leaves, len(leaves)), np.tile(leaves, len(leaves))
    ok = prob.facing_pairs(recv, src)
    prob.links = prob.evaluate(recv[ok], src[ok], prob.geometry())
    ff = prob.links.ff
    assert np.all(np.isfinite(ff)) and ff.min() >= 0 and ff.max() <= 1.0
    rows = prob.system(leaves).gather(np.ones((len(leaves), 1)))[:, 0]
    assert np.all(np.isfinite(rows)) and rows.max() <= 1.0 + 1e-6
    assert np.median(rows) > 0.9                        # closed room: rows near 1, not emptied


def test_refinement_stops_at_the_minimum_element_size(corner):
    _, sol = corner
    stats = sol.stats
    assert not stats["capped"]
    # an element splits only while its area exceeds A_min: children are >= A_min / 4 (1 -> 4 split)
    assert sol.leaf_area.min() >= stats["min_element_area"] / 4 * (1 - 1e-9)
    assert np.all(np.isfinite(sol.triangle_radiosity)) and sol.triangle_radiosity.min() >= 0


def _near_corner_triangles(scene):
    """Wall, floor and ceiling triangles touching one of the room's 90 degree edges (x, y or z in {0, 2})."""
    tv = scene.tri_vertices
    room = np.isin(scene.tri_shape, [scene.shape_index(s) for s in ("floor", "ceiling", "wall-x0", "wall-x1",
                                                                      "wall-y0", "wall-y1")])
    on_edge = (np.abs(tv) < 1e-6) | (np.abs(tv - 2.0) < 1e-6)          # (T, 3 corners, 3 axes)
    two_planes = on_edge.sum(axis=2) >= 2                               # a corner on a room edge
    return np.flatnonzero(room & two_planes.any(axis=1))


def test_radiosity_at_90_degree_corners_matches_path_tracing(corner):
    scene, sol = corner
    tris = _near_corner_triangles(scene)[::3]
    ref = triangle_reference(scene, samples_per_triangle=1 << 16, seed=5, triangles=tris)
    assert np.all(ref.stderr[:, 0] <= REF_REL / 5 * ref.radiosity[:, 0])
    ok = _within(sol.triangle_radiosity[tris], ref)
    assert ok.all(), (f"{(~ok).sum()}/{len(tris)} corner triangles off by more than 3 %: rel. errors "
                      f"{np.round(sol.triangle_radiosity[tris, 0] / ref.radiosity[:, 0] - 1, 3)[~ok]}")


@pytest.mark.xfail(strict=True, reason="measured 2026-11-23 at tolerance 0.03: 22 of 48 wedge triangles off by "
                   "more than 3 % (the plate's mean is right, 0.091 vs 0.088 W/m^2, since coplanar front/back links "
                   "no longer carry light; before that fix cluster-opened links leaked 2x through the plate): "
                   "per-triangle accuracy inside a 10 degree wedge needs finer elements than tolerance 0.03 gives")
def test_radiosity_inside_a_10_degree_wedge_matches_path_tracing(corner):
    scene, sol = corner
    tv = scene.tri_vertices
    wedge = np.flatnonzero((scene.tri_shape == scene.shape_index("plate"))
                           | ((scene.tri_shape == scene.shape_index("floor")) & (tv[:, :, 0].min(1) >= 0.5 - 1e-6)
                              & (tv[:, :, 0].max(1) <= 1.5 + 1e-6) & (tv[:, :, 1].min(1) >= 0.5 - 1e-6)
                              & (tv[:, :, 1].max(1) <= 1.5 + 1e-6)))
    ref = triangle_reference(scene, samples_per_triangle=1 << 15, seed=6, triangles=wedge)
    ok = _within(sol.triangle_radiosity[wedge], ref)
    assert ok.all(), f"{(~ok).sum()}/{len(wedge)} wedge triangles off by more than 3 %"


# --- 2. slivers ---------------------------------------------------------------------------------

def test_sliver_triangles_refine_to_a_bounded_count_and_match_path_tracing(tmp_path):
    scene = mirad.load_scene(cases.sliver_room(tmp_path))
    e = np.linalg.norm(scene.tri_vertices - np.roll(scene.tri_vertices, 1, axis=1), axis=2)
    aspect = e.max(1) ** 2 / (2 * scene.tri_area)      # longest edge / height
    slivers = np.flatnonzero(aspect >= 999)
    assert len(slivers) == 4
    sol = mirad.solve(scene)
    assert not sol.stats["capped"] and sol.stats["elements"] < 20 * scene.triangle_count
    assert sol.leaf_area.min() >= sol.stats["min_element_area"] / 4 * (1 - 1e-9)
    floor = np.flatnonzero(scene.tri_shape == scene.shape_index("floor"))
    ref = triangle_reference(scene, samples_per_triangle=1 << 16, seed=7, triangles=floor)
    assert np.all(ref.stderr[:, 0] <= REF_REL / 5 * ref.radiosity[:, 0])
    ok = _within(sol.triangle_radiosity[floor], ref)
    assert ok.all(), np.round(sol.triangle_radiosity[floor, 0] / ref.radiosity[:, 0] - 1, 3)


# --- 3. coplanar and nearly coplanar elements ----------------------------------------------------

def _lit_floor(tmp_path, jitter=0.0):
    """A 2 x 2 m floor of 8 x 8 cells under a ceiling light, nothing else (open scene)."""
    parts = cases.room_parts(cells=8, skip=("ceiling", "wall-x0", "wall-x1", "wall-y0", "wall-y1"))
    v, f = parts["floor"]["mesh"]
    rng = np.random.default_rng(1)
    parts["floor"]["mesh"] = (v + np.c_[0 * v[:, :2], jitter * rng.uniform(-1, 1, len(v))], f)
    return mirad.load_scene(cases.to_dict(tmp_path, parts))


def test_coplanar_elements_exchange_exactly_nothing(tmp_path):
    scene = _lit_floor(tmp_path)
    prob = Problem(scene, make_settings(clustering="off", core="legacy"))
    floor = np.flatnonzero(scene.tri_shape[scene.patch_tri] == scene.shape_index("floor"))
    recv, src = np.repeat(floor, len(floor)), np.tile(floor, len(floor))
    keep = recv != src
    recv, src = recv[keep], src[keep]
    assert not prob.facing_pairs(recv, src).any()       # never linked
    links = prob.evaluate(recv, src, prob.geometry())   # and zero even if they were
    assert np.all(links.ff == 0.0)


@pytest.mark.parametrize("jitter", [1e-6, 1e-4])
def test_nearly_coplanar_elements_do_not_shadow_themselves(tmp_path, jitter):
    # floor vertices jittered by +-jitter m over 25 cm cells (tilts up to ~8 jitter rad): the light's
    # links to the floor must see every ray pass (rays leave the floor at grazing-free angles but start
    # next to nearly coplanar neighbours), and the floor's radiosity must equal the flat floor's
    scene = _lit_floor(tmp_path, jitter=jitter)
    prob = Problem(scene, make_settings(clustering="off", core="legacy"))
    recv, src = prob.initial_pairs()
    links = prob.evaluate(recv, src, prob.geometry())
    from_light = scene.tri_shape[scene.patch_tri[links.src]] == scene.shape_index("light")
    assert from_light.sum() == 256                     # 2 light triangles x 128 floor triangles
    assert np.all(links.vis[from_light] == 1.0)
    # floor <-> floor links of the tilted cells exist but carry next to nothing (grazing: cos ~ 1e-3)
    floor = scene.shape_index("floor")
    pair = (scene.tri_shape[scene.patch_tri[links.src]] == floor) & (scene.tri_shape[scene.patch_tri[links.recv]] == floor)
    row = np.bincount(links.recv[pair], weights=links.ff[pair].astype(float), minlength=130)
    assert row.max() < 1e-4
    flat = mirad.solve(_lit_floor(tmp_path / "flat"), tolerance=0.05)
    bumpy = mirad.solve(scene, tolerance=0.05)
    np.testing.assert_allclose(bumpy.triangle_radiosity, flat.triangle_radiosity, rtol=0.01)


# --- 4. near-white rooms --------------------------------------------------------------------------

def test_near_white_furnace_converges_with_the_default_solver_and_jacobi_is_not_it():
    assert Settings().solver != "jacobi"
    box = closed_box(0.99, 1 / np.pi)                  # E = 1, rho = 0.99: B = 100 everywhere
    sol = mirad.solve(box, tolerance=0.05)
    np.testing.assert_allclose(sol.triangle_radiosity, 100.0, rtol=0.01)
    jacobi = mirad.solve(box, tolerance=0.05, solver="jacobi")
    # measured 2026-11-23 (legacy core): gmres 10 iterations, Jacobi 921 (rho^k: ~ln(1e-6)/ln(0.99)
    # sweeps). Either core solves once per refinement pass, warm-started; what a solver is worth
    # shows in the most one solve took
    assert sol.stats["solver_iterations_max"] <= 30
    assert jacobi.stats["solver_iterations_max"] >= 20 * sol.stats["solver_iterations_max"]


# --- 5. tiny bright source ---------------------------------------------------------------------

def test_tiny_bright_source_room_radiosity_matches_path_tracing(tmp_path):
    # (this failed until 2026-11-25, 2.5-4.6 % low with no refinement at all: the linear solve's
    # tolerance was relative to the emission, a million times the reflected light here, so the
    # warm start passed for converged; it is now relative to the first bounce, linear.py)
    scene = mirad.load_scene(cases.tiny_light_room(tmp_path))
    light = scene.tri_shape == scene.shape_index("light")
    room_area = scene.tri_area[~light].sum()
    assert scene.tri_area[light].sum() == pytest.approx(1e-6 * room_area, rel=1e-3)
    sol = mirad.solve(scene)
    ref = triangle_reference(scene, samples_per_triangle=1 << 12, seed=8)
    for sid in ("floor", "ceiling", "wall-x0", "wall-y1"):
        mask = scene.tri_shape == scene.shape_index(sid)
        b = area_mean(sol.triangle_radiosity[mask], scene.tri_area[mask])[0]
        r = area_mean(ref.radiosity[mask], scene.tri_area[mask])[0]
        assert b == pytest.approx(r, rel=REF_REL), sid


# --- 6. scale invariance and rigid motions -----------------------------------------------------

def _moved(scale=1.0, angle=0.0, shift=(0.0, 0.0, 0.0)):
    from meshgen import rotation

    m = np.eye(4)
    m[:3, :3] = scale * rotation((1, 2, 3), angle)
    m[:3, 3] = shift
    return m


@pytest.fixture(scope="module")
def sheet_solution(tmp_path_factory):
    scene = mirad.load_scene(cases.sheet_room(tmp_path_factory.mktemp("sheet")))
    return scene, mirad.solve(scene)


#: Issue 7: the same radiosity within 1e-6 relative, the same element count.
MOTION_REL = 1e-6


def _float32_flip(what):
    return pytest.mark.xfail(strict=True, reason=f"measured 2026-11-23 (llvm_ad_rgb): {what}")


@pytest.mark.parametrize("xform", [
    pytest.param(_moved(scale=1e3), id="scale-1e3"),                      # measured: same elements, 2.2e-7
    pytest.param(_moved(scale=2.0), id="scale-2"),                        # measured: bitwise equal
    pytest.param(_moved(scale=1e-3), id="scale-1e-3", marks=_float32_flip(
        "same 2078 elements, largest triangle difference 2.3 % (median 0.08 %). Not an absolute "
        "epsilon: scales 1e-2, 1e2, 1e4 held (<= 4.5e-7) when last swept; float32 rounding of the scaled "
        "vertices flips refinement decisions, and one flipped split moves its neighbours by up to the "
        "tolerance")),
    # measured: same 823 elements, 3.8e-7 (float32 vertices 11 m from the origin are rounded by
    # ~5e-7 m; it held to 1e-6 once the estimate counted partly visible links apart; before, 9.8e-6.
    # With the gathered pairs' sources judged from the links' planes too, one ray turned over past
    # the sheet: 8.5e-6 on one triangle; those pairs keep the solved means, core.VARIED_SOURCES)
    pytest.param(_moved(shift=(5, -3, 11)), id="translate"),
    pytest.param(_moved(angle=37.0, shift=(5, -3, 11)), id="rigid", marks=_float32_flip(
        "2058 elements against 2078, largest difference 2.3 % (median 0.09 %): float32 rounding of the "
        "rotated vertices flips refinement decisions near their thresholds")),
])
def test_scaled_and_moved_scene_gives_the_same_radiosity_and_elements(tmp_path, sheet_solution, xform):
    _, base = sheet_solution
    moved = mirad.solve(cases.sheet_room(tmp_path, xform=xform))
    # radiance is kept, so B (W/m^2) is scale-free (a light of fixed power would scale E by 1/s^2)
    assert moved.stats["elements"] == base.stats["elements"]
    rel = np.abs(moved.triangle_radiosity - base.triangle_radiosity) / base.triangle_radiosity
    assert rel.max() <= MOTION_REL


# --- 7. light leaks under a wall that pierces the floor ----------------------------------------

def test_closed_dark_side_of_a_piercing_wall_stays_dark(tmp_path):
    """A wall pierces the floor and closes its dark side: the path tracer gives ~1e-6 W/m^2 there.
    Measured 2026-11-23 at the default tolerance 0.03: 0.0129 W/m^2 against 0.627 on the lit side
    (2.1 %); the light leaked under the wall partly through the linear sources, whose moments took
    a floor source's mean visibility over all of it, lit side and dark side alike. With each part's
    own visibility (``core._part_moments``, 2026-11-28) 0.94 % at seed 0 (0.79 and 0.82 % at seeds
    1 and 2): within the 1 % asked, but the rest still leaks by other ways."""
    scene = mirad.load_scene(cases.pierced_room(tmp_path))
    sol = mirad.solve(scene)
    floor = np.flatnonzero(scene.tri_shape == scene.shape_index("floor"))
    x = scene.tri_vertices[floor][:, :, 0]
    lit, dark = floor[x.max(1) <= 1.0 + 1e-9], floor[x.min(1) >= 1.0 - 1e-9]
    assert len(lit) and len(dark)
    b = sol.triangle_radiosity[:, 0]
    lit_mean = np.average(b[lit], weights=scene.tri_area[lit])
    dark_mean = np.average(b[dark], weights=scene.tri_area[dark])
    assert dark_mean < 0.01 * lit_mean, f"dark side {dark_mean:.4g} vs lit {lit_mean:.4g} W/m^2"


def test_no_fit_carries_light_across_a_wall_that_pierces_the_floor():
    """The shipped wall-pierce scene: its floor cells straddle the partition (x = 2 mid-cell).
    The final gather fitted the lamp's light over a floor face cluster from points that all lay
    on the lit side, and read the fit at leaves beyond the partition: at tolerance 0.05 the
    straddling cells read up to 16 % above the path tracer (65,536 paths over the 16 cells).
    A fit may not cross a surface that crosses its receiver (``core.crossed_leaves``): none
    above 5 %. (They still read 3-12 % low, and at tolerance 0.1 up to 18 % high: light leaks
    under the wall by other ways too, see the xfail above.)"""
    scene = mirad.load_scene(SCENES / "wall-pierce" / "scene.xml")
    tv = scene.tri_vertices
    floor = scene.tri_shape == scene.shape_index("floor")
    cells = np.flatnonzero(floor & (tv[:, :, 0].min(1) < 2.0) & (tv[:, :, 0].max(1) > 2.0))
    assert len(cells) == 16
    ref = triangle_reference(scene, samples_per_triangle=1 << 14, seed=3, triangles=cells)
    sol = mirad.solve(scene, tolerance=0.05, core="hierarchical", quiet=True)
    rel = sol.triangle_radiosity[cells, 0] / ref.radiosity[:, 0] - 1
    assert rel.max() <= 0.05, np.round(rel, 3)


# --- 8. thin two-sided surfaces ------------------------------------------------------------------

def test_each_side_of_a_two_sided_sheet_gets_its_own_radiosity(tmp_path, sheet_solution):
    scene, sol = sheet_solution
    sheet = np.flatnonzero(scene.tri_shape == scene.shape_index("sheet"))
    front, back = sol.triangle_radiosity[sheet, 0], sol.back_radiosity[sheet, 0]
    ref_front = triangle_reference(scene, samples_per_triangle=1 << 14, seed=9, triangles=sheet)
    # the back side's reference: the same scene with the sheet's faces flipped (front <-> back)
    flipped = mirad.load_scene(cases.sheet_room(tmp_path, flip=True))
    ref_back = triangle_reference(flipped, samples_per_triangle=1 << 14, seed=10, triangles=sheet)
    assert area_mean(ref_front.radiosity, scene.tri_area[sheet])[0] > 3 * area_mean(ref_back.radiosity,
                                                                                    scene.tri_area[sheet])[0]
    for b, ref in ((front, ref_front), (back, ref_back)):
        mean, mean_ref = np.average(b, weights=scene.tri_area[sheet]), np.average(ref.radiosity[:, 0],
                                                                                  weights=scene.tri_area[sheet])
        assert mean == pytest.approx(mean_ref, rel=REF_REL)


@pytest.mark.parametrize("core, seed", [
    pytest.param("legacy", 0, marks=pytest.mark.xfail(
        strict=True, reason="measured 2026-11-23 at tolerance 0.05: triangles below the sheet get up to 1.9e-4 "
        "W/m^2 (median ~1e-5) against ~0.3 on the lit ceiling: a small leak through an opaque sheet")),
    ("hierarchical", 0),
    # (seed 5 put one of a wall link's source points 0.04 mm above the sheet: shadow rays that
    # stopped 1e-4 of their length short of it, 0.2 mm, never met the sheet, and the floor read
    # 1.3e-3 W/m^2; they stop half the ray offset short now, arrays.shadow_ray_length)
    ("hierarchical", 5)])
def test_no_light_crosses_an_opaque_two_sided_sheet(tmp_path, core, seed):
    # a two-sided sheet closes the room at z = 1 (edges on the walls): everything below stays black
    parts = cases.room_parts()
    parts["sheet"] = cases.part(cases.grid((0, 0, 1.0), (2.0, 0, 0), (0, 2.0, 0), 4, 4), 0.5, twosided=True)
    scene = mirad.load_scene(cases.to_dict(tmp_path, parts))
    sol = mirad.solve(scene, tolerance=0.05, core=core, seed=seed)
    below = np.flatnonzero(scene.tri_vertices[:, :, 2].max(1) <= 1.0 + 1e-9)
    below = below[scene.tri_shape[below] != scene.shape_index("sheet")]
    sheet = scene.tri_shape == scene.shape_index("sheet")
    assert len(below) == 32 + 4 * 16                   # floor + the lower half of four walls
    lit = _shape_mean(sol, scene, "ceiling")[0]
    assert sol.triangle_radiosity[sheet].min() > 0.1    # its front faces the light
    # physically exactly 0; 1e-6 of the lit side allows float round-off, not a leak
    assert sol.back_radiosity[sheet].max() <= 1e-6 * lit  # the sheet's underside sees only darkness
    assert sol.triangle_radiosity[below].max() <= 1e-6 * lit


# --- 9. coincident duplicates and non-manifold meshes ------------------------------------------

def test_duplicates_and_non_manifold_edges_are_detected_warned_once_and_solved(tmp_path):
    parts = cases.room_parts()
    sheet = cases.grid((0.6, 0.6, 0.8), (0.8, 0, 0), (0, 0.8, 0), 2, 2)
    parts["sheet"] = cases.part(sheet, 0.5)
    parts["sheet-copy"] = cases.part(sheet, 0.5)                      # coincident duplicate shape
    # a fin: a third triangle on the middle edge of a two-triangle quad (the edge has 3 triangles)
    v = np.array([[0.5, 1.5, 0.3], [1.5, 1.5, 0.3], [1.5, 1.7, 0.3], [0.5, 1.7, 0.3], [1.0, 1.6, 0.8]])
    fin = np.array([[0, 1, 2], [0, 2, 3], [0, 2, 4]])
    parts["fin"] = cases.part((v, fin), 0.5)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = mirad.load_scene(cases.to_dict(tmp_path, parts))
    dup = [w for w in caught if "coincide" in str(w.message)]
    fins = [w for w in caught if "non-manifold" in str(w.message)]
    assert len(dup) == 1 and len(fins) == 1
    assert "sheet" in str(dup[0].message) and "'fin'" in str(fins[0].message)
    assert scene.features["duplicate_triangles"] == 16 and scene.features["non_manifold_edges"] == 1
    sol = mirad.solve(scene, tolerance=0.05)
    assert np.all(np.isfinite(sol.triangle_radiosity)) and sol.triangle_radiosity.min() >= 0
    # the copies receive the same light (no shadowing between coincident triangles)
    a, b = _shape_mean(sol, scene, "sheet")[0], _shape_mean(sol, scene, "sheet-copy")[0]
    assert a == pytest.approx(b, rel=0.02) and a > 0.1


# --- 10. many emitters ---------------------------------------------------------------------------

# The floor's mean within REF_REL is stricter than either tolerance asks. The legacy core met it at
# 0.2 (3 s; 0.05 takes ~95 s on 2 cores, see bench_hard_cases); the hierarchical core's floor is
# +2.6 % there (estimate 2.0 %, 16,384-path reference) and +1.0 % at 0.1, which takes it 1.1 s
@pytest.mark.parametrize("core, tolerance", [("legacy", 0.2), ("hierarchical", 0.1)])
def test_a_thousand_small_lights_emit_their_total_power_into_a_closed_room(tmp_path, core, tolerance):
    scene = mirad.load_scene(cases.many_lights_room(tmp_path, count=1000))
    lamps = np.flatnonzero(np.char.startswith(np.array(scene.shape_ids), "lamp-"))
    assert len(lamps) == 1000 and scene.features["emitters"]["area (triangles)"] == 2000
    emitted = (scene.tri_area * scene.tri_emission[:, 0]).sum()
    assert emitted == pytest.approx(1000 * np.pi * 1e-4, rel=1e-4)     # 1000 x (1 cm)^2 x pi x 1
    sol = mirad.solve(scene, tolerance=tolerance, core=core)
    # every watt ends on a front side (black ceiling: nothing reaches the lamps' backs)
    absorbed = (sol.triangle_area * (1 - scene.tri_rho[:, 0]) * sol.triangle_irradiance[:, 0]).sum()
    assert absorbed == pytest.approx(emitted, rel=0.02)
    floor = np.flatnonzero(scene.tri_shape == scene.shape_index("floor"))
    ref = triangle_reference(scene, samples_per_triangle=1 << 12, seed=12, triangles=floor)
    assert _shape_mean(sol, scene, "floor")[0] == pytest.approx(
        np.average(ref.radiosity[:, 0], weights=scene.tri_area[floor]), rel=REF_REL)
