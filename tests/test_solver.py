"""Hierarchical radiosity against closed forms and invariants."""

import numpy as np
import pytest

import mirad
from conftest import (CLOSED_FORM_REL, F_PARALLEL, F_PERPENDICULAR, RECIPROCITY_REL, SCENES, area_mean,
                      closed_box)
from mirad.settings import make_settings
from mirad.solver import Problem


def _receiver_irradiance(path, **options):
    scene = mirad.load_scene(path)
    sol = mirad.solve(scene, **options)
    mask = sol.triangle_shape == scene.shape_index("receiver")
    return area_mean(sol.triangle_irradiance[mask], sol.triangle_area[mask])[0], sol


@pytest.mark.parametrize("name, exact", [("parallel-squares", F_PARALLEL),
                                         ("perpendicular-squares", F_PERPENDICULAR)])
def test_form_factor_closed_forms(name, exact):
    # emitter exitance E = pi * (1/pi) = 1 W/m^2 and black, so H_receiver = F exactly
    h, sol = _receiver_irradiance(SCENES / "closed-form" / f"{name}.xml", tolerance=0.01)
    assert h == pytest.approx(exact, rel=CLOSED_FORM_REL)
    assert sol.stats["rays"] > 0


@pytest.mark.parametrize("rho", [0.5, 0.9])
def test_white_furnace(rho):
    sol = mirad.solve(closed_box(rho, 1 / np.pi), tolerance=0.05)
    b = sol.triangle_radiosity
    np.testing.assert_allclose(b, 1.0 / (1.0 - rho), rtol=CLOSED_FORM_REL)


def test_furnace_near_white_converges_with_default_solver():
    sol = mirad.solve(closed_box(0.99, 1 / np.pi), tolerance=0.05)
    np.testing.assert_allclose(sol.triangle_radiosity, 100.0, rtol=CLOSED_FORM_REL)
    assert sol.stats["solver_iterations"] < 500


def test_the_reported_residual_is_the_output_systems(cornell):
    """``stats["solver_residual"]`` is the residual of the system the output solves, which stops at
    ``solver_tolerance``, not a refinement pass's, which stops at 1 % of the error tolerance (4e-3 at
    tolerance 0.4): it follows ``solver_tolerance``."""
    residual = {t: mirad.solve(cornell, tolerance=0.4, solver_tolerance=t).stats["solver_residual"]
                for t in (1e-2, 1e-6, 1e-9)}
    assert residual[1e-6] < 1e-4
    assert residual[1e-9] < residual[1e-6] < residual[1e-2], residual


def test_row_sums_and_reciprocity_of_link_transfers():
    scene = mirad.load_scene(closed_box(0.5, 1 / np.pi))
    # 64 points per link: patch-level links between whole faces are the coarsest case
    prob = Problem(scene, make_settings(samples_per_link=64))
    recv, src = prob.initial_pairs()
    links = prob.evaluate(recv, src, prob.geometry())
    assert np.all(links.ff <= 1.0)
    row = np.bincount(links.recv, weights=links.ff.astype(float), minlength=len(prob.patch_normal))
    assert row.max() <= 1 + 1e-6
    assert row.min() > 0.97  # closed: each patch sees the whole hemisphere
    # reciprocity A_i F_ij = A_j F_ji, face against face (unoccluded)
    area = prob.elements.area
    face = scene.tri_shape[scene.patch_tri]
    n_faces = len(scene.shape_ids)
    transfer = np.zeros((n_faces, n_faces))
    np.add.at(transfer, (face[links.recv], face[links.src]), area[links.recv] * links.ff)
    np.testing.assert_allclose(transfer, transfer.T, rtol=RECIPROCITY_REL)


def test_energy_balance_in_a_closed_scene():
    box = closed_box(0.6, 0.0)
    box["floor"]["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": 1 / np.pi}}
    scene = mirad.load_scene(box)
    sol = mirad.solve(scene, tolerance=0.02)
    area = sol.triangle_area
    rho = scene.tri_rho[:, 0]
    absorbed = (area * (1 - rho) * sol.triangle_irradiance[:, 0]).sum()
    emitted = (area * scene.tri_emission[:, 0]).sum()
    assert absorbed == pytest.approx(emitted, rel=0.01)


