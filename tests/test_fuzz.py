"""Fuzz the scene loader (issue 18): corrupted mesh files, mirrored and offset transforms, every
Mitsuba BSDF type. Each input must give either a clear ``SceneError`` naming the file or shape (and
exit 2 from the CLI, no traceback, nothing written) or a scene whose solution agrees with the
unperturbed one / Mitsuba's path tracer. Small scenes and few examples: seconds, not minutes."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

import mirad
import mitsuba as mi
from mirad.errors import SceneError

from conftest import run_cli

T = mi.ScalarTransform4f
FUZZ = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def _mesh_bytes(kind: str) -> bytes:
    import trimesh

    box = trimesh.creation.box()
    if kind == "ply":
        return trimesh.exchange.ply.export_ply(box, encoding="ascii")
    return trimesh.exchange.obj.export_obj(box).encode()


def _scene_xml(folder, mesh_name: str, kind: str):
    xml = folder / "scene.xml"
    xml.write_text(f'<scene version="3.0.0"><shape type="{kind}" id="part"><string name="filename" '
                   f'value="{mesh_name}"/><emitter type="area"/></shape></scene>')
    return xml


def _load_or_refuse(xml, mesh_name):
    """Load; a refusal must be a SceneError naming the mesh file or the shape."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            scene = mirad.load_scene(xml)
    except SceneError as exc:
        text = str(exc)
        assert "\n" not in text and (mesh_name in text or "'part'" in text), text
        return None
    # loaded: then it is sound
    assert np.all(np.isfinite(scene.vertices))
    assert scene.faces.min() >= 0 and scene.faces.max() < len(scene.vertices)
    assert np.all(scene.tri_area > 0)
    return scene


@pytest.mark.parametrize("kind", ["ply", "obj"])
@FUZZ
@given(data=st.data())
def test_corrupted_mesh_files_load_soundly_or_are_refused_naming_the_file(tmp_path_factory, kind, data):
    good = _mesh_bytes(kind)
    how = data.draw(st.sampled_from(["truncate", "garbage", "flip bytes", "bad index"]))
    if how == "truncate":
        body = good[: data.draw(st.integers(0, len(good) - 1))]
    elif how == "garbage":
        body = data.draw(st.binary(min_size=1, max_size=400))
    elif how == "flip bytes":
        raw = bytearray(good)
        for pos in data.draw(st.lists(st.integers(0, len(raw) - 1), min_size=1, max_size=6)):
            raw[pos] = data.draw(st.integers(0, 255))
        body = bytes(raw)
    else:  # a face index past the vertex list
        text = good.decode()
        bad = data.draw(st.integers(9, 10 ** 6))
        if kind == "ply":
            lines = text.splitlines()
            row = next(i for i, ln in enumerate(lines) if ln.startswith("3 "))
            lines[row] = f"3 0 1 {bad}"
            body = ("\n".join(lines) + "\n").encode()
        else:
            body = (text + f"f 1 2 {bad}\n").encode()
    folder = tmp_path_factory.mktemp("fuzz")
    (folder / f"mesh.{kind}").write_bytes(body)
    scene = _load_or_refuse(_scene_xml(folder, f"mesh.{kind}", kind), f"mesh.{kind}")
    if how == "bad index":
        assert scene is None                        # never a silent load with a face dropped


def test_cli_refuses_a_corrupt_mesh_with_exit_2_no_traceback_and_no_output(tmp_path):
    (tmp_path / "mesh.obj").write_bytes(_mesh_bytes("obj")[:-3])      # cut off mid face line
    xml = _scene_xml(tmp_path, "mesh.obj", "obj")
    out = tmp_path / "out.ply"
    result = run_cli("solve", xml, "-o", out)
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr and "mesh.obj" in result.stderr
    assert result.stderr.strip().count("\n") == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mesh.obj", "scene.xml"]


# ------------------------------------------------------------------------------------------
# Mirrored and offset transforms: the solution does not change
# ------------------------------------------------------------------------------------------

