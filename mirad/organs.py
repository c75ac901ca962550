"""Organs of a plant model: which organ each input triangle belongs to.

Three ways to cut a scene into organs, each a per-triangle index into a list of organs (the
tables per organ are in ``mirad.export.organ_table``):

- ``shape``: every shape is one organ.
- ``component``: the connected pieces of each shape's mesh (a leaf of a plant model), triangles
  joined where they share an edge or a corner. Corners are joined by position (welded on a grid
  of ``WELD`` times the scene diagonal), not by vertex index, so a mesh written as a triangle
  soup, or with its vertices split at UV seams, still comes out in one piece per leaf; two
  pieces that touch at a point are one component.
- ``group``: face groups written in the mesh files, read again from the files the scene names
  (``Scene.shape_files``): an integer face property of a PLY file (the user names it, e.g.
  ``organ``), or the ``g``/``o`` lines of an OBJ file (a face belongs to the group named by the
  last ``g`` or ``o`` line before it). Shapes without groups (analytic shapes, PLY files without
  the property, OBJ faces before any group line) count as one group named by the shape id.

The groups are matched to Mitsuba's triangles face by face, through ``Scene.tri_face`` (mirad
drops zero-area triangles; Mitsuba splits an OBJ polygon of n corners into n - 2 triangles).
Each file's triangle count is checked against Mitsuba's, and a PLY file's triangles against
Mitsuba's positions (the centroids must map by one affine transform, the shape's ``to_world``);
a file that does not match is refused, never guessed. No Python loop runs over triangles.
"""

from __future__ import annotations

import os

import numpy as np

from .arrays import scene_diagonal
from .errors import SceneError, SettingsError

__all__ = ["ORGAN_KINDS", "triangle_components", "triangle_groups", "read_ply_faces", "read_obj_groups"]

#: What an organ is: a connected piece of a shape's mesh, a face group of its file, or the shape.
ORGAN_KINDS = ("component", "group", "shape")

#: PLY scalar types (the PLY 1.0 names, their sized aliases and Mitsuba's extensions) as numpy types.
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8", "long": "i8", "ulong": "u8",
              "half": "f2"}
#: Names of the PLY face list that holds the corners (Mitsuba reads either).
_PLY_INDEX_NAMES = ("vertex_indices", "vertex_index")
#: Mesh classes Mitsuba reads from a PLY or OBJ file.
_FILE_MESHES = ("PLYMesh", "OBJMesh")
#: A PLY file matches Mitsuba's mesh when its triangle centroids map onto Mitsuba's within this
#: fraction of the mesh's size (float32 positions; a face out of order is off by a triangle or more).
MATCH = 1e-4


# ------------------------------------------------------------------------------------------
# Connected components
# ------------------------------------------------------------------------------------------

