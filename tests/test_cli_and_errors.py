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
    assert "solver core (core='hierarchical', the default)" in res.stdout
    assert "with core='legacy', clusters of patches as link sources (clustering='auto'): off (36 patches" \
        in res.stdout                                                   # small scene: all pairs


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
                                           ({"tolerence": 0.1}, "tolerence"),
                                           ({"error_shapes": " , "}, "error_shapes=' , ' names no shape"),
                                           ({"error_shapes": "wall-*"}, r"'wall-\*' matches none.*floor.*small-box"),
                                           ({"error_shapes": "floor", "core": "legacy"},
                                            "error_shapes='floor' runs on the hierarchical core only")])
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


# --- issue 7: more bad input, each through the CLI entry point (in process: no interpreter start-up) ---

def _ply(path, verts, normals=None):
    """One-triangle binary PLY, optionally with vertex normals."""
    props = "property float x\nproperty float y\nproperty float z\n"
    data = np.asarray(verts, np.float32)
    if normals is not None:
        props += "property float nx\nproperty float ny\nproperty float nz\n"
        data = np.hstack([data, np.asarray(normals, np.float32)])
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(data)}\n{props}element face 1\n"
              "property list uchar int vertex_indices\nend_header\n")
    path.write_bytes(header.encode() + data.tobytes() + np.uint8(3).tobytes() + np.array([0, 1, 2], np.int32).tobytes())


TRIANGLE = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
LAMP = '<shape type="rectangle" id="lamp"><emitter type="area"/></shape>'
PLY_SCENE = ('<scene version="3.0.0"><shape type="ply" id="leaf"><string name="filename" value="{}"/></shape>'
             + LAMP + '</scene>')
#: name -> (scene text, PLY (vertices, normals) or None, words the message must hold)
MORE_BAD = {
    "negative-rho.xml": ('<scene version="3.0.0"><shape type="rectangle" id="wall"><bsdf type="diffuse">'
                         '<rgb name="reflectance" value="-0.2"/></bsdf><emitter type="area"/></shape></scene>',
                         None, ["reflectance", "between 0 and 1"]),
    "negative-radiance.xml": ('<scene version="3.0.0"><shape type="rectangle" id="wall"><emitter type="area">'
                              '<rgb name="radiance" value="-1"/></emitter></shape>' + LAMP + '</scene>',
                              None, ["shape 'wall'", "radiance", "non-negative"]),
    "inf.xml": (PLY_SCENE.format("inf.ply"), ([[0, 0, 0], [1, 0, np.inf], [0, 1, 0]], None),
                ["inf.ply", "NaN or Inf", "re-export"]),
    "zero-normals.xml": (PLY_SCENE.format("zero-normals.ply"), (TRIANGLE, np.zeros((3, 3))),
                         ["shape 'leaf'", "degenerate vertex normals", "face_normals"]),
    "nan-normals.xml": (PLY_SCENE.format("nan-normals.ply"), (TRIANGLE, np.full((3, 3), np.nan)),
                        ["shape 'leaf'", "degenerate vertex normals", "face_normals"]),
}


