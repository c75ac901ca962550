"""Exports: PLY, per-triangle and per-shape tables, lightmaps, ``mirad export``."""

import csv

import numpy as np
import pytest
import trimesh

import mirad
from conftest import run_cli, CLOSED_FORM_REL, SCENES
from mirad import export
from mirad.files import read_exr

CORNELL = SCENES / "cornell-box" / "scene.xml"
FURNACE = SCENES / "closed-form" / "furnace.xml"




@pytest.fixture(scope="module")
def sol():
    return mirad.solve(CORNELL, tolerance=0.05)


def test_ply_round_trip_with_trimesh(tmp_path, sol):
    path = export.write_ply(sol, tmp_path / "c.ply")
    mesh = trimesh.load(path, process=False)
    assert np.array_equal(mesh.faces, sol.faces)
    assert np.allclose(mesh.vertices, sol.vertices, atol=1e-6)
    data = mesh.metadata["_ply_raw"]["vertex"]["data"]
    for c, name in enumerate("rgb"):
        assert np.allclose(data[f"radiosity_{name}"], sol.vertex_radiosity[:, c], rtol=1e-6)
        assert data[f"irradiance_{name}"].dtype == np.float32
    assert mesh.visual.vertex_colors.dtype == np.uint8 and mesh.visual.vertex_colors[:, :3].max() > 0