def triangle_components(vertices: np.ndarray, faces: np.ndarray, shape: np.ndarray) -> tuple:
    """Connected pieces of each shape's mesh: triangles sharing an edge or a corner position.

    Parameters
    ----------
    vertices : (V, 3) float, m          mesh vertices
    faces : (T, 3) int                  vertex indices of the triangles
    shape : (T,) int                    shape of each triangle; pieces never span two shapes

    Returns
    -------
    (component (T,) int, component_shape (K,) int, component_index (K,) int): the component of
    each triangle, numbered by shape and then by the first triangle of each component; the shape
    of each component and its index within that shape (0, 1, ... in the shape's face order).
    Corners closer than ``mirad.scene.WELD`` times the bounding-box diagonal are one point.

    >>> v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 0, 0], [6, 0, 0], [5, 1, 0.]])
    >>> comp, comp_shape, index = triangle_components(v, np.array([[0, 1, 2], [3, 4, 5]]), np.zeros(2, int))
    >>> comp.tolist(), comp_shape.tolist(), index.tolist()
    ([0, 1], [0, 0], [0, 1])
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from .scene import WELD

    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    shape = np.asarray(shape, np.int64)
    n_tri = len(faces)
    if n_tri == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
    # ---------------- weld corners by position, within each shape -----------------------------
    grid = np.round(vertices / (WELD * scene_diagonal(vertices))).astype(np.int64)
    _, weld = np.unique(grid, axis=0, return_inverse=True)
    weld = weld.reshape(-1)
    key = shape[:, None] * (int(weld.max()) + 1) + weld[faces]         # (T, 3): shape and welded point
    _, node = np.unique(key, return_inverse=True)
    node = node.reshape(n_tri, 3)
    # ---------------- components of the corner graph (two edges per triangle) ------------------
    n_node = int(node.max()) + 1
    rows = np.concatenate([node[:, 0], node[:, 1]])
    cols = np.concatenate([node[:, 1], node[:, 2]])
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(n_node, n_node))
    _, label = connected_components(graph, directed=False)
    label = label[node[:, 0]]
    # ---------------- number them by shape, then by first triangle ----------------------------
    _, first, inverse = np.unique(label, return_index=True, return_inverse=True)
    first_shape = shape[first]
    order = np.lexsort((first, first_shape))            # components sorted by (shape, first triangle)
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    component = rank[inverse.reshape(-1)]
    component_shape = first_shape[order]
    start = np.searchsorted(component_shape, component_shape, side="left")
    return component, component_shape, np.arange(len(order)) - start


# ------------------------------------------------------------------------------------------
# Face groups from the mesh files
# ------------------------------------------------------------------------------------------

def triangle_groups(scene, *, property: str | None = None) -> tuple:
    """Face groups of every input triangle of a scene, read again from its mesh files.

    Parameters
    ----------
    scene : mirad Scene                  loaded from a file or dict (``Scene.shape_files``)
    property : str or None               the integer PLY face property that numbers the groups
        (e.g. ``"organ"``). A PLY file without it is one group; a name no PLY file of the scene
        has is refused. None: PLY files give no groups, and a PLY file that has integer face
        properties is refused (mirad does not guess which of them numbers the organs).

    Returns
    -------
    (group (T,) int, group_shape (G,) int, group_name (G,) str): the group of each triangle
    (index into the groups), the shape of each group (index into ``shape_ids``) and its name:
    the PLY value as text (``"3"``), the OBJ group or object name, or the shape id for a shape
    without groups. Groups are numbered by shape, then by value (PLY) or first appearance (OBJ).

    Raises SettingsError for a property that is unknown, not an integer or not named where it
    is needed, and SceneError for a mesh file that cannot be read again or does not match the
    triangles Mitsuba loaded from it; each message names the file, its shape and the fix.
    """
    shapes = list(scene.mi_scene.shapes())
    ids = scene.shape_ids
    tri_shape = np.asarray(scene.tri_shape, np.int64)
    n_shape = len(ids)
    order = np.argsort(tri_shape, kind="stable")
    bounds = np.searchsorted(tri_shape[order], np.arange(n_shape + 1))
    # ---------------- read every mesh file once ------------------------------------------------
    files = list(scene.shape_files) or [None] * n_shape
    read = {}
    for s, (sid, shape) in enumerate(zip(ids, shapes)):           # one pass per shape, not per triangle
        if files[s] is None:
            if shape.class_name() in _FILE_MESHES and bounds[s + 1] > bounds[s]:
                raise SceneError(f"shape '{sid}' ({shape.class_name()}): mirad cannot tell which mesh file it was "
                                 "read from, so its face groups cannot be read (a shape without an id whose file "
                                 "name another unnamed shape shares, or a scene given as an mi.Scene); give the "
                                 "shape an id in the scene file and load it with mirad.load_scene(path), or "
                                 "count organs by component or shape")
            continue
        kind, path = files[s]
        if path not in read and kind in ("ply", "obj"):
            read[path] = read_ply_faces(path, shape_id=sid) if kind == "ply" else read_obj_groups(path, shape_id=sid)
    _check_property(scene, files, read, property)
    # ---------------- groups per shape ---------------------------------------------------------
    group = np.zeros(len(tri_shape), np.int64)
    group_shape, group_name = [], []
    for s, (sid, shape) in enumerate(zip(ids, shapes)):
        tris = order[bounds[s]:bounds[s + 1]]
        if not len(tris):
            continue
        names, local = [sid], np.zeros(len(tris), np.int64)
        kind, path = files[s] if files[s] is not None else (None, None)
        if kind == "ply" and property is not None and property in read[path]["face"]:
            info = read[path]
            _check_match(info, shape, sid, path)
            values = info["face"][property][scene.tri_face[tris]]
            unique, local = np.unique(values, return_inverse=True)
            names = [str(v) for v in unique.tolist()]               # one name per group
        elif kind == "obj" and read[path]["names"]:
            info = read[path]
            _check_count(len(info["group"]), shape, sid, path)
            labels = info["group"][scene.tri_face[tris]]              # -1: before any group line
            used, first, inverse = np.unique(labels, return_index=True, return_inverse=True)
            by_first = np.argsort(first, kind="stable")
            rank = np.empty(len(used), np.int64)
            rank[by_first] = np.arange(len(used))
            text = [sid if v < 0 else info["names"][v] for v in used[by_first].tolist()]
            canonical = {}
            for name in text:                                        # equal names are one group
                canonical.setdefault(name, len(canonical))
            names = list(canonical)
            local = np.array([canonical[name] for name in text], np.int64)[rank[inverse.reshape(-1)]]
        group[tris] = len(group_name) + local.reshape(-1)
        group_shape += [s] * len(names)
        group_name += names
    return group, np.asarray(group_shape, np.int64), np.asarray(group_name, dtype=str)


def _check_property(scene, files: list, read: dict, property: str | None) -> None:
    """Refuse an unknown or non-integer property, or integer face properties none names."""
    ids = scene.shape_ids
    plys = [(ids[s], f[1]) for s, f in enumerate(files) if f is not None and f[0] == "ply" and f[1] in read]
    if property is None:
        for sid, path in plys:
            extra = [name for name, kind in read[path]["face_types"].items() if kind.kind in "iu"]
            if extra:
                names = ", ".join(f"'{name}'" for name in extra)
                raise SettingsError(
                    f"mesh file '{path}' (shape '{sid}') has integer face propert{'y' if len(extra) == 1 else 'ies'} "
                    f"{names}; name the one that numbers the organs (--groups-property {extra[0]}, or "
                    f"property='{extra[0]}'), or count organs by component or shape")
        return
    having = [(sid, path) for sid, path in plys if property in read[path]["face_types"]
              or property in read[path]["list_properties"]]
    if not having:
        found = sorted({name for _, path in plys for name, kind in read[path]["face_types"].items()
                        if kind.kind in "iu"})
        where = (f"no PLY mesh file of the scene ({', '.join(repr(p) for _, p in plys[:3])}"
                 f"{', ...' if len(plys) > 3 else ''}) has a face property '{property}'" if plys
                 else f"the scene has no PLY mesh file, so there is no face property '{property}'")
        hint = (f"; their integer face properties are {', '.join(found)}" if found
                else "; they have no integer face property")
        raise SettingsError(f"groups property '{property}': {where}{hint if plys else ''}; name one of "
                            "those, or count organs by component or shape")
    for sid, path in having:
        if property in read[path]["list_properties"]:
            raise SettingsError(f"mesh file '{path}' (shape '{sid}'): face property '{property}' is a list, not "
                                "one integer per face; name an integer face property that numbers the organs")
        kind = read[path]["face_types"][property]
        if kind.kind not in "iu":
            raise SettingsError(f"mesh file '{path}' (shape '{sid}'): face property '{property}' is {kind.name}, "
                                "not an integer; write the organ numbers as an integer face property (int, "
                                "uint, short, uchar, ...) and name that one")


def _check_count(n_file: int, shape, sid: str, path: str) -> None:
    n_mitsuba = int(shape.face_count())
    if n_file != n_mitsuba:
        raise SceneError(f"mesh file '{path}' (shape '{sid}') has {n_file} triangles but Mitsuba loaded "
                         f"{n_mitsuba} from it, so its face groups cannot be matched to the triangles (the file "
                         "changed since the scene was loaded, or Mitsuba split or dropped faces); re-export it "
                         "as a triangle mesh and load the scene again, or count organs by component or shape")


def _check_match(info: dict, shape, sid: str, path: str) -> None:
    """A PLY file's triangles, in order, are Mitsuba's: same count, centroids one affine map apart."""
    _check_count(len(info["faces"]), shape, sid, path)
    mine = info["vertices"][info["faces"]].mean(1)
    theirs = np.array(shape.vertex_positions_buffer().numpy(), np.float64).reshape(-1, 3)
    theirs = theirs[np.array(shape.faces_buffer().numpy(), np.int64).reshape(-1, 3)].mean(1)
    lhs = np.column_stack([mine, np.ones(len(mine))])
    fit, *_ = np.linalg.lstsq(lhs, theirs, rcond=None)
    off = float(np.abs(lhs @ fit - theirs).max()) if len(mine) else 0.0
    if off > MATCH * scene_diagonal(theirs):
        raise SceneError(f"mesh file '{path}' (shape '{sid}'): its triangles are not the ones Mitsuba loaded "
                         f"from it in the same order (off by {off:.3g} m), so its face groups cannot be matched "
                         "(the file changed since the scene was loaded?); load the scene again, or count organs "
                         "by component or shape")


# ------------------------------------------------------------------------------------------
# Readers
# ------------------------------------------------------------------------------------------

def _read_bytes(path: str, shape_id: str) -> bytes:
    try:
        with open(path, "rb") as handle:
            return handle.read()
    except OSError as exc:
        raise SceneError(f"mesh file '{path}' (shape '{shape_id}') cannot be read again for its face groups "
                         f"({exc.strerror or exc}); keep the scene's mesh files where the scene names them, or "
                         "count organs by component or shape") from None


def _unreadable(path: str, shape_id: str, why: str) -> SceneError:
    return SceneError(f"mesh file '{path}' (shape '{shape_id}') cannot be read for its face groups ({why}); "
                      "re-export it as a triangle mesh, or count organs by component or shape")


def read_ply_faces(path, *, shape_id: str = "") -> dict:
    """The faces of a PLY file as Mitsuba reads them (triangles, in file order), with their properties.

    Returns a dict: ``vertices`` (V, 3) float and ``faces`` (F, 3) int of the file; ``face``
    {name: (F,) array} of every scalar face property (its PLY type: integers stay integers);
    ``face_types`` {name: numpy dtype}; ``list_properties`` the names of the face's list
    properties. ASCII and binary (either byte order) files; every list must hold 3 items, as in
    Mitsuba's reader. SceneError naming the file if it cannot be read or parsed.
    """
    path = os.fspath(path)
    data = _read_bytes(path, shape_id)
    end = data.find(b"end_header")
    body = data.find(b"\n", end) + 1 if end >= 0 else 0
    if not data.startswith(b"ply") or end < 0 or body == 0:
        raise _unreadable(path, shape_id, "no PLY header")
    fmt, elements = None, []
    try:
        for line in data[:end].decode("latin-1").splitlines():         # header lines
            tok = line.split()
            if not tok:
                continue
            if tok[0] == "format":
                fmt = tok[1]
            elif tok[0] == "element":
                elements.append((tok[1], int(tok[2]), []))
            elif tok[0] == "property" and tok[1] == "list":
                elements[-1][2].append((tok[4], _PLY_TYPES[tok[2]], _PLY_TYPES[tok[3]]))
            elif tok[0] == "property":
                elements[-1][2].append((tok[2], None, _PLY_TYPES[tok[1]]))
    except (IndexError, KeyError, ValueError) as exc:
        raise _unreadable(path, shape_id, f"header: {type(exc).__name__} {exc}") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise _unreadable(path, shape_id, f"format {fmt!r}")
    names = [e[0] for e in elements]
    if "vertex" not in names or "face" not in names:
        raise _unreadable(path, shape_id, "no vertex or face element")
    try:
        records = _ply_records(data, body, fmt, elements[: names.index("face") + 1])
    except (ValueError, TypeError, OverflowError) as exc:
        raise _unreadable(path, shape_id, f"{type(exc).__name__}: {exc}") from None
    vertex, face = records["vertex"], records["face"]
    index = next((n for n in _PLY_INDEX_NAMES if n in face.dtype.names), None)
    if index is None or not all(c in vertex.dtype.names for c in "xyz"):
        raise _unreadable(path, shape_id, "no vertex_indices face list or no x, y, z vertex coordinates")
    props = elements[names.index("face")][2]
    return {
        "vertices": np.column_stack([vertex[c].astype(np.float64) for c in "xyz"]),
        "faces": np.asarray(face[index], np.int64).reshape(-1, 3),
        "face": {name: np.asarray(face[name]) for name, count, _ in props if count is None},
        "face_types": {name: np.dtype(kind) for name, count, kind in props if count is None},
        "list_properties": [name for name, count, _ in props if count is not None],
    }


def _ply_records(data: bytes, start: int, fmt: str, elements: list) -> dict:
    """{element name: structured array} of the elements given (in file order), lists of 3."""
    out = {}
    if fmt == "ascii":
        tokens = np.array(data[start:].split())
        pos = 0
        for name, count, props in elements:                            # one block per element
            width = sum(1 if c is None else 4 for _, c, _ in props)
            block = tokens[pos: pos + count * width]
            if len(block) != count * width:
                raise ValueError(f"the file ends inside element '{name}'")
            block = block.reshape(count, width)
            pos += count * width
            fields, columns, col = [], [], 0
            for prop, ctype, itype in props:
                if ctype is None:
                    fields.append((prop, itype))
                    columns.append(block[:, col].astype(itype))
                    col += 1
                else:
                    if np.any(block[:, col].astype(np.int64) != 3):
                        raise ValueError(f"list '{prop}' of element '{name}' does not hold 3 items in every row")
                    fields.append((prop, itype, (3,)))
                    columns.append(block[:, col + 1: col + 4].astype(itype))
                    col += 4
            record = np.empty(count, fields)
            for (prop, *_), values in zip(fields, columns):
                record[prop] = values
            out[name] = record
        return out
    endian = "<" if fmt == "binary_little_endian" else ">"
    offset = start
    for name, count, props in elements:
        fields = []
        for prop, ctype, itype in props:
            if ctype is None:
                fields.append((prop, endian + itype))
            else:
                fields.append((prop + " count", endian + ctype))
                fields.append((prop, endian + itype, (3,)))
        dtype = np.dtype(fields)
        record = np.frombuffer(data, dtype, count=count, offset=offset)
        offset += count * dtype.itemsize
        for prop, ctype, _ in props:
            if ctype is not None and np.any(record[prop + " count"] != 3):
                raise ValueError(f"list '{prop}' of element '{name}' does not hold 3 items in every row")
        out[name] = record
    return out


def read_obj_groups(path, *, shape_id: str = "") -> dict:
    """The group of every triangle Mitsuba makes of an OBJ file (a polygon of n corners gives n - 2).

    Returns a dict: ``group`` (F,) int, the index into ``names`` of the last ``g`` or ``o`` line
    before each triangle's face line (-1 before any); ``names`` list[str], one per group line in
    file order (the rest of the line, ``default`` if empty). Parsed on the bytes as arrays, with no
    loop over lines. SceneError naming the file if it cannot be read.
    """
    path = os.fspath(path)
    data = _read_bytes(path, shape_id)
    b = np.frombuffer(data + b"\n", np.uint8)
    white = np.isin(b, np.frombuffer(b" \t\r\n\v\f", np.uint8))
    newline = b == 10
    line = np.cumsum(newline) - newline                                 # line of every byte
    starts = np.flatnonzero(~white & np.concatenate([[True], white[:-1]]))    # token starts
    token_line = line[starts]
    tokens = np.bincount(token_line, minlength=int(line[-1]) + 1)
    head = np.concatenate([[True], token_line[1:] != token_line[:-1]])
    first = starts[head]                                                # first token of each line
    first_line = token_line[head]
    single = np.isin(b[first + 1], np.frombuffer(b" \t", np.uint8))    # a one-letter keyword and a blank
    is_face = single & (b[first] == ord("f"))
    is_group = (single | newline[first + 1] | (b[first + 1] == 13)) & np.isin(b[first], np.frombuffer(b"go", np.uint8))
    face_line, group_line = first_line[is_face], first_line[is_group]
    triangles = np.maximum(tokens[face_line] - 3, 0)                    # "f" + n corners: n - 2 triangles
    owner = np.searchsorted(group_line, face_line, side="right") - 1
    ends = np.flatnonzero(newline)
    names = []
    for at, line_no in zip(first[is_group].tolist(), group_line.tolist()):   # one per group line
        text = data[at + 1: ends[line_no]].strip().decode("utf-8", "replace")
        names.append(" ".join(text.split()) or "default")
    return {"group": np.repeat(owner, triangles).astype(np.int64), "names": names}