def test_same_seed_gives_bitwise_identical_solution(cornell):
    a = mirad.solve(cornell, tolerance=0.1, seed=3)
    b = mirad.solve(cornell, tolerance=0.1, seed=3)
    assert np.array_equal(a.triangle_radiosity, b.triangle_radiosity)
    c = mirad.solve(cornell, tolerance=0.1, seed=4)
    assert not np.array_equal(a.triangle_radiosity, c.triangle_radiosity)


@pytest.mark.parametrize("solver", ["jacobi", "gauss-seidel"])
def test_solvers_agree(solver):
    ref = mirad.solve(closed_box(0.7, 1 / np.pi), tolerance=0.1)
    other = mirad.solve(closed_box(0.7, 1 / np.pi), tolerance=0.1, solver=solver)
    np.testing.assert_allclose(other.triangle_radiosity, ref.triangle_radiosity, rtol=1e-4)


def test_cornell_box_outputs_have_contract_shapes(cornell):
    sol = mirad.solve(cornell, tolerance=0.1)
    t = cornell.triangle_count
    assert sol.shape_ids == cornell.shape_ids
    assert sol.triangle_radiosity.shape == (t, 3)
    assert sol.triangle_area.shape == (t,) and sol.triangle_shape.shape == (t,)
    assert sol.vertex_radiosity.shape == (len(cornell.vertices), 3)
    light = sol.shape_radiosity("light")
    np.testing.assert_allclose(light, cornell.tri_emission[cornell.tri_shape == 0].mean(0), rtol=0.05)
    for key in ("elements", "links", "rays", "seconds", "estimated_error", "features", "variant"):
        assert key in sol.stats
    assert set(sol.stats["seconds"]) >= {"total", "refine", "visibility", "solve"}
    assert np.all(sol.triangle_radiosity >= 0)


def test_point_light_direct_pass_follows_inverse_square_law():
    import mitsuba as mi

    T = mi.ScalarTransform4f
    scene = {"type": "scene",
             "floor": {"type": "rectangle", "id": "floor", "to_world": T().scale(0.01)},
             "bulb": {"type": "point", "position": [0, 0, 2], "intensity": {"type": "rgb", "value": 4.0}}}
    sol = mirad.solve(scene, tolerance=0.05)
    assert sol.stats["features"]["direct_light_pass"]
    np.testing.assert_allclose(sol.triangle_irradiance, 4.0 / 2**2, rtol=1e-3)
    h = sol.irradiance_at([[0, 0, 0], [1, 0, 0]], [[0, 0, 1], [0, 0, 1]])
    np.testing.assert_allclose(h[:, 0], [1.0, 4.0 * 2 / 5**1.5], rtol=1e-3)  # I cos / r^2


def test_leaf_row_sums_stay_at_most_one_behind_occluders(tmp_path):
    # The Cornell box closed by a black front wall: every leaf's true row sum is <= 1, but
    # independently sampled visibility per link can push an occluded receiver's sum above it.
    xml = (SCENES / "cornell-box" / "scene.xml").read_text().replace("</scene>", """
    <shape type="rectangle" id="front">
        <transform name="to_world"><rotate y="1" angle="180"/><translate value="0, 0, 1"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0, 0, 0"/></bsdf>
    </shape>
</scene>""")
    path = tmp_path / "closed-cornell.xml"
    path.write_text(xml)
    prob = Problem(mirad.load_scene(path), make_settings(samples_per_link=4))
    prob.elements.split(prob.elements.leaves)
    prob.update_direct(np.arange(len(prob.elements)))
    leaves = prob.elements.leaves
    recv = np.repeat(leaves, len(leaves))
    src = np.tile(leaves, len(leaves))
    ok = prob.facing_pairs(recv, src)
    prob.links = prob.evaluate(recv[ok], src[ok], prob.geometry())
    raw = np.bincount(prob.links.recv, weights=prob.links.ff.astype(float), minlength=len(prob.elements))
    assert raw.max() > 1.0 + 1e-3          # the case this guards against does occur
    rows = prob.system(leaves).gather(np.ones((len(leaves), 1)))[:, 0]
    assert rows.max() <= 1.0 + 1e-6
    assert np.median(rows) > 0.9           # scaled back, not emptied