@pytest.mark.parametrize("name", sorted(MORE_BAD))
def test_more_bad_scenes_name_shape_or_file_and_the_fix(tmp_path, capsys, name):
    from mirad.cli import main

    text, mesh, words = MORE_BAD[name]
    if mesh is not None:
        _ply(tmp_path / name.replace(".xml", ".ply"), *mesh)
    path = _write(tmp_path, name, text)
    out = tmp_path / "out.ply"
    assert main(["solve", str(path), "-o", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("mirad: error: ") and name in err and "Traceback" not in err
    for word in words:
        assert word in err
    assert not out.exists() and not list(tmp_path.glob(".out.ply*"))


@pytest.mark.parametrize("option, word", [(["--tolerance", "0"], "tolerance"), (["--tolerance", "1"], "tolerance"),
                                          (["--tolerance", "-0.1"], "tolerance"),
                                          (["--samples-per-link", "0"], "samples_per_link")])
def test_bad_cli_options_name_the_parameter_and_write_nothing(tmp_path, capsys, option, word):
    from mirad.cli import main

    out = tmp_path / "out.ply"
    assert main(["solve", str(CORNELL), "-o", str(out), "--quiet", *option]) == 2
    err = capsys.readouterr().err
    assert word in err and ("(0, 1)" in err or ">= 1" in err) and "Traceback" not in err
    assert not out.exists()


def test_error_shapes_that_match_nothing_are_refused_by_the_cli(tmp_path, capsys):
    from mirad.cli import main

    out = tmp_path / "out.ply"
    assert main(["solve", str(CORNELL), "-o", str(out), "--quiet", "--error-shapes", "floor,tabel"]) == 2
    err = capsys.readouterr().err
    assert "'tabel' matches none" in err and "large-box" in err and "Traceback" not in err
    assert not out.exists()
    # and one that matches solves over those shapes
    saved = tmp_path / "boxes.npz"
    assert main(["solve", str(CORNELL), "-o", str(saved), "--quiet", "--tolerance", "0.2", "--error-shapes", "*-box"]) == 0
    assert mirad.load_solution(saved).stats["error_shapes"] == ["large-box", "small-box"]


def test_output_in_a_file_or_onto_a_folder_is_refused_before_solving(tmp_path, capsys):
    from mirad.cli import main

    (tmp_path / "notes.txt").write_text("x")
    assert main(["solve", str(CORNELL), "-o", str(tmp_path / "notes.txt" / "out.ply"), "--quiet"]) == 2
    assert "is a file, not a folder" in capsys.readouterr().err
    (tmp_path / "sub.ply").mkdir()
    assert main(["solve", str(CORNELL), "-o", str(tmp_path / "sub.ply"), "--quiet"]) == 2
    assert "it is a folder" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt", "sub.ply"]


@pytest.mark.skipif(not hasattr(__import__("os"), "geteuid") or __import__("os").geteuid() == 0,
                    reason="root may write into read-only folders")
def test_output_in_an_unwritable_folder_is_refused(tmp_path, capsys):
    from mirad.cli import main

    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    assert main(["solve", str(CORNELL), "-o", str(locked / "out.ply"), "--quiet"]) == 2
    assert "not writable" in capsys.readouterr().err
    assert not list(locked.iterdir())


def test_a_shape_with_only_zero_area_triangles_is_named_in_one_warning(tmp_path, capsys):
    from mirad.cli import main

    _ply(tmp_path / "flat.ply", [[0, 0, 0], [1, 0, 0], [2, 0, 0]])
    path = _write(tmp_path, "flat.xml", PLY_SCENE.format("flat.ply"))
    assert main(["info", str(path)]) == 0
    err = capsys.readouterr().err
    assert err.count("mirad: warning:") == 1 and "shape 'leaf' has only zero-area triangles" in err


def test_ctrl_c_during_a_solve_leaves_no_file_and_a_clean_message(tmp_path):
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "out.ply"
    proc = subprocess.Popen([sys.executable, "-m", "mirad.cli", "solve", str(SCENES / "wall-pierce" / "scene.xml"),
                             "--tolerance", "0.01", "-o", str(out)], stderr=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True,
                            # a test run started in the background ('&' in a script) ignores SIGINT, and
                            # its children inherit that: Ctrl-C must mean what it means at a terminal
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.time() + 120
        seen = ""
        while "links=" not in seen and "elements=" not in seen and time.time() < deadline:     # the progress bar: refinement runs
            seen += proc.stderr.read1(4096) if hasattr(proc.stderr, "read1") else proc.stderr.read(1)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130
    assert "interrupted; no output was written" in err and "Traceback" not in seen + err
    assert not out.exists() and not list(tmp_path.iterdir())


@pytest.mark.parametrize("options, words", [
    ({"tolerance": "0.1"}, ["tolerance='0.1'", "must be a number"]),
    ({"tolerance": float("nan")}, ["tolerance=nan", "finite"]),
    ({"samples_per_link": 1.5}, ["samples_per_link=1.5", "integer"]),
    ({"quiet": "false"}, ["quiet='false'", "True or False"]),
    ({"samples_per_link": 10 ** 9}, ["samples_per_link=1000000000", "at most 65536"]),
])
def test_settings_of_the_wrong_type_or_size_name_the_option(options, words):
    with pytest.raises(mirad.SettingsError) as caught:
        mirad.solve(SCENES / "cornell-box" / "scene.xml", **options)
    assert all(w in str(caught.value) for w in words)


def test_cli_refuses_a_render_pass_memory_cannot_hold(tmp_path):
    # 1e9 samples per pixel failed inside Dr.Jit with a custom-operation error naming nothing
    result = run_cli("render", str(SCENES / "cornell-box" / "scene.xml"), "--spp", "1000000000", "--tolerance", "0.3",
                     "-o", str(tmp_path / "x.exr"))
    assert result.returncode == 2
    assert "spp=1000000000" in result.stderr and "Traceback" not in result.stderr
    assert not list(tmp_path.iterdir())


def test_cli_main_called_in_process_puts_back_the_handlers_it_changed(tmp_path, capsys):
    """main() turns SIGTERM into a clean exit and shows warnings in one line while a command runs;
    called from Python (a notebook, a test run) it must leave the process as it found it: a SIGTERM
    handler left behind turned a later timeout's SIGTERM into an exception in unrelated code."""
    import signal
    import warnings

    from mirad.cli import main

    before_sigterm, before_show = signal.getsignal(signal.SIGTERM), warnings.showwarning
    assert main(["info", str(CORNELL)]) == 0
    assert main(["solve", str(tmp_path / "missing.xml"), "-o", str(tmp_path / "out.ply"), "--quiet"]) == 2
    assert signal.getsignal(signal.SIGTERM) is before_sigterm
    assert warnings.showwarning is before_show
