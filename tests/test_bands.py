"""Several wavebands in one solve (mirad/bands.py, docs/bands.md).

A band solve is a solve whose channels are the bands: it must give, band by band, what the same
scene gives with that band's values as grey reflectances and emitters (mirad's own solve, and
Mitsuba's path tracer on that grey scene), conserve energy band by band, weigh each non-area
emitter by its factor on the RGB mean of its emission, and refuse every table it cannot mean.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import mirad
import mitsuba as mi
from mirad import export
from mirad.bands import band_table, emitter_ids, read_band_table

from conftest import run_cli

#: The loader's warning about leaf transmission on the legacy core; these tests solve on the
#: hierarchical core, which carries it (docs/leaves.md).
pytestmark = pytest.mark.filterwarnings("ignore:.*transmits light")

T = mi.ScalarTransform4f

#: Per band: leaf front and back reflectance, leaf transmittance, floor reflectance, lamp and sun
#: factors (the scene's lamp radiance and sun irradiance are 1, so the factors are W/(m^2 sr), W/m^2).
BANDS = {"PAR": dict(front=0.08, back=0.12, tau=0.05, floor=0.15, lamp=1.0, sun=2.0),
         "NIR": dict(front=0.45, back=0.40, tau=0.45, floor=0.35, lamp=0.3, sun=1.2)}


def leaf(rho, tau) -> dict:
    return {"type": "leaf", "reflectance": rho, "transmittance": tau}


def garden(front=0.1, back=0.2, tau=0.1, floor=0.5, lamp=1.0, sun=1.0) -> dict:
    """A two-sided leaf (1 x 1 m, 0.5 m up) over a 3 x 3 m floor under a square lamp and a sun
    that the lamp does not shadow; with band values as arguments, the grey scene of that band."""
    return {"type": "scene",
            "blade": {"type": "rectangle", "to_world": T().translate([0, 0, 0.5]).scale(0.5),
                      "bsdf": {"type": "twosided", "allow_transmission": True,
                               "front": leaf(front, tau), "back": leaf(back, tau)}},
            "floor": {"type": "rectangle", "to_world": T().scale(1.5),
                      "bsdf": {"type": "diffuse", "reflectance": floor}},
            "lamp": {"type": "rectangle", "to_world": T().translate([0, 0, 1.5]).rotate([1, 0, 0], 180).scale(0.5),
                     "bsdf": {"type": "diffuse", "reflectance": 0.0}, "emitter": {"type": "area", "radiance": lamp}},
            "sun": {"type": "directional", "direction": [1.2, 0.5, -1], "irradiance": sun}}


def garden_rows() -> list:
    rows = []
    for band, v in BANDS.items():
        rows += [dict(band=band, id="blade", reflectance=v["front"], back_reflectance=v["back"], transmittance=v["tau"]),
                 dict(band=band, id="floor", reflectance=v["floor"]),
                 dict(band=band, id="lamp", reflectance=0.0, scale=v["lamp"]),
                 dict(band=band, id="sun", scale=v["sun"])]
    return rows


def load(scene):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return mirad.load_scene(scene)


@pytest.fixture(scope="module")
def garden_solve():
    scene = mirad.with_bands(load(garden()), garden_rows())
    return scene, mirad.solve(scene, tolerance=TOL, core="hierarchical")


TOL = 0.02


# ------------------------------------------------------------------------------------------
# The band scene
# ------------------------------------------------------------------------------------------

def test_band_scene_holds_the_tables_values_per_triangle_and_side():
    base = load(garden())
    scene = mirad.with_bands(base, garden_rows())
    assert scene.band_names == ["PAR", "NIR"] and scene.channels == 2 and not scene.grey
    blade, floor, lamp = (scene.tri_shape == scene.shape_index(s) for s in ("blade", "floor", "lamp"))
    for c, v in enumerate(BANDS.values()):
        np.testing.assert_array_equal(scene.tri_rho[blade, c], v["front"])
        np.testing.assert_array_equal(scene.back_rho[blade, c], v["back"])
        np.testing.assert_array_equal(scene.tri_transmittance[blade, c], v["tau"])
        np.testing.assert_array_equal(scene.back_transmittance[blade, c], v["tau"])
        np.testing.assert_array_equal(scene.tri_rho[floor, c], v["floor"])
        np.testing.assert_array_equal(scene.back_rho[floor, c], 0.0)                 # one-sided, as in the file
        np.testing.assert_allclose(scene.tri_emission[lamp, c], np.pi * v["lamp"], rtol=1e-6)   # E = pi L
        np.testing.assert_array_equal(scene.tri_emission[~lamp, c], 0.0)
    np.testing.assert_array_equal(scene.light_band_scale, [[2.0, 1.2]])
    # structure and geometry are the scene's own; the fingerprint tells the two apart
    assert scene.mi_scene is base.mi_scene and np.array_equal(scene.patch_tri, base.patch_tri)
    assert scene.fingerprint != base.fingerprint and base.band_names is None
    assert scene.fingerprint == mirad.with_bands(base, garden_rows()).fingerprint
    assert mirad.with_bands(base, garden_rows(), bands=["NIR"]).band_names == ["NIR"]


def test_direct_light_is_the_factor_times_the_emitters_rgb_mean_exactly():
    """A lone leaf under a sun of RGB irradiance (1, 2, 3) (mean 2) at normal incidence: in each band
    its top receives H = 2 x factor, its top's radiosity is rho H and its underside's tau H, exactly
    (the hierarchical core carries the transmitted light; nothing else is in the scene)."""
    scene = load({"type": "scene",
                  "blade": {"type": "rectangle", "bsdf": {"type": "twosided", "allow_transmission": True,
                                                          "front": leaf(0.1, 0.2), "back": leaf(0.3, 0.2)}},
                  "sun": {"type": "directional", "direction": [0, 0, -1],
                          "irradiance": {"type": "rgb", "value": [1.0, 2.0, 3.0]}}})
    factor = np.array([0.5, 3.0, 10.0])
    rho, back, tau = np.array([0.1, 0.4, 0.05]), np.array([0.2, 0.5, 0.05]), np.array([0.3, 0.5, 0.0])
    rows = [dict(band=b, id="blade", reflectance=rho[c], back_reflectance=back[c], transmittance=tau[c])
            for c, b in enumerate(("blue", "red", "far-red"))]
    rows += [dict(band=b, id="sun", scale=factor[c]) for c, b in enumerate(("blue", "red", "far-red"))]
    banded = mirad.with_bands(scene, rows)
    sol = mirad.solve(banded, tolerance=0.05, core="hierarchical")
    h = 2.0 * factor
    np.testing.assert_allclose(sol.triangle_irradiance, np.broadcast_to(h, (2, 3)), rtol=1e-6)
    np.testing.assert_allclose(sol.triangle_radiosity, np.broadcast_to(rho * h, (2, 3)), rtol=1e-6)
    np.testing.assert_allclose(sol.back_radiosity, np.broadcast_to(tau * h, (2, 3)), rtol=1e-6, atol=1e-12)
    absorbed = export.absorbed_power(sol, sol.triangle_irradiance, sol.back_irradiance).sum(0)
    np.testing.assert_allclose(absorbed, (1 - rho - tau) * h * 1.0 * 4.0, rtol=1e-6)   # a 2 x 2 m leaf
    assert sol.stats["bands"] == ["blue", "red", "far-red"]


# ------------------------------------------------------------------------------------------
# Band by band: the grey scene of each band, mirad's and Mitsuba's path tracer's
# ------------------------------------------------------------------------------------------

def relative_l1(a: np.ndarray, b: np.ndarray, area: np.ndarray, reflected: float) -> float:
    return float((area * np.abs(a - b)).sum() / area.sum() / reflected)


def test_each_band_is_the_grey_scene_of_that_band_solved_alone(garden_solve):
    """Per band, per-triangle radiosity (front and back) against a solve of the same geometry with the
    band's values as grey BSDFs and emitters: within the two solves' estimated errors added (each is
    within its estimate of the truth, so their difference within the sum). Measured (2 cores): PAR
    1.1 %, NIR 0.02 % of mean(B - E), against estimates of 1.5 + 1.7 % and 1.5 + 1.3 %."""
    scene, sol = garden_solve
    area = scene.tri_area
    for c, v in enumerate(BANDS.values()):
        grey = mirad.solve(load(garden(**v)), tolerance=TOL, core="hierarchical")
        reflected = float((area * (grey.triangle_radiosity[:, 0] - grey.triangle_emission[:, 0])).sum() / area.sum())
        budget = sol.stats["estimated_error"] + grey.stats["estimated_error"]
        for mine, theirs in ((sol.triangle_radiosity, grey.triangle_radiosity),
                             (sol.back_radiosity, grey.back_radiosity)):
            assert relative_l1(mine[:, c], theirs[:, 0], area, reflected) <= budget, (c, budget)
        # emission and the leaf's irradiance by band: the grey scene's, to the same estimate
        np.testing.assert_allclose(sol.triangle_emission[:, c], grey.triangle_emission[:, 0], rtol=1e-6)


def test_each_band_matches_mitsubas_path_tracer_on_its_grey_scene(garden_solve):
    """Per band, per-shape and side means of the band solve against Mitsuba's path tracer on the
    band's grey scene (the same leaf BSDF, that band's values): within 1.5 x the tolerance plus 3
    reference standard errors, as tests/test_leaf.py. Measured (8,192 paths per triangle side):
    PAR floor -0.1 %, leaf top +0.5 %, underside +2.0 %; NIR +0.1, +0.2, -0.2 %."""
    from mirad.reference import triangle_reference

    scene, sol = garden_solve
    area = scene.tri_area
    for c, v in enumerate(BANDS.values()):
        grey = load(garden(**v))
        for sid, side in (("floor", "front"), ("blade", "front"), ("blade", "back")):
            tris = np.flatnonzero(grey.tri_shape == grey.shape_index(sid))
            ref = triangle_reference(grey, samples_per_triangle=8192, seed=5 + c, triangles=tris, side=side)
            mine = (sol.back_radiosity if side == "back" else sol.triangle_radiosity)[tris, c]
            w = area[tris]
            mean, mean_ref = (w * mine).sum() / w.sum(), (w * ref.radiosity[:, 0]).sum() / w.sum()
            noise = np.sqrt((w ** 2 * ref.stderr[:, 0] ** 2).sum()) / w.sum()
            assert abs(mean - mean_ref) <= 1.5 * TOL * mean_ref + 3 * noise, (c, sid, side, mean, mean_ref, noise)


def test_rgb_solve_of_a_grey_scene_is_the_one_band_solve_of_its_values():
    """A one-band table holding a grey scene's own values gives the RGB solve's numbers to float
    rounding (both solve one channel: the same links, rays and direct samples)."""
    v = BANDS["NIR"]
    grey = load(garden(**v))
    rows = [r for r in garden_rows() if r["band"] == "NIR"]
    one = mirad.with_bands(load(garden()), rows)
    a = mirad.solve(grey, tolerance=0.05, core="hierarchical")
    b = mirad.solve(one, tolerance=0.05, core="hierarchical")
    assert b.channels == 1
    np.testing.assert_allclose(b.triangle_radiosity[:, 0], a.triangle_radiosity[:, 0], rtol=1e-6)
    np.testing.assert_allclose(b.back_radiosity[:, 0], a.back_radiosity[:, 0], rtol=1e-6)


def test_the_rgb_channels_as_three_bands_give_the_rgb_solve():
    """An RGB scene (coloured leaf, floor, lamp and sun) and the band table that holds its own values
    per channel (each emitter's factor its channel over its RGB mean): the same links and rays,
    and the same radiosity to float rounding (measured 4e-7 on scenes/plant-canopy, 2,300
    triangles)."""
    rgb = lambda v: {"type": "rgb", "value": v}                                       # noqa: E731
    front, back, tau = [0.1, 0.3, 0.05], [0.2, 0.25, 0.1], [0.05, 0.2, 0.4]
    floor, lamp, sun = [0.3, 0.2, 0.1], np.array([1.0, 0.8, 0.5]), np.array([2.0, 1.5, 1.0])
    d = garden()
    d["blade"]["bsdf"]["front"], d["blade"]["bsdf"]["back"] = leaf(rgb(front), rgb(tau)), leaf(rgb(back), rgb(tau))
    d["floor"]["bsdf"]["reflectance"] = rgb(floor)
    d["lamp"]["emitter"]["radiance"], d["sun"]["irradiance"] = rgb(lamp.tolist()), rgb(sun.tolist())
    scene = load(d)
    rows = []
    for c, band in enumerate("rgb"):
        rows += [dict(band=band, id="blade", reflectance=front[c], back_reflectance=back[c], transmittance=tau[c]),
                 dict(band=band, id="floor", reflectance=floor[c]),
                 dict(band=band, id="lamp", reflectance=0.0, scale=lamp[c] / lamp.mean()),
                 dict(band=band, id="sun", scale=sun[c] / sun.mean())]
    a = mirad.solve(scene, tolerance=0.02, core="hierarchical")
    b = mirad.solve(mirad.with_bands(scene, rows), tolerance=0.02, core="hierarchical")
    assert (a.stats["links"], a.stats["rays"]) == (b.stats["links"], b.stats["rays"])
    for x, y in ((a.triangle_radiosity, b.triangle_radiosity), (a.back_radiosity, b.back_radiosity),
                 (a.triangle_irradiance, b.triangle_irradiance)):
        np.testing.assert_allclose(y, x, rtol=1e-5, atol=1e-7 * float(x.max()))


# ------------------------------------------------------------------------------------------
# Energy, band by band
# ------------------------------------------------------------------------------------------

def closed_room() -> dict:
    """A closed 2 m cube (inward faces, the ceiling an area emitter of radiance 1), a point light of
    intensity 1 W/sr and a tilted translucent leaf inside: nothing escapes."""
    faces = {"floor": T().translate([0, 0, -1]), "ceiling": T().translate([0, 0, 1]).rotate([1, 0, 0], 180),
             "xp": T().translate([1, 0, 0]).rotate([0, 1, 0], -90), "xm": T().translate([-1, 0, 0]).rotate([0, 1, 0], 90),
             "yp": T().translate([0, 1, 0]).rotate([1, 0, 0], 90), "ym": T().translate([0, -1, 0]).rotate([1, 0, 0], -90)}
    d = {"type": "scene"}
    for sid, t in faces.items():
        d[sid] = {"type": "rectangle", "to_world": t, "bsdf": {"type": "diffuse", "reflectance": 0.5}}
    d["ceiling"]["emitter"] = {"type": "area", "radiance": 1.0}
    d["blade"] = {"type": "rectangle", "to_world": T().rotate([1, 0, 0], 30).scale(0.4),
                  "bsdf": {"type": "twosided", "allow_transmission": True,
                           "front": leaf(0.1, 0.2), "back": leaf(0.3, 0.2)}}
    d["bulb"] = {"type": "point", "position": [0.3, 0.2, 0.5], "intensity": 1.0}
    return d


def test_absorbed_equals_emitted_in_every_band_of_a_closed_room():
    """sum over triangles and sides of (1 - rho - tau) H A = sum A E + 4 pi I x factor, per band, within
    the solve's estimate times the reflected power (measured: -0.4 % and -0.3 % of it against an
    estimate of 2.8 % at tolerance 0.05)."""
    rows = []
    for band, (wall, lamp, bulb, front, back, tau) in {"PAR": (0.3, 0.5, 2.0, 0.08, 0.12, 0.05),
                                                        "NIR": (0.6, 0.2, 1.0, 0.45, 0.40, 0.45)}.items():
        rows += [dict(band=band, id="*", reflectance=wall), dict(band=band, id="ceiling", reflectance=wall, scale=lamp),
                 dict(band=band, id="blade", reflectance=front, back_reflectance=back, transmittance=tau),
                 dict(band=band, id="bulb", scale=bulb)]
    scene = mirad.with_bands(load(closed_room()), rows)
    sol = mirad.solve(scene, tolerance=0.05, core="hierarchical")
    area = scene.tri_area[:, None]
    absorbed = export.triangle_table(sol)["absorbed"].sum(0)
    emitted = (area * scene.tri_emission).sum(0) + 4 * np.pi * 1.0 * scene.light_band_scale[0]
    np.testing.assert_allclose(emitted, [4 * np.pi * 0.5 + 4 * np.pi * 2.0, 4 * np.pi * 0.2 + 4 * np.pi * 1.0])
    reflected = (area * (sol.triangle_radiosity - sol.triangle_emission + sol.back_radiosity)).sum(0)
    assert np.all(np.abs(absorbed - emitted) <= sol.stats["estimated_error"] * reflected), (absorbed, emitted)
    # the two bands differ by more than that: a mix-up of bands would not pass
    assert abs(absorbed[0] / emitted[0] - absorbed[1] / emitted[1]) < 0.01 and absorbed[0] > 2 * absorbed[1]


# ------------------------------------------------------------------------------------------
# Outputs per band
# ------------------------------------------------------------------------------------------

def test_tables_name_their_columns_by_band(garden_solve, tmp_path):
    scene, sol = garden_solve
    export.write_table(sol, tmp_path / "t.csv")
    export.write_table(sol, tmp_path / "t.npz")
    export.write_organ_table(sol, tmp_path / "o.csv", by="shape")
    export.write_shape_summary(sol, tmp_path / "s.csv")
    header = (tmp_path / "t.csv").read_text().splitlines()[0].split(",")
    for name in ("radiosity", "irradiance", "back_radiosity", "absorbed", "error"):
        assert [f"{name}_PAR", f"{name}_NIR"] == [h for h in header if h.rsplit("_", 1)[0] == name]
    assert not any(h.endswith(("_r", "_g", "_b")) for h in header)
    rows = np.genfromtxt(tmp_path / "t.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    table = export.triangle_table(sol)
    np.testing.assert_allclose(rows["absorbed_NIR"], table["absorbed"][:, 1], rtol=1e-8)
    with np.load(tmp_path / "t.npz") as data:
        assert list(data["bands"]) == ["PAR", "NIR"]
        np.testing.assert_array_equal(data["radiosity_PAR"], table["radiosity"][:, 0])
        np.testing.assert_array_equal(data["shape_summary_absorbed_NIR"], export.shape_summary(sol)["absorbed"][:, 1])
    organs = np.genfromtxt(tmp_path / "o.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    for c, band in enumerate(("PAR", "NIR")):      # per organ (shape) = the triangles' sum, per band
        per_shape = np.bincount(table["shape"], weights=table["absorbed"][:, c], minlength=len(sol.shape_ids))
        np.testing.assert_allclose(organs[f"absorbed_{band}"], per_shape, rtol=1e-8)
    assert "mean_radiosity_NIR" in (tmp_path / "s.csv").read_text().splitlines()[0]


def test_cli_solves_and_exports_in_bands(tmp_path):
    """``mirad export --bands``: the per-triangle and per-organ tables in bands, the same numbers as
    the API's; a saved band solution asks for its table again."""
    xml = tmp_path / "garden.xml"
    xml.write_text(GARDEN_XML)
    table = tmp_path / "bands.csv"
    table.write_text(GARDEN_CSV)
    res = run_cli("solve", xml, "--bands", table, "--core", "hierarchical", "--tolerance", "0.05", "-o",
                  tmp_path / "sol.npz", "--quiet")
    assert res.returncode == 0, res.stderr
    res = run_cli("export", xml, "--solution", tmp_path / "sol.npz", "--bands", table, "-o", tmp_path / "t.csv",
                  "--organs", tmp_path / "o.csv", "--quiet")
    assert res.returncode == 0, res.stderr
    sol = mirad.load_solution(tmp_path / "sol.npz", scene=mirad.with_bands(load(xml), table))
    rows = np.genfromtxt(tmp_path / "t.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    np.testing.assert_allclose(rows["absorbed_PAR"], export.triangle_table(sol)["absorbed"][:, 0], rtol=1e-8)
    assert "incident_NIR" in (tmp_path / "o.csv").read_text().splitlines()[0]
    res = run_cli("export", xml, "--solution", tmp_path / "sol.npz", "-o", tmp_path / "u.csv")
    assert res.returncode == 2 and "solved in bands PAR, NIR; give the band table" in res.stderr
    assert "Traceback" not in res.stderr and not (tmp_path / "u.csv").exists()


GARDEN_XML = """<scene version="3.0.0">
    <shape type="rectangle" id="blade">
        <transform name="to_world"><scale value="0.5"/><translate value="0, 0, 0.5"/></transform>
        <bsdf type="twosided">
            <boolean name="allow_transmission" value="true"/>
            <bsdf type="leaf"><float name="reflectance" value="0.1"/><float name="transmittance" value="0.1"/></bsdf>
            <bsdf type="leaf"><float name="reflectance" value="0.2"/><float name="transmittance" value="0.1"/></bsdf>
        </bsdf>
    </shape>
    <shape type="rectangle" id="floor">
        <transform name="to_world"><scale value="1.5"/></transform>
        <bsdf type="diffuse"><float name="reflectance" value="0.5"/></bsdf>
    </shape>
    <emitter type="directional" id="sun"><vector name="direction" value="1.2, 0.5, -1"/></emitter>
    <emitter type="constant"><float name="radiance" value="0.2"/></emitter>
</scene>
"""

#: Lines: 1 header, 2 comment, 3-6 PAR, 7-10 NIR. The sky has no id: it is emitter_1.
GARDEN_CSV = """band,id,reflectance,transmittance,back_reflectance,scale
# factors on the scene's sun (irradiance 1 W/m^2) and sky (radiance 0.2 W/(m^2 sr))
PAR,blade,0.08,0.05,0.1,
PAR,*,0.1,,,
PAR,sun,,,,400
PAR,emitter_1,,,,100
NIR,blade,0.45,0.45,0.4,
NIR,*,0.3,,,
NIR,sun,,,,350
NIR,emitter_1,,,,50
"""


# ------------------------------------------------------------------------------------------
# Refusals
# ------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def garden_file_scene(tmp_path_factory):
    path = tmp_path_factory.mktemp("bands") / "garden.xml"
    path.write_text(GARDEN_XML)
    return load(path)


def test_unnamed_emitters_are_named_by_their_place(garden_file_scene, tmp_path):
    assert emitter_ids(garden_file_scene) == ["sun", "emitter_1"]
    table = read_band_table(_write(tmp_path, GARDEN_CSV))
    assert table.bands == ["PAR", "NIR"] and list(table.line[:2]) == [3, 4]
    scene = mirad.with_bands(garden_file_scene, table)
    np.testing.assert_array_equal(scene.light_band_scale, [[400, 350], [100, 50]])


def _write(folder, text: str):
    path = folder / "bands.csv"
    path.write_text(text)
    return path


def _edit(line: int, new: str | None) -> str:
    """GARDEN_CSV with file line ``line`` replaced (None: removed)."""
    lines = GARDEN_CSV.splitlines()
    if new is None:
        del lines[line - 1]
    else:
        lines[line - 1] = new
    return "\n".join(lines) + "\n"


REFUSALS = [
    # unknown shape id, with a suggestion
    (_edit(3, "PAR,blad,0.08,0.05,0.1,"), r"line 3 \(band 'PAR'\): the scene has no shape or emitter 'blad' \(did "
                                          r"you mean 'blade'\?\).*ids are 'blade', 'floor', 'sun', 'emitter_1'"),
    # rho + tau > 1, front and back
    (_edit(7, "NIR,blade,0.6,0.45,0.4,"), r"line 7 \(band 'NIR', shape 'blade'\): reflectance 0\.6 \+ transmittance "
                                          r"0\.45 = 1\.05 > 1 breaks energy conservation; lower them"),
    (_edit(7, "NIR,blade,0.45,0.45,0.6,"), r"line 7 \(band 'NIR', shape 'blade'\): back reflectance 0\.6 \+ "
                                           r"transmittance 0\.45 = 1\.05 > 1"),
    # below 0
    (_edit(4, "PAR,*,-0.1,,,"), r"line 4 \(band 'PAR', id '\*'\): reflectance -0\.1 < 0; give a reflectance >= 0"),
    # missing values: a leaf's transmittance, a shape's reflectance, an emitter's scale
    (_edit(7, "NIR,blade,0.45,,0.4,"), r"line 7 \(band 'NIR', shape 'blade'\): the shape is a leaf and its "
                                       r"transmittance is missing; give it"),
    (_edit(8, "NIR,*,,,,"), r"line 8 \(band 'NIR', shape 'floor'\): the reflectance is missing"),
    (_edit(9, "NIR,sun,,,,"), r"line 9 \(band 'NIR', emitter 'sun'\): the scale is missing"),
    # a band the other rows have, missing for one shape (no default row) and for one emitter
    (_edit(8, None), r"shape 'floor' has no row for band 'NIR' and the band has no default row; add a row "
                     r"'NIR,floor,\.\.\.' or 'NIR,\*,\.\.\.'"),
    (_edit(8, None).replace("PAR,*,0.1,,,", "PAR,floor,0.1,,,"),
     r"shape 'floor' has rows for band\(s\) PAR \(line 4\) but none for band 'NIR', which other rows have; give "
     r"it a row 'NIR,floor,\.\.\.' or the band a default row 'NIR,\*,\.\.\.'"),
    (_edit(10, None), r"emitter 'emitter_1' \(ConstantBackgroundEmitter\) has no row for band 'NIR'; add a row "
                      r"'NIR,emitter_1,,,,SCALE'"),
    # values a shape cannot take
    (_edit(4, "PAR,floor,0.1,0.2,,") + "PAR,*,0.1,,,\n", r"line 4 \(band 'PAR', shape 'floor'\): transmittance 0\.2 "
                                                          r"on a shape whose BSDF is not a leaf"),
    (_edit(4, "PAR,floor,0.1,,0.2,") + "PAR,*,0.1,,,\n", r"shape 'floor'\): back_reflectance on a one-sided shape"),
    (_edit(4, "PAR,floor,0.1,,,5") + "PAR,*,0.1,,,\n", r"shape 'floor'\): a scale on a shape that emits no light"),
    (_edit(5, "PAR,sun,0.3,,,400"), r"line 5 \(band 'PAR', emitter 'sun'\): an emitter has no reflectance"),
    (_edit(4, "PAR,*,0.1,,,3"), r"line 4 \(band 'PAR', default row \*\): a default row cannot give a scale"),
    # form: duplicates, names, numbers, columns
    (GARDEN_CSV + "PAR,blade,0.1,0.1,,\n", r"line 11: band 'PAR', id 'blade' has a row already \(line 3\)"),
    (_edit(3, "P AR,blade,0.08,0.05,0.1,"), r"line 3: band name 'P AR' must start with a letter or digit"),
    (_edit(3, "par,blade,0.08,0.05,0.1,"), r"bands 'par' and 'PAR' differ only in case"),
    (_edit(3, "PAR,blade,high,0.05,0.1,"), r"line 3 \(band 'PAR', id 'blade'\): reflectance 'high' is not a number"),
    (_edit(3, "PAR,blade,nan,0.05,0.1,"), r"line 3 \(band 'PAR', id 'blade'\): reflectance nan is not a finite number"),
    (_edit(1, "band,id,reflectence,transmittance,back_reflectance,scale"),
     r"unknown column 'reflectence' \(did you mean 'reflectance'\?\)"),
    (_edit(1, "band,shape,reflectance,transmittance,back_reflectance,scale"), r"lacks column\(s\) id"),
    (_edit(3, "PAR,,0.08,0.05,0.1,"), r"line 3 \(band 'PAR'\): the id is empty"),
    (_edit(3, "PAR,blade,0.08,0.05,0.1,,7"), r"line 3: 7 cells but the header names 6 columns"),
    ("band,id,reflectance\n", r"has a header but no rows"),
]


@pytest.mark.parametrize("text, match", REFUSALS, ids=[f"refusal-{k}" for k in range(len(REFUSALS))])
def test_refusals_name_file_line_band_and_shape_and_the_fix(garden_file_scene, tmp_path, text, match):
    path = _write(tmp_path, text)
    with pytest.raises(mirad.BandTableError, match=match) as info:
        mirad.with_bands(garden_file_scene, path)
    assert isinstance(info.value, ValueError) and str(path) in str(info.value) and "\n" not in str(info.value)


def test_refusals_of_rows_given_in_code(garden_file_scene):
    good = [dict(band="PAR", id="*", reflectance=0.2, transmittance=0.1), dict(band="PAR", id="sun", scale=1),
            dict(band="PAR", id="emitter_1", scale=1)]
    assert mirad.with_bands(garden_file_scene, good).band_names == ["PAR"]
    with pytest.raises(mirad.BandTableError, match=r"band 'UV' is not in band table '<table>'; its bands are PAR"):
        mirad.with_bands(garden_file_scene, good, bands=["PAR", "UV"])
    with pytest.raises(mirad.BandTableError, match=r"<table>, row 1 \(band 'PAR', shape 'blade'\): reflectance 0\.95 "
                                                   r"\+ transmittance 0\.1 = 1\.05 > 1"):
        mirad.with_bands(garden_file_scene, [dict(good[0], reflectance=0.95)] + good[1:])
    with pytest.raises(mirad.BandTableError, match="not a dict"):
        band_table({"band": "PAR"})
    with pytest.raises(mirad.BandTableError, match="already has bands PAR"):
        mirad.with_bands(mirad.with_bands(garden_file_scene, good), good)


def test_cli_refusal_is_one_line_with_a_non_zero_exit(tmp_path):
    xml = tmp_path / "garden.xml"
    xml.write_text(GARDEN_XML)
    bad = tmp_path / "bad.csv"
    bad.write_text(_edit(7, "NIR,blade,0.6,0.45,0.4,"))
    res = run_cli("solve", xml, "--bands", bad, "-o", tmp_path / "x.npz")
    assert res.returncode == 2 and "Traceback" not in res.stderr
    errors = [line for line in res.stderr.strip().splitlines() if line.startswith("mirad: error:")]
    assert errors == [f"mirad: error: {bad}, line 7 (band 'NIR', shape 'blade'): reflectance 0.6 + transmittance "
                      "0.45 = 1.05 > 1 breaks energy conservation; lower them so that reflectance + transmittance "
                      "<= 1 (the rest is absorbed)"]
    assert not (tmp_path / "x.npz").exists()


def test_the_table_in_docs_bands_md_applies_as_documented(tmp_path):
    """The example table of docs/bands.md on a scene with its ids: a leaf shape, soil, a sun and a sky."""
    from conftest import ROOT

    text = (ROOT / "docs" / "bands.md").read_text()
    block = text.split("```csv\n", 1)[1].split("```", 1)[0]
    scene = load({"type": "scene",
                  "leaves": {"type": "rectangle", "to_world": T().translate([0, 0, 0.5]).scale(0.3),
                             "bsdf": {"type": "twosided", "allow_transmission": True,
                                      "front": leaf(0.1, 0.1), "back": leaf(0.1, 0.1)}},
                  "soil": {"type": "rectangle", "bsdf": {"type": "diffuse"}},
                  "sun": {"type": "directional", "direction": [0, 0, -1]},
                  "sky": {"type": "constant", "radiance": 1.0}})
    banded = mirad.with_bands(scene, _write(tmp_path, block))
    assert banded.band_names == ["PAR", "NIR"]
    leaves = banded.tri_shape == banded.shape_index("leaves")
    np.testing.assert_array_equal(banded.tri_rho[leaves][0], [0.08, 0.45])
    np.testing.assert_array_equal(banded.back_rho[leaves][0], [0.10, 0.40])
    np.testing.assert_array_equal(banded.tri_transmittance[leaves][0], [0.05, 0.45])
    np.testing.assert_array_equal(banded.tri_rho[~leaves][0], [0.10, 0.30])
    np.testing.assert_array_equal(banded.tri_transmittance[~leaves], 0.0)
    np.testing.assert_array_equal(banded.light_band_scale, [[400, 350], [40, 25]])