def _room(floor_xf, light_xf, offset):
    t = T().translate(list(offset))
    diffuse = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.6}}
    return {"type": "scene",
            "floor": {"type": "rectangle", "id": "floor", "to_world": t @ floor_xf, "bsdf": diffuse},
            "wall": {"type": "rectangle", "id": "wall", "bsdf": diffuse,
                     "to_world": t @ T().translate([0, 1, 1]).rotate([1, 0, 0], 90)},
            "light": {"type": "rectangle", "id": "light", "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}},
                      "to_world": t @ T().translate([0, 0, 2]).rotate([1, 0, 0], 180) @ light_xf}}


@pytest.fixture(scope="module")
def plain_room():
    sol = mirad.solve(mirad.load_scene(_room(T(), T(), (0, 0, 0))), tolerance=0.05)
    return {sid: sol.shape_radiosity(sid) for sid in ("floor", "wall")}


signs = st.tuples(*[st.sampled_from([-1.0, 1.0])] * 2)
offsets = st.tuples(*[st.sampled_from([0.0, 3.0, -2e3, 1e5, -3e6])] * 3)


@settings(max_examples=8, deadline=None)
@given(floor=signs, light=signs, offset=offsets)
def test_mirrors_in_the_plane_and_offsets_leave_the_solution_unchanged(plain_room, floor, light, offset):
    """Mirroring a square within its plane maps it onto itself: Mitsuba lights it identically, so
    mirad must too (issue 18: B = 0 before); moving the whole scene must not change it either."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = mirad.load_scene(_room(T().scale([floor[0], floor[1], 1]), T().scale([light[0], light[1], 1]), offset))
        sol = mirad.solve(scene, tolerance=0.05)
    for sid, expected in plain_room.items():
        np.testing.assert_allclose(sol.shape_radiosity(sid), expected, rtol=0.02)


# ------------------------------------------------------------------------------------------
# Every Mitsuba BSDF type
# ------------------------------------------------------------------------------------------

_RGB = {"type": "rgb", "value": 0.5}
BSDFS = {
    "diffuse": {"type": "diffuse"}, "dielectric": {"type": "dielectric"},
    "thindielectric": {"type": "thindielectric"}, "roughdielectric": {"type": "roughdielectric"},
    "conductor": {"type": "conductor"}, "roughconductor": {"type": "roughconductor"},
    "plastic": {"type": "plastic"}, "roughplastic": {"type": "roughplastic"},
    "principled": {"type": "principled"}, "principledthin": {"type": "principledthin"},
    "hair": None, "measured": None, "pplastic": {"type": "pplastic"},
    "polarizer": None, "retarder": None, "circular": None,
    "twosided": {"type": "twosided", "bsdf": {"type": "diffuse"}},
    "blendbsdf": {"type": "blendbsdf", "weight": 0.4, "bsdf_0": {"type": "diffuse"}, "bsdf_1": {"type": "plastic"}},
    "mask": {"type": "mask", "opacity": 0.5, "bsdf": {"type": "diffuse", "reflectance": _RGB}},
    "null": {"type": "null"},
    "normalmap": None, "bumpmap": None,
}


@pytest.mark.parametrize("name", [k for k, v in BSDFS.items() if v is not None])
def test_every_bsdf_type_loads_with_energy_conserved_and_losses_said(name):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = mirad.load_scene({"type": "scene", "s": {"type": "rectangle", "id": "thing", "bsdf": BSDFS[name],
                                                          "emitter": {"type": "area"}}})
    for rho, tau in ((scene.tri_rho, scene.tri_transmittance), (scene.back_rho, scene.back_transmittance)):
        assert np.all((rho >= 0) & (tau >= 0)) and np.all(rho + tau <= 1.02)
    assert np.all(scene.tri_specular <= scene.tri_rho + 1e-9)
    lossy = scene.tri_transmittance.max() > 1e-3 or scene.tri_specular.max() > 1e-3
    said = [str(w.message) for w in caught if "shape 'thing'" in str(w.message)]
    assert bool(said) == bool(scene.approximations) and (not lossy or said)
    assert (scene.model_error() > 0) == (lossy and scene.tri_rho.max() > 0)