def test_triangle_table_csv_and_npz(tmp_path, sol):
    export.write_table(sol, tmp_path / "t.csv")
    with open(tmp_path / "t.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == len(sol.triangle_area)
    area = np.array([float(r["area"]) for r in rows])
    assert np.allclose(area, sol.triangle_area, rtol=1e-6)
    assert [r["shape_id"] for r in rows] == [sol.shape_ids[s] for s in sol.triangle_shape]
    b = np.array([[float(r[f"radiosity_{c}"]) for c in "rgb"] for r in rows])
    assert np.allclose(b, sol.triangle_radiosity, rtol=1e-6)
    absorbed = np.array([[float(r[f"absorbed_{c}"]) for c in "rgb"] for r in rows])
    rho = sol.triangle_reflectance
    naive = np.array([[(1 - rho[t, c]) * sol.triangle_irradiance[t, c] * sol.triangle_area[t] for c in range(3)]
                      for t in range(len(rows))])                 # one-sided scene: front only
    assert np.allclose(absorbed, naive, rtol=1e-6, atol=1e-12)
    export.write_table(sol, tmp_path / "t.npz")
    with np.load(tmp_path / "t.npz") as data:
        assert np.allclose(data["absorbed"], absorbed, rtol=1e-6, atol=1e-12)
        assert list(data["shape_summary_shape_id"]) == sol.shape_ids


def test_shape_summary(sol):
    summary = shape_summary = export.shape_summary(sol)
    table = export.triangle_table(sol)
    for s, sid in enumerate(sol.shape_ids):
        assert np.allclose(summary["mean_radiosity"][s], sol.shape_radiosity(sid), rtol=1e-9)
        assert np.allclose(shape_summary["absorbed"][s], table["absorbed"][table["shape"] == s].sum(0))
    assert np.isclose(summary["area"].sum(), sol.triangle_area.sum())


def test_closed_scene_absorbs_what_it_emits():
    """In the closed furnace every watt emitted is absorbed: sum (1 - rho) H A = sum E A."""
    sol = mirad.solve(FURNACE, tolerance=0.1)
    summary = export.shape_summary(sol)
    emitted = (sol.triangle_emission * sol.triangle_area[:, None]).sum(0)
    assert np.allclose(summary["absorbed"].sum(0), emitted, rtol=CLOSED_FORM_REL)


def test_two_sided_leaf_absorbs_on_both_sides():
    """A two-sided grey leaf between two lights absorbs (1 - rho) (H_front + H_back) A."""
    import mitsuba as mi

    T = mi.ScalarTransform4f
    scene = {"type": "scene",
             "leaf": {"type": "rectangle", "to_world": T().scale(0.1),
                      "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.3}}}},
             "above": {"type": "point", "position": [0, 0, 1.0], "intensity": {"type": "rgb", "value": 4.0}},
             "below": {"type": "point", "position": [0, 0, -2.0], "intensity": {"type": "rgb", "value": 4.0}}}
    s = mirad.solve(scene, tolerance=0.1)
    table = export.triangle_table(s)
    area = s.triangle_area.sum()
    # small leaf: H ~ I / d^2 on each side
    expected = 0.7 * (4.0 / 1.0 + 4.0 / 4.0) * area
    assert np.allclose(table["absorbed"].sum(0), expected, rtol=0.03)
    assert np.all(table["back_irradiance"] > 0)


def test_lightmap_of_a_quad_averages_to_its_triangles(sol):
    maps = export.bake_lightmaps(sol, resolution=64)
    for sid in ("floor", "back", "red-wall"):    # rectangles: uv covers [0, 1]^2 uniformly
        s = sol.shape_ids.index(sid)
        mask = sol.triangle_shape == s
        area = sol.triangle_area[mask][:, None]
        expected = (sol.triangle_radiosity[mask] * area).sum(0) / area.sum()
        assert maps[sid].shape == (64, 64, 3)
        assert np.allclose(maps[sid].mean(axis=(0, 1)), expected, rtol=0.01)


def test_dilation_fills_rings_around_islands_without_black():
    image = np.zeros((9, 9, 1))
    filled = np.zeros((9, 9), bool)
    image[3:6, 3:6] = 2.0
    filled[3:6, 3:6] = True
    out = export.dilate_islands(image, filled, 1)
    assert np.all(out[2:7, 2:7] == 2.0)          # one ring, same value: bilinear lookups see no black
    assert np.all(out[0] == 0) and np.all(out[:, 0] == 0)
    assert np.all(export.dilate_islands(image, filled, 8) == 2.0)


def test_cli_export_with_saved_solution(tmp_path, sol):
    saved = sol.save(tmp_path / "sol.npz")
    maps = tmp_path / "maps"
    maps.mkdir()
    res = run_cli("export", CORNELL, "--solution", saved, "-o", tmp_path / "t.csv", "-o", tmp_path / "m.ply",
                  "--shapes", tmp_path / "s.csv", "--lightmaps", maps, "--lightmap-res", 16, "--quiet")
    assert res.returncode == 0, res.stderr
    rows = np.loadtxt(tmp_path / "t.csv", delimiter=",", skiprows=1, usecols=(4, 5, 6))
    assert np.allclose(rows, sol.triangle_radiosity, rtol=1e-6)   # the saved solution, not a new solve
    assert len(trimesh.load(tmp_path / "m.ply", process=False).faces) == len(sol.faces)
    assert (tmp_path / "s.csv").read_text().splitlines()[0].startswith("shape_id,triangles,area,mean_radiosity_r")
    channels = read_exr(maps / "floor.exr")
    assert sorted(channels) == ["B", "G", "R"] and channels["R"].shape == (16, 16)
    assert sorted(p.stem for p in maps.glob("*.exr")) == sorted(sol.shape_ids)


@pytest.mark.parametrize("args, hint", [
    (("-o", "{tmp}/t.txt"), "must end in"),
    (("-o", "{tmp}/missing/t.csv"), "does not exist"),
    (("--lightmaps", "{tmp}/nodir"), "does not exist"),
    ((), "nothing to export"),
])
def test_cli_export_bad_output_writes_nothing(tmp_path, args, hint):
    args = [a.format(tmp=tmp_path) for a in args]
    res = run_cli("export", CORNELL, "--tolerance", 0.1, *args)
    assert res.returncode != 0 and hint in res.stderr and "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert not [p for p in tmp_path.rglob("*") if p.is_file()]
