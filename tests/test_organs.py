"""Per-organ output: connected components, face groups of PLY/OBJ files, the organ table, ``mirad export --organs``."""

import csv
import warnings

import numpy as np
import pytest

import mirad
from conftest import run_cli
from mirad import export, organs
from mirad.errors import SceneError, SettingsError

#: Organ sums against shape and scene totals: the same numbers added in another order.
SUM_REL = 1e-9
#: Where the plant lies, far enough from the origin (> 100 diagonals) that mirad re-centres it.
FAR = np.array([2048.0, 32.0, 2.0])
#: Every position below is a multiple of 1/8 m, exact in float32 near FAR; centroids are means.
POSITION_ABS = 1e-6

# Two separated squares in one mesh, 2 triangles each, facing +z: side 0.25 at x = 0 and side 0.5
# at x = 1 (relative to FAR), after a zero-area face that mirad drops (so file faces and mirad's
# triangles are numbered differently). Face 3 (in square B) has organ 7, the others organ 5, so
# groups cross components.
SQUARE_VERTICES = np.array([[-0.125, -0.125, 0], [0.125, -0.125, 0], [0.125, 0.125, 0], [-0.125, 0.125, 0],
                            [0.75, -0.25, 0], [1.25, -0.25, 0], [1.25, 0.25, 0], [0.75, 0.25, 0]]) + FAR
