"""Output files: atomic, umask and mode kept, errors name the file; unique lightmap names; probe CSVs."""

from __future__ import annotations

import errno
import os
import stat

import numpy as np
import pytest

import mirad
from conftest import SCENES, run_cli
from mirad import export
from mirad.errors import OutputError, SettingsError
from mirad.files import WRITTEN, atomic_write, display_colors, srgb8

CORNELL = SCENES / "cornell-box" / "scene.xml"


def _mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def test_new_files_honour_the_umask_and_overwrites_keep_the_mode(tmp_path):
    old = os.umask(0o022)
    try:
        atomic_write(tmp_path / "a.txt", lambda h: h.write(b"1"))
        assert _mode(tmp_path / "a.txt") == 0o644
        os.umask(0o007)
        atomic_write(tmp_path / "b.txt", lambda h: h.write(b"1"))
        assert _mode(tmp_path / "b.txt") == 0o660
        os.chmod(tmp_path / "a.txt", 0o640)
        atomic_write(tmp_path / "a.txt", lambda h: h.write(b"2"))
        assert _mode(tmp_path / "a.txt") == 0o640 and (tmp_path / "a.txt").read_bytes() == b"2"
    finally:
        os.umask(old)
    assert WRITTEN[-1] == tmp_path / "a.txt"


@pytest.mark.parametrize("error", [KeyboardInterrupt(), OSError(errno.ENOSPC, "No space left on device")])
def test_an_interrupted_or_failed_write_leaves_nothing_and_names_the_file(tmp_path, error):
    (tmp_path / "keep.bin").write_bytes(b"old")

    def writer(handle):
        handle.write(b"half")
        raise error

    expected = KeyboardInterrupt if isinstance(error, KeyboardInterrupt) else OutputError
    with pytest.raises(expected) as info:
        atomic_write(tmp_path / "keep.bin", writer)
    if expected is OutputError:
        assert "keep.bin" in str(info.value) and "disk is full" in str(info.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.bin"]       # no .part left
    assert (tmp_path / "keep.bin").read_bytes() == b"old"


def test_display_colours_ignore_emitters_when_asked():
    b = np.array([[1.0, 1.0, 1.0]] * 90 + [[1000.0, 1000.0, 1000.0]] * 10)   # a light in view: 10 %
    lit = np.zeros(100, bool)
    lit[90:] = True
    assert display_colors(b)[0, 0] < 40                      # the light sets the exposure: dark walls
    assert display_colors(b, exclude=lit)[0, 0] == 255       # walls at their 99th percentile: white
    assert np.array_equal(display_colors(b, exclude=lit)[:, 3], np.full(100, 255))
    assert srgb8(np.array([0.0, 0.0031308 / 2, 1.0]))[2] == 255


def test_lightmap_names_are_unique_across_unsafe_characters_and_case():
    stems = export.lightmap_names(["wall 1", "wall_1", "Wall_1", "a/b", "..", "x"])
    assert len(set(s.lower() for s in stems.values())) == 6
    assert stems["wall 1"] == "wall_1" and stems["wall_1"] == "wall_1~2" and stems["x"] == "x"
    assert all("/" not in s and not s.startswith(".") for s in stems.values())


def test_probe_csv_with_bom_reads_and_binary_is_refused(tmp_path):
    good = tmp_path / "excel.csv"
    good.write_bytes("x,y,z,nx,ny,nz\r\n0,0,0,0,1,0\r\n".encode("utf-8-sig"))
    points, normals = export.read_points(good)
    assert points.shape == (1, 3) and normals[0, 1] == 1.0
    binary = tmp_path / "points.npz"
    binary.write_bytes(b"PK\x03\x04\x00\x00\xff\xfe")
    with pytest.raises(SettingsError, match="not a text CSV"):
        export.read_points(binary)


def test_cli_checks_every_output_before_solving(tmp_path):
    res = run_cli("solve", CORNELL, "--tolerance", "0.2", "-o", tmp_path / "sol.npz",
                  "--stats", tmp_path / "missing" / "stats.json")
    assert res.returncode == 2 and "missing" in res.stderr and "Traceback" not in res.stderr
    assert list(tmp_path.iterdir()) == []                    # nothing solved, nothing written


def test_cuda_variant_without_a_gpu_is_one_line(tmp_path):
    import mitsuba as mi

    if mi.variant().startswith("cuda"):                      # mirad picks CUDA where there is a GPU
        pytest.skip("this machine has a GPU")
    res = run_cli("info", CORNELL, "--variant", "cuda_ad_rgb")
    assert res.returncode == 2, res.stderr
    assert res.stderr.count("\n") == 1 and "GPU" in res.stderr and "llvm_ad_rgb" in res.stderr


def test_refined_ply_holds_the_leaves_and_their_radiosity(tmp_path):
    import trimesh

    sol = mirad.solve(CORNELL, tolerance=0.2)
    path = export.write_ply(sol, tmp_path / "refined.ply", mesh="refined")
    mesh = trimesh.load(path, process=False)
    front = sol.leaf_side == 0
    assert len(mesh.faces) == front.sum()
    area = mesh.area_faces
    assert np.isclose(area.sum(), sol.leaf_area[front].sum(), rtol=1e-5)
    b = np.asarray(mesh.metadata["_ply_raw"]["vertex"]["data"]["radiosity_r"])[mesh.faces[:, 0]]
    assert np.allclose(b, sol.leaf_radiosity[front, 0], rtol=1e-6)   # no shadow textures: flat per leaf
    table = export.triangle_table(sol)
    assert np.array_equal(table["triangle_in_shape"][table["shape"] == 1],
                          np.arange((table["shape"] == 1).sum()))
