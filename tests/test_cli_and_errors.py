"""CLI end to end, bad input (clear message, non-zero exit, no traceback, nothing written)."""


import numpy as np
import pytest
import trimesh

import mirad
from conftest import run_cli, SCENES

CORNELL = SCENES / "cornell-box" / "scene.xml"




def test_cli_solve_writes_ply_that_trimesh_reads(tmp_path):
    out = tmp_path / "cornell.ply"
    res = run_cli("solve", CORNELL, "--tolerance", "0.1", "-o", out, "--quiet")
    assert res.returncode == 0, res.stderr
    mesh = trimesh.load(out, process=False)
    colors = mesh.visual.vertex_colors
    assert len(mesh.faces) == mirad.load_scene(CORNELL).triangle_count
    assert colors.shape[1] == 4 and colors[:, :3].max() > 0
    assert "radiosity_r" in mesh.metadata["_ply_raw"]["vertex"]["data"].dtype.names


def test_cli_info_reports_features():
    res = run_cli("info", CORNELL)
    assert res.returncode == 0, res.stderr
    assert "channels solved: 3" in res.stdout and "area (triangles)" in res.stdout
    assert "clustering='auto'): off (36 patches" in res.stdout        # small scene: all pairs


def _write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return path


BAD_SCENES = {
    "syntax.xml": ('<scene version="3.0.0"><shape type="rectangle" id="a"></scene>', "XML syntax"),
    "plugin.xml": ('<scene version="3.0.0"><shape type="teapot" id="a"/></scene>', "plugin"),
    "missing.xml": ('<scene version="3.0.0"><shape type="ply" id="m"><string name="filename" '
                    'value="nothere.ply"/></shape></scene>', "referenced file exists"),
    "rho.xml": ('<scene version="3.0.0"><shape type="rectangle" id="wall"><bsdf type="diffuse">'
                '<rgb name="reflectance" value="1.3"/></bsdf><emitter type="area"/></shape></scene>',
                "between 0 and 1"),
    "dark.xml": ('<scene version="3.0.0"><shape type="rectangle" id="wall"/></scene>', "no light"),
}


@pytest.mark.parametrize("name", sorted(BAD_SCENES))
def test_bad_scenes_give_one_clear_message(tmp_path, name):
    text, hint = BAD_SCENES[name]
    path = _write(tmp_path, name, text)
    with pytest.raises(mirad.SceneError, match=hint):
        mirad.load_scene(path)
    out = tmp_path / "out.ply"
    res = run_cli("solve", path, "-o", out, "--quiet")
    assert res.returncode != 0
    assert "Traceback" not in res.stderr and hint in res.stderr and name in res.stderr
    assert not out.exists() and not list(tmp_path.glob(".out.ply*"))


def test_missing_file_and_bad_output_folder(tmp_path):
    res = run_cli("solve", tmp_path / "nope.xml", "-o", tmp_path / "x.ply")
    assert res.returncode != 0 and "does not exist" in res.stderr and "Traceback" not in res.stderr
    res = run_cli("solve", CORNELL, "-o", tmp_path / "no" / "dir" / "x.ply")
    assert res.returncode != 0 and "does not exist" in res.stderr


def test_nan_vertices_name_the_file(tmp_path):
    verts = np.array([[0, 0, 0], [1, 0, np.nan], [0, 1, 0]], np.float32)
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
              "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n")
    body = verts.tobytes() + np.uint8(3).tobytes() + np.array([0, 1, 2], np.int32).tobytes()
    (tmp_path / "nan.ply").write_bytes(header.encode() + body)
    path = _write(tmp_path, "nan.xml", '<scene version="3.0.0"><shape type="ply" id="leaf">'
                  '<string name="filename" value="nan.ply"/><emitter type="area"/></shape></scene>')
    with pytest.raises(mirad.SceneError, match="nan.ply.*re-export"):
        mirad.load_scene(path)


def test_zero_area_triangles_are_dropped_and_counted():
    scene = {"type": "scene",
             "light": {"type": "rectangle", "emitter": {"type": "area"}},
             "mesh": {"type": "ply", "filename": str(SCENES / "closed-form" / "degenerate.ply")}}
    loaded = mirad.load_scene(scene)
    assert loaded.dropped_triangles == 1
    assert loaded.features["dropped_zero_area_triangles"] == 1


@pytest.mark.parametrize("options, word", [({"tolerance": 0}, "tolerance"), ({"tolerance": 1.5}, "tolerance"),
                                           ({"samples_per_link": 0}, "samples_per_link"),
                                           ({"tolerence": 0.1}, "tolerence")])
def test_bad_settings_name_the_parameter(options, word):
    with pytest.raises(mirad.SettingsError, match=word):
        mirad.solve(CORNELL, **options)


def test_npz_round_trip_and_fingerprint_check(tmp_path, cornell):
    sol = mirad.solve(cornell, tolerance=0.1)
    path = sol.save(tmp_path / "sol.npz")
    back = mirad.load_solution(path, scene=cornell)
    assert np.array_equal(back.triangle_radiosity, sol.triangle_radiosity)
    other = mirad.load_scene(SCENES / "closed-form" / "furnace.xml")
    with pytest.raises(mirad.SolutionMismatch, match="fingerprint"):
        mirad.load_solution(path, scene=other)
