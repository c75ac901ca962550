"""Scene loader on real-world input (issue 18): mirrored transforms, non-diffuse BSDFs, far-away
scenes, textures. Expected values come from Mitsuba's path tracer (``mirad.reference``), closed
forms or the input itself (a texture's exact mean)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import mirad
import mitsuba as mi
from mirad.reference import triangle_reference

T = mi.ScalarTransform4f
#: Mirrored against unmirrored, and mirad against the path tracer (its stderr at 4096 paths ~0.5 %).
REF_REL = 0.03


def _square(to_world, sid, *, rho=0.5, radiance=None, kind="rectangle", **extra):
    d = {"type": kind, "to_world": to_world, "id": sid,
         "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": rho}}, **extra}
    if radiance is not None:
        d["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": radiance}}
    return d


def _light_over_floor(floor_xf=T(), light_xf=T(), *, kind="rectangle", **floor_extra):
    """A unit-radiance square light 1 m above a floor facing it; ``*_xf`` act in the shapes' own frames."""
    down = T().translate([0, 0, 1]).rotate([1, 0, 0], 180)
    return {"type": "scene", "floor": _square(floor_xf, "floor", kind=kind, **floor_extra),
            "light": _square(down @ light_xf, "light", radiance=1.0)}


def _floor_radiosity(scene_dict, *, seed=1):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = mirad.load_scene(scene_dict)
        sol = mirad.solve(scene, tolerance=0.05)
    ref = triangle_reference(scene, samples_per_triangle=4096, seed=seed)
    return scene, sol.shape_radiosity("floor")[0], ref.shape_radiosity(scene, "floor")[0]


@pytest.fixture(scope="module")
def unmirrored():
    return _floor_radiosity(_light_over_floor())[1:]


@pytest.mark.parametrize("case", ["receiver", "light", "both", "disk receiver"])
def test_mirrored_shapes_are_lit_and_emit_on_mitsubas_side(case, unmirrored):
    """Negative-determinant transforms: mirad used the winding, Mitsuba the transformed normal, so a
    mirrored floor read B = 0 and a mirrored light lit nothing (issue 18); both now agree with the
    path tracer and with the unmirrored scene."""
    mirror = T().scale([-1, 1, 1])
    floor_xf, light_xf, kind = {
        "receiver": (mirror, T(), "rectangle"), "light": (T(), T().scale([1, -1, 1]), "rectangle"),
        "both": (mirror, mirror, "rectangle"), "disk receiver": (T().scale([-1, 1, 1]), T(), "disk"),
    }[case]
    scene, b, ref = _floor_radiosity(_light_over_floor(floor_xf, light_xf, kind=kind))
    assert ref > 0.3                                 # the path tracer lights it ...
    assert b == pytest.approx(ref, rel=REF_REL)      # ... and so does mirad
    if kind == "rectangle":
        assert b == pytest.approx(unmirrored[0], rel=REF_REL)
    assert scene.tri_emission[scene.tri_shape == scene.shape_index("light")].max() == pytest.approx(np.pi)


def test_mirrored_mesh_with_vertex_normals_follows_the_normals(tmp_path):
    """A PLY with vertex normals under a mirror: Mitsuba shades by the (transformed) normals, whose
    side the winding no longer gives; mirad's front must be the normals' side."""
    import trimesh

    box = trimesh.creation.box(extents=(2.0, 2.0, 0.2))
    path = tmp_path / "slab.ply"
    path.write_bytes(trimesh.exchange.ply.export_ply(box, vertex_normal=True))
    slab = {"type": "ply", "filename": str(path), "to_world": T().translate([0, 0, -0.1]).scale([-1, 1, 1]),
            "face_normals": False}
    scene_dict = _light_over_floor()
    scene_dict["floor"] = {**slab, "id": "floor",
                           "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}}}
    scene = mirad.load_scene(scene_dict)
    tris = scene.tri_shape == scene.shape_index("floor")
    normals = np.array(scene.mi_scene.shapes()[scene.shape_index("floor")].vertex_normals_buffer().numpy())
    shading = normals.reshape(-1, 3)[scene.faces[tris]].sum(axis=1)
    assert np.all(np.einsum("ij,ij->i", shading, scene.tri_normal[tris]) > 0)
    top = tris & (scene.tri_normal[:, 2] > 0.9)
    ref = triangle_reference(scene, samples_per_triangle=2048, seed=3, triangles=np.flatnonzero(top))
    assert ref.radiosity[:, 0].mean() > 0.3          # the top, lit in Mitsuba, is mirad's front


@pytest.mark.parametrize("kind", ["sphere", "cylinder", "disk"])
@pytest.mark.parametrize("mirror", [[-1, 1, 1], [1, 1, -1]])
def test_mirrored_curved_shapes_face_where_mitsuba_says(kind, mirror):
    """Each triangle's front normal agrees with Mitsuba's shading normal at its centroid."""
    scene = mirad.load_scene({"type": "scene", "s": {"type": kind, "to_world": T().scale(mirror),
                                                    "emitter": {"type": "area"}}})
    n, c = scene.tri_normal, scene.tri_vertices.mean(axis=1)
    o = c + 0.05 * n
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(o[:, i]) for i in range(3)]),
                   mi.Vector3f(*[mi.Float(-n[:, i]) for i in range(3)]))
    si = scene.mi_scene.ray_intersect(ray)
    sh = np.array(si.sh_frame.n.numpy()).reshape(3, -1).T
    hit = np.array(si.is_valid().numpy(), dtype=bool)
    assert hit.mean() > 0.95
    assert np.all(np.einsum("ij,ij->i", sh[hit], n[hit]) > 0)