SQUARE_FACES = np.array([[0, 0, 1], [0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
SQUARE_ORGAN = np.array([9, 5, 5, 7, 5])
SQUARE_WEIGHT = np.array([0.5, 1.5, 2.5, 3.5, 4.5])
SQUARE_AREA = (0.0625, 0.25)
SQUARE_CENTROID = (FAR, FAR + [1.0, 0, 0])

# An OBJ of a triangle (no group), a quad in group "blade" and a triangle in group "stem", beside
# the squares: the triangle and the quad share an edge (one piece of area 0.375), the stem stands apart.
OBJ_VERTICES = np.array([[1.5, 0, 0], [2, 0, 0], [2, 0.5, 0], [1.5, 0.5, 0], [3, 0, 0], [3.5, 0, 0], [3, 0.5, 0],
                         [1.75, -0.5, 0]]) + FAR
OBJ_TEXT = ("# made in the test\n" + "".join(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in OBJ_VERTICES)
            + "f 1 8 2\ng blade\nf 1 2 3 4\no stem\nf 5 6 7\n")
OBJ_GROUP = ["obj", "blade", "blade", "stem"]          # per triangle Mitsuba makes (shape id first)
#: Centre of the floor, a 4 m square facing +z under the plant.
FLOOR = FAR + [1.5, 0.25, -0.5]


def ply_bytes(vertices, faces, face_props, *, ascii=False) -> bytes:
    """A PLY file with float x, y, z and extra scalar face properties {name: (ply type, values)}."""
    head = ["ply", f"format {'ascii' if ascii else 'binary_little_endian'} 1.0", "comment organs test",
            f"element vertex {len(vertices)}", "property float x", "property float y", "property float z",
            f"element face {len(faces)}", "property list uchar int vertex_indices"]
    head += [f"property {kind} {name}" for name, (kind, _) in face_props.items()]
    head = ("\n".join(head + ["end_header"]) + "\n").encode()
    numpy_type = {"int": "<i4", "uchar": "u1", "ushort": "<u2", "float": "<f4"}
    if ascii:
        lines = [" ".join(f"{x:.9g}" for x in v) for v in vertices]
        for f, face in enumerate(faces):
            extra = [str(values[f]) for _, values in face_props.values()]
            lines.append(" ".join(["3", *map(str, face), *extra]))
        return head + ("\n".join(lines) + "\n").encode()
    fields = [("n", "u1"), ("i", "<i4", (3,))] + [(name, numpy_type[kind]) for name, (kind, _) in face_props.items()]
    rows = np.zeros(len(faces), fields)
    rows["n"], rows["i"] = 3, faces
    for name, (_, values) in face_props.items():
        rows[name] = values
    return head + np.asarray(vertices, "<f4").tobytes() + rows.tobytes()


def scene_xml(folder, *, ascii=False, props=None) -> str:
    """plant.ply (squares), plant.obj and a grey floor under a constant sky; returns the XML path."""
    props = props if props is not None else {"organ": ("int", SQUARE_ORGAN), "weight": ("float", SQUARE_WEIGHT)}
    (folder / "plant.ply").write_bytes(ply_bytes(SQUARE_VERTICES, SQUARE_FACES, props, ascii=ascii))
    (folder / "plant.obj").write_text(OBJ_TEXT)
    xml = folder / "scene.xml"
    xml.write_text(f"""<scene version="3.0.0">
  <emitter type="constant"><rgb name="radiance" value="1.0"/></emitter>
  <shape type="ply" id="squares"><string name="filename" value="plant.ply"/>
    <bsdf type="twosided"><bsdf type="diffuse"><rgb name="reflectance" value="0.2, 0.3, 0.4"/></bsdf></bsdf></shape>
  <shape type="obj" id="obj"><string name="filename" value="plant.obj"/>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.25"/></bsdf></shape>
  <shape type="rectangle" id="floor">
    <transform name="to_world"><scale value="2"/><translate x="{FLOOR[0]}" y="{FLOOR[1]}" z="{FLOOR[2]}"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf></shape>
</scene>
""")
    return str(xml)


def load(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")          # far from the origin: a float32 precision warning
        return mirad.load_scene(path)


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    folder = tmp_path_factory.mktemp("plant")
    scene = load(scene_xml(folder))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sol = mirad.solve(scene, tolerance=0.1, quiet=True)
    return folder, scene, sol


def naive_components(faces, positions_key):
    """Union-find over <= 20 triangles, corners joined by their position key."""
    parent = list(range(len(faces)))

    def find(i):
        while parent[i] != i:
            i = parent[i]
        return i

    for a in range(len(faces)):
        for b in range(a):
            if {positions_key[v] for v in faces[a]} & {positions_key[v] for v in faces[b]}:
                parent[find(a)] = find(b)
    return [find(i) for i in range(len(faces))]


# ------------------------------------------------------------------------------------------
# Components
# ------------------------------------------------------------------------------------------

def test_components_match_a_naive_union_find_and_ignore_vertex_indexing():
    rng = np.random.default_rng(3)
    # shape 0: a strip of 4 triangles, a lone triangle; shape 1: two triangles touching at one
    # corner, the first triangle of shape 0 again, two triangles touching at their last corners
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [2, 0, 0], [2, 1, 0],
                  [5, 5, 0], [6, 5, 0], [5, 6, 0],
                  [9, 0, 0], [10, 0, 0], [9, 1, 0], [8, -1, 0], [8, 0, 0],
                  [0, 9, 0], [1, 9, 0], [1, 10, 0], [2, 11, 0], [1, 11, 0]], float)
    faces = np.array([[0, 1, 2], [1, 3, 2], [1, 4, 3], [4, 5, 3], [6, 7, 8], [9, 10, 11], [12, 9, 13],
                      [0, 1, 2], [14, 15, 16], [17, 18, 16]])
    shape = np.array([0, 0, 0, 0, 0, 1, 1, 1, 1, 1])
    comp, comp_shape, index = organs.triangle_components(v, faces, shape)
    key = [tuple(p) for p in v]
    naive = naive_components(faces[:5], key), naive_components(faces[5:], key)
    for s, tris in ((0, np.arange(5)), (1, np.arange(5, 10))):
        expected = naive[s]
        same = np.equal.outer(expected, expected)
        assert np.array_equal(np.equal.outer(comp[tris], comp[tris]), same)
        assert np.all(comp_shape[comp[tris]] == s)
    assert comp.tolist() == [0, 0, 0, 0, 1, 2, 2, 3, 4, 4]     # by shape, then by first triangle
    assert comp_shape.tolist() == [0, 0, 1, 1, 1] and index.tolist() == [0, 1, 0, 1, 2]
    # a triangle soup (every triangle its own vertices, shuffled) gives the same pieces
    soup = v[faces].reshape(-1, 3)
    perm = rng.permutation(len(soup))
    inverse = np.argsort(perm)
    soup_comp, _, _ = organs.triangle_components(soup[perm], inverse[np.arange(len(soup)).reshape(-1, 3)], shape)
    assert np.array_equal(soup_comp, comp)


def test_two_separated_squares_are_two_components_with_their_areas_and_centroids(plant):
    _, scene, sol = plant
    assert np.linalg.norm(scene.origin) > 100         # solved moved; the table is in the user's frame
    table = export.organ_table(sol, by="component")
    rows = np.flatnonzero(table["shape_id"] == "squares")
    assert table["component"][rows].tolist() == [0, 1]
    assert table["triangles"][rows].tolist() == [2, 2]
    assert np.allclose(table["area"][rows], SQUARE_AREA, rtol=1e-12)
    assert np.allclose(table["centroid"][rows], SQUARE_CENTROID, rtol=0, atol=POSITION_ABS)
    obj = np.flatnonzero(table["shape_id"] == "obj")
    assert table["triangles"][obj].tolist() == [3, 1]
    assert np.allclose(table["area"][obj], [0.375, 0.125], rtol=1e-12)
    floor = np.flatnonzero(table["shape_id"] == "floor")
    assert np.allclose(table["centroid"][floor], [FLOOR], rtol=0, atol=POSITION_ABS)


# ------------------------------------------------------------------------------------------
# Face groups
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("ascii", [False, True])
def test_ply_face_property_reproduces_the_grouping(tmp_path, ascii):
    scene = load(scene_xml(tmp_path, ascii=ascii))
    info = organs.read_ply_faces(tmp_path / "plant.ply")
    assert info["face"]["organ"].tolist() == SQUARE_ORGAN.tolist()
    assert info["face_types"]["organ"].kind == "i" and info["face_types"]["weight"].kind == "f"
    assert np.array_equal(info["faces"], SQUARE_FACES)
    group, group_shape, name = organs.triangle_groups(scene, property="organ")
    ids = scene.shape_ids
    labels = [(ids[group_shape[g]], str(name[g])) for g in group]
    sq, ob, fl = (np.flatnonzero(scene.tri_shape == ids.index(s)) for s in ("squares", "obj", "floor"))
    assert scene.tri_face[sq].tolist() == [1, 2, 3, 4]            # the zero-area face 0 is dropped
    assert [labels[t] for t in sq] == [("squares", str(v)) for v in SQUARE_ORGAN[scene.tri_face[sq]]]
    assert [labels[t] for t in ob] == [("obj", g) for g in OBJ_GROUP]
    assert {labels[t] for t in fl} == {("floor", "floor")}
    assert len(name) == 2 + 3 + 1                   # organs 5 and 7 (9 was dropped); obj, blade, stem; the floor


def test_obj_groups_follow_the_last_g_or_o_line():
    text = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nv 2 2 0\nf 1 2 3\ng  a   b \r\nf 1 2 3 4 5\n  o\nf 1 2 3\ngx\nf 3 2 1\n"
    import tempfile

    with tempfile.NamedTemporaryFile(suffix=".obj") as handle:
        handle.write(text)
        handle.flush()
        info = organs.read_obj_groups(handle.name)
    assert info["names"] == ["a b", "default"]              # "gx" is not a group line
    assert info["group"].tolist() == [-1, 0, 0, 0, 1, 1]    # a pentagon is 3 triangles


# ------------------------------------------------------------------------------------------
# The organ table
# ------------------------------------------------------------------------------------------

def test_organ_sums_equal_shape_and_scene_totals(plant):
    _, scene, sol = plant
    summary = export.shape_summary(sol)
    triangles = export.triangle_table(sol)
    tables = {by: export.organ_table(sol, by=by, property="organ" if by == "group" else None)
              for by in export.ORGAN_KINDS}
    assert np.all(summary["absorbed"].sum(0) > 0)
    for by, table in tables.items():
        assert table["triangles"].sum() == len(sol.faces)
        for s in range(len(sol.shape_ids)):
            rows = table["shape"] == s
            assert np.allclose(table["absorbed"][rows].sum(0), summary["absorbed"][s], rtol=SUM_REL, atol=0), by
            assert np.allclose(table["area"][rows].sum(), summary["area"][s], rtol=SUM_REL), by
        incident = ((triangles["irradiance"] + triangles["back_irradiance"]) * triangles["area"][:, None]).sum(0)
        assert np.allclose(table["incident"].sum(0), incident, rtol=SUM_REL), by
        assert np.allclose(table["absorbed"].sum(0), triangles["absorbed"].sum(0), rtol=SUM_REL), by
        mean = (table["mean_irradiance"] + table["mean_back_irradiance"]) * table["area"][:, None]
        assert np.allclose(table["incident"], mean, rtol=1e-9), by
    shape_table = tables["shape"]
    assert np.allclose(shape_table["mean_radiosity"], summary["mean_radiosity"], rtol=1e-12)
    # one-sided obj and floor with a grey albedo: absorbed = (1 - rho) * incident, organ by organ
    for sid, rho in (("obj", 0.25), ("floor", 0.5)):
        rows = tables["component"]["shape_id"] == sid
        assert np.allclose(tables["component"]["absorbed"][rows], (1 - rho) * tables["component"]["incident"][rows],
                           rtol=1e-9)


def test_group_rows_against_a_naive_loop_over_triangles(plant):
    _, scene, sol = plant
    table = export.organ_table(sol, by="group", property="organ")
    tri = export.triangle_table(sol)
    expected = {}
    s = sol.shape_ids.index("squares")
    for t in range(len(sol.faces)):                                # <= 20 triangles
        if tri["shape"][t] == s:
            key = str(SQUARE_ORGAN[scene.tri_face[t]])
            expected[key] = expected.get(key, 0) + tri["absorbed"][t]
    rows = np.flatnonzero(table["shape"] == s)
    assert table["group"][rows].tolist() == ["5", "7"]
    for r in rows:
        assert np.allclose(table["absorbed"][r], expected[table["group"][r]], rtol=1e-12)
    assert table["triangles"][rows].tolist() == [3, 1]


def test_both_sides_of_a_two_sided_square_count(plant):
    _, _, sol = plant
    table = export.organ_table(sol, by="component")
    rows = table["shape_id"] == "squares"
    assert np.all(table["mean_back_irradiance"][rows] > 0)        # the floor lights the undersides
    h = table["mean_irradiance"][rows] + table["mean_back_irradiance"][rows]
    rho = np.array([0.2, 0.3, 0.4])
    assert np.allclose(table["absorbed"][rows], (1 - rho) * h * table["area"][rows, None], rtol=1e-6)  # float32 rho


def test_csv_and_npz_round_trip(plant, tmp_path):
    _, _, sol = plant
    table = export.organ_table(sol, by="group", property="organ")
    export.write_organ_table(sol, tmp_path / "o.csv", by="group", property="organ")
    with open(tmp_path / "o.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == len(table["shape"])
    assert [r["group"] for r in rows] == table["group"].tolist()
    assert [r["shape_id"] for r in rows] == table["shape_id"].tolist()
    assert [int(r["triangles"]) for r in rows] == table["triangles"].tolist()
    absorbed = np.array([[float(r[f"absorbed_{c}"]) for c in "rgb"] for r in rows])
    assert np.allclose(absorbed, table["absorbed"], rtol=1e-8, atol=0)
    header = (tmp_path / "o.csv").read_text().splitlines()[0].split(",")
    centroid = np.loadtxt(tmp_path / "o.csv", delimiter=",", skiprows=1,
                          usecols=[header.index(f"centroid_{a}") for a in "xyz"])
    assert np.allclose(centroid, table["centroid"], rtol=1e-8, atol=0)
    export.write_organ_table(sol, tmp_path / "o.npz", by="component")
    with np.load(tmp_path / "o.npz", allow_pickle=False) as saved:
        again = export.organ_table(sol, by="component")
        assert sorted(saved.files) == sorted(again)
        for key, values in again.items():
            assert np.array_equal(saved[key], values), key


# ------------------------------------------------------------------------------------------
# Refusals
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, error, words", [
    ({"by": "leaves"}, SettingsError, ["by='leaves'", "component, group, shape"]),
    ({"by": "component", "property": "organ"}, SettingsError, ["only applies to organs by group"]),
    ({"by": "group"}, SettingsError, ["plant.ply", "'squares'", "'organ'", "--groups-property organ"]),
    ({"by": "group", "property": "organs"}, SettingsError, ["'organs'", "plant.ply", "organ"]),
    ({"by": "group", "property": "weight"}, SettingsError, ["plant.ply", "'weight'", "float32, not an integer"]),
    ({"by": "group", "property": "vertex_indices"}, SettingsError, ["'vertex_indices' is a list"]),
])
def test_bad_organ_options_are_refused_with_the_fix(plant, kwargs, error, words):
    _, _, sol = plant
    with pytest.raises(error) as caught:
        export.organ_table(sol, **kwargs)
    for word in words:
        assert word in str(caught.value)


def test_a_mesh_file_gone_or_changed_since_loading_is_refused(tmp_path):
    path = scene_xml(tmp_path)
    scene = load(path)
    ply = tmp_path / "plant.ply"
    props = {"organ": ("int", SQUARE_ORGAN)}
    # faces in another order: same count, not the triangles Mitsuba loaded
    ply.write_bytes(ply_bytes(SQUARE_VERTICES, SQUARE_FACES[[0, 3, 4, 1, 2]], props))
    with pytest.raises(SceneError, match="not the ones Mitsuba loaded"):
        organs.triangle_groups(scene, property="organ")
    ply.write_bytes(ply_bytes(SQUARE_VERTICES, SQUARE_FACES[:4], {"organ": ("int", SQUARE_ORGAN[:4])}))
    with pytest.raises(SceneError, match=r"plant.ply' \(shape 'squares'\) has 4 triangles but Mitsuba loaded 5"):
        organs.triangle_groups(scene, property="organ")
    ply.write_bytes(b"ply\nformat ascii 1.0\nend_header\n")
    with pytest.raises(SceneError, match="plant.ply' \\(shape 'squares'\\) cannot be read"):
        organs.triangle_groups(scene, property="organ")
    ply.unlink()
    with pytest.raises(SceneError, match="cannot be read again"):
        organs.triangle_groups(scene, property="organ")
    ply.write_bytes(ply_bytes(SQUARE_VERTICES, SQUARE_FACES, props))
    assert len(organs.triangle_groups(scene, property="organ")[2]) == 6       # restored: read again
    (tmp_path / "plant.obj").write_text(OBJ_TEXT.replace("f 5 6 7\n", ""))
    with pytest.raises(SceneError, match=r"plant.obj' \(shape 'obj'\) has 3 triangles but Mitsuba loaded 4"):
        organs.triangle_groups(scene, property="organ")


def test_a_mesh_of_an_mi_scene_has_no_known_file(plant):
    import mitsuba as mi

    folder, _, _ = plant
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = mirad.load_scene(mi.load_file(str(folder / "scene.xml"), optimize=False))
    assert scene.shape_files == [None] * len(scene.shape_ids)
    with pytest.raises(SceneError, match="cannot tell which mesh file"):
        organs.triangle_groups(scene, property="organ")
    comp, _, _ = organs.triangle_components(scene.vertices, scene.faces, scene.tri_shape)
    assert comp.max() + 1 == 2 + 2 + 1


# ------------------------------------------------------------------------------------------
# CLI
# ------------------------------------------------------------------------------------------

def test_cli_export_organs_from_a_saved_solution(plant, tmp_path):
    folder, _, sol = plant
    saved = sol.save(tmp_path / "sol.npz")
    out = tmp_path / "organs.csv"
    res = run_cli("export", folder / "scene.xml", "--solution", saved, "--organs", out, "--organs-by", "group",
                  "--groups-property", "organ", "--quiet")
    assert res.returncode == 0, res.stderr
    table = export.organ_table(sol, by="group", property="organ")
    with open(out, newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert [r["group"] for r in rows] == table["group"].tolist()
    incident = np.array([[float(r[f"incident_{c}"]) for c in "rgb"] for r in rows])
    assert np.allclose(incident, table["incident"], rtol=1e-8, atol=0)


@pytest.mark.parametrize("args, words", [
    (("--organs", "{tmp}/o.csv", "--organs-by", "leaves"), ["--organs-by leaves", "component"]),
    (("--organs", "{tmp}/o.csv", "--organs-by", "group", "--groups-property", "organs"), ["'organs'", "plant.ply"]),
    (("--organs", "{tmp}/o.csv", "--organs-by", "group"), ["--groups-property organ"]),
    (("--organs", "{tmp}/o.txt"), ["must end in"]),
    (("-o", "{tmp}/t.csv", "--organs-by", "shape"), ["--organs-by needs --organs"]),
])
def test_cli_bad_organ_options_give_one_line_and_write_nothing(plant, tmp_path, args, words):
    folder, _, _ = plant
    out = tmp_path / "out"
    out.mkdir()
    res = run_cli("export", folder / "scene.xml", "--tolerance", 0.1, *[a.format(tmp=out) for a in args])
    assert res.returncode == 2 and "Traceback" not in res.stderr
    errors = [line for line in res.stderr.splitlines() if line.startswith("mirad: error:")]
    assert len(errors) == 1, res.stderr
    for word in words:
        assert word in errors[0]
    assert not list(out.iterdir())