@pytest.mark.parametrize("tolerance", [0.1, 0.05])
def test_error_control_on_the_cornell_box_against_path_tracing(cornell, tolerance):
    """The legacy core: the achieved error meets the tolerance and the estimate is within 2x of
    it (the hierarchical core's error is below this reference's noise; its own check, against a
    finer reference: test_core.test_the_estimate_is_within_twice_the_measured_error_on_the_cornell_box).

    Both in the tolerance's norm: area-weighted L1 of per-triangle radiosity over the mean
    reflected radiosity B - E, measured against Mitsuba's path tracer.
    """
    from mirad.metrics import relative_l1
    from mirad.reference import triangle_reference

    ref = triangle_reference(cornell, samples_per_triangle=16384, seed=11)
    sol = mirad.solve(cornell, tolerance=tolerance, core="legacy")
    area = sol.triangle_area
    reflected = ref.radiosity - cornell.tri_emission
    l1 = relative_l1(sol.triangle_radiosity, ref.radiosity, area=area)
    measured = l1 * area_mean(ref.radiosity, area).mean() / area_mean(reflected, area).mean()
    noise = relative_l1(ref.radiosity + ref.stderr, ref.radiosity, area=area)
    assert noise < 0.2 * measured            # the reference is fine enough to judge
    assert measured <= tolerance
    estimated = sol.stats["estimated_error"]
    assert 0.5 * estimated <= measured <= 2.0 * estimated
    # the same estimate in the validation metric's norm (over mean B)
    assert 0.5 * sol.stats["estimated_error_of_mean"] <= l1 <= 2.0 * sol.stats["estimated_error_of_mean"]


def test_link_cap_stops_refinement_with_a_warning_and_an_honest_estimate():
    """max_links (by default what half the memory holds) stops refinement where a wave would
    pass it, after the part of that wave that fits (the links of largest error first: the
    whole wave was dropped, 4,807 links): a warning names the cap, the links stay under it and
    the estimate says the tolerance was not reached. The warning points at the caller's line,
    not into mirad (a fixed stack level pointed at mirad/__init__.py, and Python showed it once
    per process)."""
    # (at 20,000 links the box already estimates 0.94 % since transfers whose rays were all
    # blocked count their visibility's noise, 2026-11-28: capped, and within the tolerance all
    # the same; 5,000 stops it at 1.55 %)
    with pytest.warns(UserWarning, match="max_links=5,000") as record:
        sol = mirad.solve(SCENES / "cornell-box" / "scene.xml", tolerance=0.01, max_links=5_000, quiet=True)
    assert {w.filename for w in record} == {__file__}
    assert sol.stats["capped"] and 0.98 * 5_000 <= sol.stats["links"] <= 5_000
    assert sol.stats["estimated_error"] > 0.01
    with pytest.raises(mirad.errors.SettingsError, match="max_links"):
        make_settings(max_links=0)


def test_a_request_the_link_budget_cannot_hold_is_told_before_solving():
    """The legacy core: the Cornell box without clusters starts with 536 links (its 36 patches' facing pairs):
    a cap below that is refused before any work, naming max_links and clustering; a cap below
    twice that (one refinement of every link) is warned about up front; 36 patches need 36 links
    whatever the clustering."""
    path = SCENES / "cornell-box" / "scene.xml"
    with pytest.raises(mirad.errors.SettingsError, match=r"536 links .* max_links=500; .*clustering='on'"):
        mirad.solve(path, tolerance=0.2, max_links=500, core="legacy", quiet=True)
    with pytest.raises(mirad.errors.SettingsError, match=r"36 patches need one link each: 36 links"):
        mirad.solve(path, tolerance=0.2, max_links=30, clustering="on", core="legacy", quiet=True)
    with pytest.warns(UserWarning, match=r"536 links before any refinement, and refining each once needs at "
                                         r"least 1,072, more than max_links=1,000"):
        mirad.solve(path, tolerance=0.2, max_links=1000, core="legacy", quiet=True)
