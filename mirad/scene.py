"""Scene ingestion: a Mitsuba scene in, triangles with reflectance and emission out.

Every shape becomes world-space triangles (meshes as they are, analytic sphere,
disk and cylinder tessellated; visibility rays still go to the true Mitsuba
shape). Each triangle gets its diffuse albedo rho (C,) averaged over the triangle
and its emitted radiosity E = pi * L_e (C,) from an ``area`` emitter. Two-sided
BSDFs give a back-side *patch* per triangle; patches are the roots of the
element hierarchy. Other emitters (point, spot, directional, environment) are
kept for the direct-light pass (``emitters.py``).
"""

from __future__ import annotations

import hashlib
import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import _runtime  # noqa: F401  (LLVM set-up before mitsuba)
from ._runtime import choose_variant
from .arrays import channel_max, scene_diagonal, to_float, to_uint
from .errors import SceneError, warn
from .leaf import LeafError, is_leaf

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

#: Relative size under which a triangle counts as degenerate (area < ZERO_AREA * diag^2).
ZERO_AREA = 1e-12



def emitters_grey(emitters: list) -> bool:
    """True when every one of these (non-area) Mitsuba emitters has the same value in all
    channels: its colour parameters (a sun's irradiance, a lamp's intensity, a sky's
    radiance) and every pixel of an environment map."""
    for emitter in emitters:
        params = mi.traverse(emitter)
        for key in params.keys():
            value = params[key]
            if isinstance(value, mi.Color3f):
                rgb = np.asarray(value).reshape(3, -1)
            elif isinstance(value, mi.TensorXf) and value.ndim == 3 and value.shape[-1] == 3:
                rgb = np.asarray(value).reshape(-1, 3).T
            else:
                continue
            if not np.all(rgb == rgb[:1]):
                return False
    return True

@dataclass
class Scene:
    """A Mitsuba scene turned into triangle arrays (all float64, world space, metres).

    Attributes
    ----------
    mi_scene : mi.Scene            the loaded scene (visibility rays go here)
    source : str or None           file the scene came from
    shape_ids : list[str]          Mitsuba ids, in ``mi_scene.shapes()`` order
    shape_types : list[str]        Mitsuba class names ("Mesh", "Rectangle", "Sphere", ...)
    vertices : (V, 3) float        triangle-mesh vertices of all shapes
    faces : (T, 3) int             vertex indices of every input triangle
    tri_shape : (T,) int           shape index of each triangle
    tri_area : (T,) float          m^2
    tri_normal : (T, 3) float      unit front normal
    tri_rho : (T, C) float         front diffuse albedo
    tri_emission : (T, C) float    front emitted radiosity E = pi L_e, W/m^2
    patch_tri : (P,) int           triangle of each patch (front patches first, then back patches)
    patch_side : (P,) int          0 front, 1 back
    patch_rho, patch_emission : (P, C) float
    patch_opposite : (P,) int; patch_transmittance : (P, C) float
        the patch on the other side of the triangle (-1: none) and the fraction of the irradiance
        handed to it (leaves only, docs/leaves.md)
    curve_center, curve_axis : (T, 3) float; curve_radius : (T,) float
        true-surface projection for tessellated spheres/cylinders (radius 0: flat)
    light_emitters : list          non-area Mitsuba emitters (direct-light pass)
    light_kinds : list[str]        their class names
    tri_face : (T,) int            index of each triangle in its Mitsuba shape's face list
    tri_transmittance, back_transmittance : (T, C) float
        hemispherical transmittance of the front / back side in Mitsuba (light through the surface,
        glass or an opacity mask); mirad's surfaces are opaque, so this light is lost
    tri_specular : (T, C) float    the part of ``tri_rho`` Mitsuba reflects specularly or glossily
        (mirad reflects it diffusely)
    approximations : list[dict]    one record per shape whose BSDF the diffuse model approximates:
        ``shape`` id, ``bsdf`` class, ``what`` ("transmission", "opacity", "non-diffuse reflection"),
        ``area`` m^2, and area means (C,) of ``albedo`` (used), ``transmitted`` (lost), ``non_diffuse``
        (redirected); ``model_error()`` turns them into a relative error
    shape_files : list             per shape (``shape_ids`` order), the mesh file it was read from as
        (plugin type, path), e.g. ("ply", "plants/p1.ply"), or None (analytic shapes, meshes made in
        code, an ``mi.Scene`` given as it is, or a file mirad cannot tell); ``mirad.organs`` reads the
        file again for its face groups
    band_names : list[str] or None  the channels' names when they are wavebands (``mirad.with_bands``);
        None: RGB
    light_band_scale : (E, C) float or None  per non-area emitter (``light_emitters``) and band, the
        factor on the RGB mean of its emission (``mirad.bands``); None: the emitters' own RGB
    tri_leaf : (T,) bool           triangles whose BSDF is a leaf (``mirad/leaf.py``; or a ``twosided``
        or blend of leaves: every lobe diffuse, one of them transmitting): their transmittance is
        diffuse, the same both ways, and is what ``patch_transmittance`` hands to the other side
    origin : (3,) float            m; the scene as loaded was moved by -origin so that its bounding box
        is centred at 0 (float32 precision far from the origin; zero for scenes near it): every
        position above, ``mi_scene`` and its sensors are in this internal frame; ``to_user`` /
        ``to_internal`` convert points (exports and probes work in the user's frame)
    """

    mi_scene: object
    source: str | None
    shape_ids: list
    shape_types: list
    vertices: np.ndarray
    faces: np.ndarray
    tri_shape: np.ndarray
    tri_area: np.ndarray
    tri_normal: np.ndarray
    tri_rho: np.ndarray
    tri_emission: np.ndarray
    back_rho: np.ndarray
    curve_center: np.ndarray
    curve_axis: np.ndarray
    curve_radius: np.ndarray
    vertex_uv: np.ndarray | None
    light_emitters: list
    light_kinds: list
    variant: str
    dropped_triangles: int = 0
    duplicate_triangles: int = 0
    non_manifold_edges: int = 0
    warnings: list = field(default_factory=list)
    non_diffuse_shapes: list = field(default_factory=list)
    tri_face: np.ndarray | None = None
    tri_transmittance: np.ndarray | None = None
    back_transmittance: np.ndarray | None = None
    tri_specular: np.ndarray | None = None
    approximations: list = field(default_factory=list)
    origin: np.ndarray | None = None
    tri_leaf: np.ndarray | None = None
    shape_files: list = field(default_factory=list)
    band_names: list | None = None
    light_band_scale: np.ndarray | None = None
    #: what solvers derive from the scene alone and keep for its next solve (the hierarchical
    #: core's node tree, as Mitsuba keeps its ray-tracing hierarchy), by the solver's own key;
    #: a copy of the scene (``dataclasses.replace``) starts without it
    prepared: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self):
        T = len(self.faces)
        if not self.shape_files:
            self.shape_files = [None] * len(self.shape_ids)
        self.origin = np.zeros(3) if self.origin is None else np.asarray(self.origin, dtype=np.float64)
        if self.tri_face is None:
            self.tri_face = np.arange(T)
        if self.tri_leaf is None:
            self.tri_leaf = np.zeros(T, bool)
        for name in ("tri_transmittance", "back_transmittance", "tri_specular"):
            if getattr(self, name) is None:
                setattr(self, name, np.zeros((T, self.tri_rho.shape[1])))

    # --- derived ---------------------------------------------------------------------------
    @property
    def triangle_count(self) -> int:
        return len(self.faces)

    @property
    def channels(self) -> int:
        return self.tri_rho.shape[1]

    @property
    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = self.mi_scene.bbox().min, self.mi_scene.bbox().max
        return np.array(lo, dtype=np.float64), np.array(hi, dtype=np.float64)

    @property
    def diagonal(self) -> float:
        """Length of the scene bounding-box diagonal, m (the unit of every epsilon)."""
        return scene_diagonal(self.vertices)

    @property
    def tri_vertices(self) -> np.ndarray:
        """(T, 3, 3) float: the corners of each triangle."""
        return self.vertices[self.faces]

    @property
    def back_triangles(self) -> np.ndarray:
        """(B,) int: triangles with a back-side patch: a two-sided BSDF (back reflectance > 0), or a
        leaf that transmits (light passes to its back side even where that side reflects nothing)."""
        # (columnwise maxima: this runs at every patch property's use, a dozen times a solve)
        back = channel_max(self.back_rho) > 0
        back |= self.tri_leaf & ((channel_max(self.tri_transmittance) > 0) | (channel_max(self.back_transmittance) > 0))
        return np.flatnonzero(back)

    @property
    def patch_tri(self) -> np.ndarray:
        return np.concatenate([np.arange(self.triangle_count), self.back_triangles])

    @property
    def patch_side(self) -> np.ndarray:
        return np.concatenate(
            [np.zeros(self.triangle_count, np.int8), np.ones(len(self.back_triangles), np.int8)]
        )

    @property
    def patch_rho(self) -> np.ndarray:
        return np.concatenate([self.tri_rho, self.back_rho[self.back_triangles]])

    @property
    def patch_emission(self) -> np.ndarray:
        back = np.zeros((len(self.back_triangles), self.channels))
        return np.concatenate([self.tri_emission, back])

    @property
    def patch_opposite(self) -> np.ndarray:
        """(P,) int: the patch on the other side of each patch's triangle, -1 where it has none."""
        T, back = self.triangle_count, self.back_triangles
        opposite = np.full(T + len(back), -1, np.int64)
        opposite[back] = T + np.arange(len(back))
        opposite[T:] = back
        return opposite

    @property
    def patch_transmittance(self) -> np.ndarray:
        """(P, C) float: the fraction of the irradiance arriving on each patch's side that leaves,
        diffusely, from the other side (``patch_opposite``): ``tri_transmittance`` for a front patch,
        ``back_transmittance`` for a back patch, on leaf triangles (``tri_leaf``); zero elsewhere,
        where transmission (glass, masks) is light the diffuse, opaque model loses (``model_error``).
        Dimensionless, in [0, 1 - patch_rho]."""
        leaf = self.tri_leaf[:, None]
        front = np.where(leaf, self.tri_transmittance, 0.0)
        back = np.where(leaf, self.back_transmittance, 0.0)[self.back_triangles]
        return np.concatenate([front, back])

    @property
    def diffuse_transmission(self) -> bool:
        """True when some shape has a leaf BSDF (``tri_leaf``) that transmits light (tau > 0)."""
        return bool(np.any(self.patch_transmittance > 0))

    @property
    def grey(self) -> bool:
        """True when every reflectance, emission and leaf transmittance is the same in all channels."""
        rho, em = self.tri_rho, self.tri_emission
        if self.diffuse_transmission:  # a grey leaf may transmit in colour (only leaf scenes look)
            tau = self.patch_transmittance
            if not np.all(tau == tau[:, :1]):
                return False
        scale = self.light_band_scale          # bands: the sun may differ between bands (None: RGB)
        if scale is not None and not np.all(scale == scale[:, :1]):
            return False
        if scale is None and not emitters_grey(self.light_emitters):   # a coloured sun on grey surfaces
            return False
        return bool(np.all(rho == rho[:, :1]) and np.all(em == em[:, :1]) and np.all(self.back_rho == self.back_rho[:, :1]))

    @property
    def features(self) -> dict:
        """What the scene uses and what mirad switches on for it."""
        kinds: dict[str, int] = {}
        n_area = int(np.count_nonzero(channel_max(self.tri_emission) > 0))
        if n_area:
            kinds["area (triangles)"] = n_area
        for k in self.light_kinds:
            kinds[k] = kinds.get(k, 0) + 1
        return {
            "triangles": self.triangle_count,
            "shapes": len(self.shape_ids),
            "channels": 1 if self.grey else self.channels,
            "back_side_patches": int(len(self.back_triangles)),
            "emitters": kinds,
            "direct_light_pass": bool(self.light_emitters),
            "curved_shapes": int(np.count_nonzero(self.curve_radius > 0)),
            "non_diffuse_approximated": list(self.non_diffuse_shapes),
            "dropped_zero_area_triangles": int(self.dropped_triangles),
            "duplicate_triangles": int(self.duplicate_triangles),
            "non_manifold_edges": int(self.non_manifold_edges),
            "translucent_leaf_triangles": int(np.count_nonzero(
                self.tri_leaf & (channel_max(np.maximum(self.tri_transmittance, self.back_transmittance)) > 0))),
        }

    @property
    def fingerprint(self) -> str:
        """Hash of geometry, materials and lights (area emission, and the kind and every parameter of
        the other emitters): saved solutions and caches check it."""
        h = hashlib.sha256()
        for arr in (self.vertices.astype(np.float32), self.faces.astype(np.int64),
                    np.round(self.tri_rho, 6), np.round(self.tri_emission, 6), np.round(self.back_rho, 6)):
            h.update(np.ascontiguousarray(arr).tobytes())
        if self.diffuse_transmission:  # only then: every other scene keeps the fingerprint it had
            h.update(np.ascontiguousarray(np.round(self.patch_transmittance, 6)).tobytes())
        h.update("\0".join(self.shape_ids).encode())
        h.update("\0".join(self.light_kinds).encode())
        if self.band_names:          # band scenes only: RGB scenes keep the fingerprint they had
            h.update("\0".join(self.band_names).encode())
            h.update(np.ascontiguousarray(np.round(self.light_band_scale, 6)).tobytes())
        for emitter in self.light_emitters:   # their values too: two skies of one kind differ
            params = mi.traverse(emitter)
            for key in sorted(params.keys()):
                value = params[key]
                value = value.matrix if hasattr(value, "matrix") else value
                h.update(key.encode())
                h.update(np.ascontiguousarray(np.round(np.array(value, dtype=np.float64), 6)).tobytes())
        return h.hexdigest()[:16]

    def model_error(self, irradiance: np.ndarray | None = None,
                    back_irradiance: np.ndarray | None = None, *, leaf_transmission: bool = False) -> float:
        """Relative error of the diffuse, opaque model of the scene's non-diffuse BSDFs (first order).

        The power Mitsuba sends through a surface (transmittance tau) or reflects directionally
        (non-diffuse reflectance s) but mirad absorbs or spreads diffusely, over the power all
        surfaces reflect: ``sum A H (tau + s) / sum A rho H``, largest over channels, with the
        irradiance H of each triangle side. It has the units of ``tolerance`` (relative error of the
        reflected radiosity B - E) and adds to the solver's estimate: a solution cannot be closer
        to Mitsuba's path tracer than this. Not a strict bound (the lost light's fate after its
        first bounce is not followed), but zero exactly when every BSDF is diffuse and opaque.

        Parameters
        ----------
        irradiance : (T, C) float, W/m^2, optional
            front-side irradiance per triangle (``Solution.triangle_irradiance``); default: uniform,
            a prior before solving
        back_irradiance : (T, C) float, W/m^2, optional
            back-side irradiance; default: as the front where given, else uniform
        leaf_transmission : bool, default False
            the solver carried the diffuse transmission of ``leaf`` BSDFs to the other side
            (the hierarchical core does): that light is not lost

        Returns
        -------
        float, dimensionless (0.05: the model alone puts the solution ~5 % off the path tracer)
        """
        h = np.ones_like(self.tri_rho) if irradiance is None else np.asarray(irradiance, dtype=np.float64)
        hb = h if back_irradiance is None else np.asarray(back_irradiance, dtype=np.float64)
        a = self.tri_area[:, None]
        back = np.zeros(self.triangle_count, bool)
        back[self.back_triangles] = True
        kept = self.tri_leaf[:, None] if leaf_transmission else np.zeros((self.triangle_count, 1), bool)
        tau, tau_back = np.where(kept, 0.0, self.tri_transmittance), np.where(kept, 0.0, self.back_transmittance)
        lost = a * (h * (tau + self.tri_specular) + hb * tau_back * back[:, None])
        reflected = a * (h * self.tri_rho + hb * self.back_rho)
        total = reflected.sum(axis=0)
        ratio = np.divide(lost.sum(axis=0), total, out=np.zeros_like(total), where=total > 0)
        return float(ratio.max())

    def to_user(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) float internal positions (``vertices``, m) in the user's frame: + ``origin``."""
        return np.asarray(points, dtype=np.float64) + self.origin

    def to_internal(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) float positions in the user's frame (probe points, m) in the internal one."""
        return np.asarray(points, dtype=np.float64) - self.origin

    def shape_index(self, shape_id: str) -> int:
        try:
            return self.shape_ids.index(shape_id)
        except ValueError:
            raise KeyError(f"no shape with id {shape_id!r}; ids are {self.shape_ids}") from None


# ------------------------------------------------------------------------------------------
# Loading
# ------------------------------------------------------------------------------------------

def load_scene(source, *, variant: str | None = None) -> Scene:
    """Load a scene from an XML path, a Mitsuba dict or an ``mi.Scene``.

    Files and dicts are loaded with ``optimize=False`` so every shape keeps its id.

    >>> scene = load_scene("scenes/cornell-box/scene.xml")   # doctest: +SKIP
    >>> scene.shape_ids[:2]                                 # doctest: +SKIP
    ['floor', 'ceiling']
    """
    if isinstance(source, Scene):
        return source
    variant = choose_variant(variant)
    path = None
    if isinstance(source, (str, os.PathLike)):
        path = str(source)
        if not os.path.exists(path):
            raise SceneError(f"scene file '{path}' does not exist; check the path")
        if os.path.isdir(path):
            raise SceneError(f"'{path}' is a folder; give the scene's XML file")
        _check_is_xml(path)
        meshes = _mesh_files(path)
        _check_ply_indices(path, meshes)
        try:
            mi_scene = mi.load_file(path, optimize=False)
        except Exception as exc:  # Mitsuba raises RuntimeError with its own text
            raise SceneError(_explain_load_error(path, exc, meshes, source=path)) from None
    elif isinstance(source, dict):
        meshes = _mesh_files(source)
        _check_ply_indices("<dict>", meshes)
        try:
            mi_scene = mi.load_dict(source, optimize=False)
        except Exception as exc:
            raise SceneError(_explain_load_error("<dict>", exc, meshes, source=source)) from None
    elif isinstance(source, mi.Scene):
        mi_scene, meshes = source, []
    else:
        raise SceneError(
            f"cannot load a scene from {type(source).__name__}; give an XML path, a Mitsuba dict or an mi.Scene"
        )
    where = path or ("<dict>" if isinstance(source, dict) else "<scene>")
    _check_obj_faces(where, meshes)
    origin, notes = _recentre(mi_scene, where, own=not isinstance(source, mi.Scene))
    scene = _ingest(mi_scene, path, variant, origin=origin, meshes=meshes)
    for note in notes:
        _warn_once(scene, note)
    return scene


#: A scene whose bounding-box centre lies farther than this many diagonals from the origin is
#: moved to it (float32 rays and offsets lose precision with the distance); nearer ones stay put.
RECENTRE = 100.0
#: Warn when float32 rounding of the positions Mitsuba loaded exceeds this fraction of the diagonal.
PRECISION = 1e-5


def _recentre(mi_scene, where: str, *, own: bool) -> tuple[np.ndarray, list]:
    """Move a scene far from the origin to it; return (origin (3,) float m, warnings to give).

    Mitsuba holds positions in float32: at distance d from the origin they are rounded to about
    d * 2^-24, and ray offsets and shadow tests relative to the scene's size fail there (a 2 m scene
    at 1e5 m came out several per cent dark). Mesh vertices, the transforms of analytic shapes,
    sensors and emitters, and point-light positions are translated by -centre, in float64 before
    rounding, which keeps whatever precision the file gave at load. A scene handed over as an
    ``mi.Scene`` (``own=False``) belongs to the caller and is not moved; it gets a warning instead.
    """
    box = mi_scene.bbox()
    lo, hi = np.array(box.min, dtype=np.float64), np.array(box.max, dtype=np.float64)
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        return np.zeros(3), []
    centre = 0.5 * (lo + hi)
    diag = scene_diagonal(np.stack([lo, hi]))
    far = float(np.abs(np.concatenate([lo, hi])).max())
    notes = []
    rounding = far * 2.0 ** -24
    if rounding > PRECISION * diag:
        notes.append(f"{where}: the scene lies {far:.3g} m from the origin, {far / diag:.3g} times its size; "
                     f"Mitsuba stores positions in float32, rounded there by up to {rounding:.2g} m ({rounding / diag:.1e} "
                     "of the scene), which mirad cannot restore; move the scene near the origin in the "
                     f"file (subtract about {np.round(centre, 1).tolist()}) for full precision")
    if np.linalg.norm(centre) <= RECENTRE * diag:
        return np.zeros(3), notes
    if not own:
        notes.append(f"{where}: the scene's centre lies {np.linalg.norm(centre):.3g} m from the origin and "
                     "an mi.Scene given to mirad is not moved, so ray offsets lose float32 precision (results "
                     "can come out dark); give mirad.load_scene the file or dict so it can re-centre it")
        return np.zeros(3), notes
    params = mi.traverse(mi_scene)
    for key in list(params.keys()):
        if key.endswith(".vertex_positions"):
            v = np.array(params[key].numpy(), dtype=np.float64).reshape(-1, 3) - centre
            params[key] = type(params[key])(v.reshape(-1).astype(np.float32))
        elif key.endswith(".to_world"):
            value = params[key]
            m = np.array(value.matrix.numpy() if hasattr(value.matrix, "numpy") else value.matrix,
                         dtype=np.float64).reshape(4, 4)
            m[:3, 3] -= centre
            params[key] = type(value)(mi.ScalarMatrix4f(m.tolist()))
        elif key.endswith(".position"):
            p = np.array(params[key], dtype=np.float64).reshape(-1)[:3] - centre
            params[key] = type(params[key])(*p.tolist())
    params.update()
    return centre, notes


#: Mesh formats Mitsuba reads from a file, by plugin type.
MESH_TYPES = ("ply", "obj", "serialized", "stl")


def _check_is_xml(path: str) -> None:
    """Refuse a mesh (or any non-XML file) given where a scene file is expected."""
    try:
        with open(path, "rb") as f:
            head = f.read(64).lstrip(b"\xef\xbb\xbf \t\r\n")
    except OSError as exc:
        raise SceneError(f"cannot read scene file '{path}' ({exc.strerror}); check its permissions") from None
    suffix = Path(path).suffix.lower().lstrip(".")
    if head.startswith(b"<"):
        return
    kind = suffix if suffix in MESH_TYPES else ("ply" if head.startswith(b"ply") else None)
    if kind:
        raise SceneError(
            f"'{path}' is a {kind.upper()} mesh, not a scene; wrap it in a scene XML with a light, e.g. "
            f"<scene version=\"3.0.0\"><shape type=\"{kind}\"><string name=\"filename\" "
            f"value=\"{Path(path).name}\"/></shape><emitter type=\"constant\"/></scene>")
    raise SceneError(f"'{path}' is not a Mitsuba scene XML file (it does not start with '<'); give the "
                     "scene's .xml file")


def _mesh_files(source) -> list:
    """Mesh files a scene XML path or dict refers to: [(shape id or '', plugin type, path)].

    Read before Mitsuba loads the scene, so messages can name the file at fault. XML paths are
    resolved against the scene's folder as Mitsuba does; ``$parameters`` and includes are skipped.
    """
    found = []
    if isinstance(source, dict):
        def walk(d, key):
            if isinstance(d, dict):
                if d.get("type") in MESH_TYPES and isinstance(d.get("filename"), str):
                    found.append((str(d.get("id", key)), d["type"], d["filename"]))
                for k, v in d.items():
                    walk(v, k)
        walk(source, "")
        return found
    import xml.etree.ElementTree as ET

    try:
        root = ET.parse(source).getroot()
    except (ET.ParseError, OSError, UnicodeDecodeError):
        return found
    base = Path(source).parent
    for shape in root.iter("shape"):
        kind = shape.get("type", "")
        name = next((c.get("value") for c in shape if c.tag == "string" and c.get("name") == "filename"), None)
        if kind in MESH_TYPES and name and "$" not in name:
            found.append((shape.get("id", ""), kind, str(base / name)))
    return found


def _check_obj_faces(where: str, meshes: list) -> None:
    """Refuse OBJ files with a face line of fewer than 3 vertices (a file cut off mid-line).

    Mitsuba drops such a face silently; the file is truncated or corrupt, and the answer would be
    missing a piece of surface with no word.
    """
    import re

    short = re.compile(rb"^[ \t]*f(?:[ \t]+[^ \t\r\n]+){0,2}[ \t]*\r?$", re.MULTILINE)
    for sid, kind, name in meshes:
        if kind != "obj" or not os.path.isfile(name):
            continue
        with open(name, "rb") as f:
            data = f.read()
        bad = short.search(data)
        if bad:
            line = data.count(b"\n", 0, bad.start()) + 1
            raise SceneError(f"{where}: mesh file '{name}'{_shape_note(sid)}: line {line} is a face with fewer "
                             "than 3 vertices (the file is cut off or corrupt); re-export the mesh")


def _check_ply_indices(where: str, meshes: list) -> None:
    """Refuse PLY files whose faces index past their vertices, before Mitsuba reads them.

    Mitsuba does not check PLY face indices and crashes the process (segmentation fault) on one far
    out of range, so each PLY is read once with trimesh (no processing) first. Files trimesh cannot
    read are left to Mitsuba, whose error is explained by ``_explain_load_error``.
    """
    import trimesh

    for sid, kind, name in meshes:
        if kind != "ply" or not os.path.isfile(name):
            continue
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                mesh = trimesh.load(name, file_type="ply", process=False, force="mesh")
            faces, count = np.asarray(mesh.faces), len(mesh.vertices)
        except Exception:
            continue
        if faces.size and (faces.max() >= count or faces.min() < 0):
            bad = int(faces.max() if faces.max() >= count else faces.min())
            raise SceneError(f"{where}: mesh file '{name}'{_shape_note(sid)}: a face refers to vertex {bad} of "
                             f"{count} (indices out of range: the file is corrupt); re-export the mesh")


def _shape_note(sid: str) -> str:
    return f" (shape '{sid}')" if sid else ""


def _culprit(meshes: list, text: str):
    """The mesh file behind a Mitsuba load error: the one named in it, else the first Mitsuba cannot
    load on its own; (id, type, path) or None."""
    for mesh in meshes:
        if os.path.basename(mesh[2]) and os.path.basename(mesh[2]) in text:
            return mesh
    for mesh in meshes:
        try:
            mi.load_dict({"type": mesh[1], "filename": mesh[2]})
        except Exception:
            return mesh
    return None


_LOAD_FIXES = (  # (substring of Mitsuba's message, lower case; what the user should do)
    ("without a transmission component", "a twosided BSDF that holds a transmitting BSDF (a leaf: "
                                         "docs/leaves.md) needs <boolean name=\"allow_transmission\" "
                                         "value=\"true\"/> inside it"),
    ("incompatible sizes", "the mesh has no faces (a point cloud?) or no vertices; mirad needs triangles: "
                           "re-export it with its faces"),
    ("codec can't decode", "the file is corrupt or not a mesh of that format (unreadable bytes in its header); "
                           "re-export it"),
    ("reference to invalid vertex", "a face refers to a vertex the file does not have (the file is cut off or "
                                    "corrupt); re-export the mesh"),
    ("parsing of xml file", "fix the XML syntax at the position given"),
    ("plugin \"", "check the plugin's 'type' name against Mitsuba's plugin list"),
    ("file not found", "check that every referenced file exists (paths are relative to the scene file)"),
    ("invalid vertex", "the mesh has NaN or Inf vertex positions; repair or re-export it"),
    ("could not parse", "the referenced file is malformed (NaN or text in a number field); re-export it"),
    ("must be in the range", "give reflectances between 0 and 1"),
    ("unreferenced", "remove or use the property Mitsuba names"),
)


def _explain_load_error(where: str, exc: Exception, meshes: list = (), *, source=None) -> str:
    text = str(exc).strip()
    refusal = _leaf_refusal(where, text, source)
    if refusal is not None:
        return refusal
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    detail = lines[-1] if lines else type(exc).__name__
    low = text.lower()
    fix = next((f for key, f in _LOAD_FIXES if key in low), None)
    if "parsing of xml file" not in low and meshes:
        mesh = _culprit(list(meshes), text)
        if mesh is not None:
            return (f"{where}: mesh file '{mesh[2]}'{_shape_note(mesh[0])} cannot be loaded ({detail}); "
                    f"{fix or 'the file is corrupt or not a ' + mesh[1].upper() + ' mesh; re-export it'}")
    return f"{where}: Mitsuba could not load the scene ({detail}); {fix or 'fix the scene so that Mitsuba itself can load it'}"


def _leaf_refusal(where: str, text: str, source) -> str | None:
    """A leaf BSDF's refusal of its values (``mirad.leaf.LeafError``) inside Mitsuba's load error,
    as one line naming the file (and line), the shapes that use the BSDF, and the fix; None for any
    other error. ``source`` is the scene's XML path or dict (to find the shapes), or None."""
    marker = f"{LeafError.__name__}: "
    message = next((ln.strip()[len(marker):] for ln in text.splitlines() if ln.strip().startswith(marker)), None)
    if message is None:
        return None
    at_line = re.search(r"\(line (\d+), col \d+\)", text)
    node = re.search(r'At dictionary node "([^"]+)"', text)
    owners: list = []
    try:
        if isinstance(source, dict) and node:
            owners = _dict_owners(source, node.group(1))
        elif isinstance(source, (str, os.PathLike)) and at_line:
            owners = _xml_owners(str(source), int(at_line.group(1)))
    except Exception:  # locating the shape is a courtesy: the message stands without it
        owners = []
    place = f"{where} (line {at_line.group(1)})" if at_line and isinstance(source, (str, os.PathLike)) else where
    shapes = ""
    if owners:
        shapes = ("shape " if len(owners) == 1 else "shapes ") + ", ".join(f"'{o}'" for o in owners[:5]) + \
            (f" and {len(owners) - 5} more" if len(owners) > 5 else "") + ": "
    return f"{place}: {shapes}{message}"


def _dict_owners(source: dict, node: str) -> list:
    """Ids of the shapes of a scene dict that own (or refer to) the object at ``node`` ("blade.bsdf")."""
    top = node.split(".")[0]
    users = []

    def refers(d) -> bool:
        if isinstance(d, dict):
            if d.get("type") == "ref" and d.get("id") == top:
                return True
            return any(refers(v) for v in d.values())
        return False

    for key, value in source.items():
        if key != top and isinstance(value, dict) and refers(value):
            users.append(str(value.get("id", key)))
    if users:
        return users
    entry = source.get(top)
    return [str(entry.get("id", top))] if isinstance(entry, dict) and "." in node else []


def _xml_owners(path: str, line: int) -> list:
    """Ids of the shapes of a scene XML that hold the element starting at ``line`` or refer to the
    top-level object holding it (unnamed shapes as "line N")."""
    import xml.parsers.expat

    parents: list = []      # stack of (tag, attributes, line)
    found: list = []        # the element's ancestors, outermost first, itself last
    shapes_by_ref: dict = {}

    def start(tag, attrs):
        here = parser.CurrentLineNumber
        parents.append((tag, attrs, here))
        if not found and here == line:
            found.extend(parents)
        if tag == "ref":
            shape = next((p for p in reversed(parents[:-1]) if p[0] == "shape"), None)
            if shape is not None:
                shapes_by_ref.setdefault(attrs.get("id"), []).append(shape[1].get("id") or f"line {shape[2]}")

    parser = xml.parsers.expat.ParserCreate()
    parser.StartElementHandler = start
    parser.EndElementHandler = lambda tag: parents.pop()
    with open(path, "rb") as f:
        parser.ParseFile(f)
    shape = next((p for p in reversed(found) if p[0] == "shape"), None)
    if shape is not None:
        return [shape[1].get("id") or f"line {shape[2]}"]
    top = found[1] if len(found) > 1 else None          # found[0] is <scene>
    return shapes_by_ref.get(top[1].get("id"), []) if top is not None else []


def _ingest(mi_scene, path: str | None, variant: str, *, origin: np.ndarray | None = None,
            meshes: list = ()) -> Scene:
    where = path or "<scene>"
    shapes = list(mi_scene.shapes())
    if not shapes:
        raise SceneError(f"{where}: the scene has no shapes; add geometry to solve")
    ids, types = [], []
    verts_all, faces_all, shape_of, face_of = [], [], [], []
    uv_all = []
    c_center, c_axis, c_radius = [], [], []
    offset = 0
    has_uv = False
    for index, shape in enumerate(shapes):
        sid = shape.id() or f"shape_{index}"
        ids.append(sid)
        kind = shape.class_name()
        types.append(kind)
        verts, faces, uv, curve = _triangulate(shape, sid, where, {m[0]: m[2] for m in meshes if m[0]})
        if not shape.is_mesh():
            faces = _curved_shading_side(mi_scene, shape, verts, faces)
        if not np.all(np.isfinite(verts)):
            raise SceneError(
                f"{where}: shape '{sid}' has NaN or Inf vertex positions; repair or re-export the mesh"
            )
        has_uv |= uv is not None
        uv_all.append(uv if uv is not None else np.full((len(verts), 2), np.nan))
        verts_all.append(verts)
        faces_all.append(faces + offset)
        shape_of.append(np.full(len(faces), index, np.int32))
        face_of.append(np.arange(len(faces)))
        center, axis, radius = curve
        c_center.append(np.tile(center, (len(faces), 1)))
        c_axis.append(np.tile(axis, (len(faces), 1)))
        c_radius.append(np.full(len(faces), radius))
        offset += len(verts)
    vertices = np.concatenate(verts_all)
    faces = np.concatenate(faces_all).astype(np.int64)
    tri_shape = np.concatenate(shape_of)
    tri_face = np.concatenate(face_of)
    vertex_uv = np.concatenate(uv_all) if has_uv else None
    curve_center, curve_axis, curve_radius = map(np.concatenate, (c_center, c_axis, c_radius))

    # --- geometry per triangle, drop degenerate ones --------------------------------------
    diag = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0))) or 1.0
    tv = vertices[faces]
    cross = np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0])
    double_area = np.linalg.norm(cross, axis=1)
    keep = double_area > 2 * ZERO_AREA * diag * diag
    dropped = int(np.count_nonzero(~keep))
    faces, tri_shape, tri_face = faces[keep], tri_shape[keep], tri_face[keep]
    curve_center, curve_axis, curve_radius = curve_center[keep], curve_axis[keep], curve_radius[keep]
    cross, double_area = cross[keep], double_area[keep]
    if len(faces) == 0:
        raise SceneError(f"{where}: every triangle has zero area; the scene has no usable geometry")
    vanished = np.setdiff1d(np.arange(len(ids)), tri_shape)
    pending = [f"{where}: shape '{ids[i]}' has only zero-area triangles and is left out of the solve; "
               "fix or remove it" for i in vanished]
    tri_area = 0.5 * double_area
    tri_normal = cross / double_area[:, None]

    scene = Scene(
        mi_scene=mi_scene, source=path, shape_ids=ids, shape_types=types, vertices=vertices,
        faces=faces, tri_shape=tri_shape, tri_area=tri_area, tri_normal=tri_normal,
        tri_rho=np.zeros((len(faces), 3)), tri_emission=np.zeros((len(faces), 3)),
        back_rho=np.zeros((len(faces), 3)), curve_center=curve_center, curve_axis=curve_axis,
        curve_radius=curve_radius, vertex_uv=vertex_uv, light_emitters=[], light_kinds=[],
        variant=variant, dropped_triangles=dropped, tri_face=tri_face, origin=origin,
        shape_files=_shape_files(shapes, meshes),
    )
    for message in pending:
        _warn_once(scene, message)
    _evaluate_materials(scene, shapes, where)

    for emitter in mi_scene.emitters():
        if emitter.get_shape() is not None:
            continue
        scene.light_emitters.append(emitter)
        scene.light_kinds.append(emitter.class_name())
    _check_topology(scene, where)
    if scene.tri_emission.max() <= 0 and not scene.light_emitters:
        raise SceneError(
            f"{where}: the scene has no light; add an area emitter to a shape or a point/spot/"
            "directional/environment emitter"
        )
    unnamed = [i for i, s in enumerate(shapes) if not s.id()]
    if unnamed and isinstance(path, str) is False:
        # Mitsuba's loader merges shapes that share a BSDF unless told optimize=False, and the
        # merged shape has no id: any unnamed shape of a given mi.Scene may be such a merge
        _warn_once(scene, f"{len(unnamed)} of the mi.Scene's {len(shapes)} shapes have no id (mi.load_file "
                          "without optimize=False merges shapes that share a BSDF and drops their ids); "
                          "load the file with mirad.load_scene(path), or mi.load_file(path, optimize=False), "
                          "to keep every shape's id")
    return scene


def _shape_files(shapes: list, meshes: list) -> list:
    """The mesh file of each shape: (plugin type, path) or None; see ``Scene.shape_files``.

    A shape with an id takes the file listed under that id; a mesh without one takes the file
    whose name Mitsuba gives it, if exactly one unnamed shape's file has that name.
    """
    by_id = {sid: (kind, name) for sid, kind, name in meshes if sid}
    unnamed = {}
    for sid, kind, name in meshes:
        if not sid:
            unnamed.setdefault(os.path.basename(name), set()).add((kind, name))
    files = []
    for shape in shapes:
        sid = shape.id()
        if sid:
            files.append(by_id.get(sid) if shape.is_mesh() else None)
            continue
        found = re.search(r'name = "([^"]*)"', str(shape)) if shape.is_mesh() else None
        candidates = unnamed.get(found.group(1), set()) if found else set()
        files.append(next(iter(candidates)) if len(candidates) == 1 else None)
    return files


#: Vertices closer than this fraction of the scene diagonal are the same point (topology checks).
WELD = 1e-7


def _check_topology(scene: Scene, where: str) -> None:
    """Detect coincident duplicate triangles and non-manifold edges; warn once for each.

    Vertices are welded on a grid of ``WELD * diagonal`` (the check works across shapes and
    whatever the indexing); a triangle is a duplicate when another one has the same three welded
    corners (either winding), an edge is non-manifold when more than two triangles of one shape
    share it. Both are solved as they are (coincident elements are coplanar: no transfer between
    them); the counts go to ``scene.features``.
    """
    q = np.round(scene.vertices / (WELD * scene.diagonal)).astype(np.int64)
    _, weld = np.unique(q, axis=0, return_inverse=True)
    corners = np.sort(weld.reshape(-1)[scene.faces], axis=1)                  # (T, 3)
    _, tri_key, tri_count = np.unique(corners, axis=0, return_inverse=True, return_counts=True)
    dup = tri_count[tri_key.reshape(-1)] > 1
    edges = np.concatenate([corners[:, [0, 1]], corners[:, [1, 2]], corners[:, [0, 2]]])
    shape3 = np.tile(scene.tri_shape, 3)
    keys = np.column_stack([shape3, edges])
    _, edge_key, edge_count = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    bad_edge = edge_count > 2
    scene.duplicate_triangles = int(dup.sum())
    scene.non_manifold_edges = int(bad_edge.sum())
    if dup.any():
        names = ", ".join(f"'{scene.shape_ids[i]}'" for i in np.unique(scene.tri_shape[dup])[:5])
        _warn_once(scene, f"{where}: {int(dup.sum())} triangles coincide with another triangle (shapes "
                          f"{names}); mirad solves them as separate coplanar surfaces that exchange no "
                          "light; remove the duplicates (merge by distance) unless they are meant")
    if bad_edge.any():
        tri_of_edge = np.tile(np.arange(scene.triangle_count), 3)[bad_edge[edge_key.reshape(-1)]]
        names = ", ".join(f"'{scene.shape_ids[i]}'" for i in np.unique(scene.tri_shape[tri_of_edge])[:5])
        _warn_once(scene, f"{where}: {int(bad_edge.sum())} non-manifold edges (shared by more than two "
                          f"triangles of one shape: {names}); mirad solves each triangle on its own; "
                          "repair the mesh if the fins are not meant")


def _warn_once(scene: Scene, message: str) -> None:
    if message not in scene.warnings:
        scene.warnings.append(message)
        warn(message)


# ------------------------------------------------------------------------------------------
# Shapes to triangles
# ------------------------------------------------------------------------------------------

def _to_world_matrix(shape) -> np.ndarray:
    params = mi.traverse(shape)
    m = np.array(params["to_world"].matrix.numpy(), dtype=np.float64)
    return m.reshape(4, 4) if m.size == 16 else m[..., 0]


def _apply(m: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts @ m[:3, :3].T + m[:3, 3]


def _file_note(sid: str, files: dict) -> str:
    return f" (mesh file '{files[sid]}')" if sid in files else ""


def _triangulate(shape, sid: str, where: str, files: dict | None = None):
    """Return (vertices (V,3), faces (F,3), uv (V,2) or None, (center, axis, radius))."""
    flat = (np.zeros(3), np.zeros(3), 0.0)
    files = files or {}
    kind = shape.shape_type()
    if shape.is_mesh():
        verts = np.array(shape.vertex_positions_buffer().numpy(), dtype=np.float64).reshape(-1, 3)
        faces = np.array(shape.faces_buffer().numpy(), dtype=np.int64).reshape(-1, 3)
        if faces.size and faces.max() >= len(verts):
            raise SceneError(f"{where}: shape '{sid}'{_file_note(sid, files)}: a face refers to vertex "
                             f"{int(faces.max())} of {len(verts)} (indices out of range: the mesh file is "
                             "corrupt); re-export the mesh")
        uv = None
        if shape.has_vertex_texcoords():
            uv = np.array(shape.vertex_texcoords_buffer().numpy(), dtype=np.float64).reshape(-1, 2)
        if shape.has_flipped_normals():
            faces = faces[:, ::-1].copy()
        if shape.has_vertex_normals():
            _check_vertex_normals(shape, sid, where, faces)
            faces = _face_shading_side(shape, verts, faces)
        return verts, faces, uv, flat
    if kind == mi.ShapeType.Disk:
        m = _to_world_matrix(shape)
        local, faces, uv = _disk_mesh()
        verts = _apply(m, local)
    elif kind == mi.ShapeType.Sphere:
        m = _to_world_matrix(shape)
        local, faces, uv = _sphere_mesh()
        verts = _apply(m, local)
        center = _apply(m, np.zeros((1, 3)))[0]
        radius = float(np.linalg.norm(m[:3, 0]))
        flat = (center, np.zeros(3), radius)
    elif kind == mi.ShapeType.Cylinder:
        m = _to_world_matrix(shape)
        local, faces, uv = _cylinder_mesh()
        verts = _apply(m, local)
        center = _apply(m, np.zeros((1, 3)))[0]
        axis = m[:3, 2] / np.linalg.norm(m[:3, 2])
        radius = float(np.linalg.norm(m[:3, 0]))
        flat = (center, axis, radius)
    else:
        raise SceneError(
            f"{where}: shape '{sid}' is a {shape.class_name()}, which mirad cannot mesh; "
            "convert it to a triangle mesh (obj/ply) or use rectangle, disk, cube, sphere or cylinder"
        )
    if shape.has_flipped_normals():
        faces = faces[:, ::-1].copy()
    return verts, faces, uv, flat


def _face_shading_side(shape, verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Wind every triangle so that its front is the side Mitsuba's shading normal points to.

    Mitsuba lights a surface (diffuse BSDF, area emitter) on the side of its *shading* normal, which
    for a mesh with vertex normals is the interpolated vertex normal (negated by ``flip_normals``),
    while the winding gives the geometric one. They disagree under a mirroring transform
    (negative determinant: Mitsuba transforms positions and normals, so the winding turns over but
    the normals do not), which CAD and Blender exports often carry; mirad takes its front from the
    winding, so those triangles are turned over here. (F, 3) int in, (F, 3) int out.
    """
    normals = np.array(shape.vertex_normals_buffer().numpy(), dtype=np.float64).reshape(-1, 3)
    tv = verts[faces]
    winding = np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0])
    shading = normals[faces].sum(axis=1) * (-1.0 if shape.has_flipped_normals() else 1.0)
    turn = np.einsum("ij,ij->i", winding, shading) < 0
    if turn.any():
        faces = faces.copy()
        faces[turn] = faces[turn][:, ::-1]
    return faces


def _curved_shading_side(mi_scene, shape, verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Like ``_face_shading_side`` for mirad's tessellation of a disk, sphere or cylinder.

    Mitsuba's normal of these shapes comes from their own formulas (a sphere's points outward
    whatever the transform, a disk's is the transformed +z normal), so it is read where Mitsuba
    reports it: one ray per triangle, from half its shortest edge above the centroid (more than
    the tessellation's sagitta) towards it, and the triangle is turned over where the normal at the
    hit on this shape faces the other way. Triangles whose ray hits something else keep their winding.
    """
    tv = verts[faces]
    winding = np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0])
    length = np.linalg.norm(winding, axis=1)
    ok = length > 0
    n = np.zeros_like(winding)
    n[ok] = winding[ok] / length[ok, None]
    edges = np.linalg.norm(tv - np.roll(tv, 1, axis=1), axis=2).min(axis=1)
    lift = 0.5 * edges
    origin = tv.mean(axis=1) + n * lift[:, None]
    ray = mi.Ray3f(_points(origin), _points(-n, mi.Vector3f))
    ray.maxt = to_float(2.0 * lift)
    si = mi_scene.ray_intersect(ray)
    mine = np.array((si.is_valid() & (si.shape == mi.ShapePtr(shape))).numpy(), dtype=bool)
    sh = _columns(si.sh_frame.n)
    turn = ok & mine & (np.einsum("ij,ij->i", sh, n) < 0)
    if turn.any():
        faces = faces.copy()
        faces[turn] = faces[turn][:, ::-1]
    return faces


def _points(a: np.ndarray, kind=None):
    """(N, 3) float array as a Dr.Jit Point3f (or the given 3-vector type)."""
    kind = kind or mi.Point3f
    return kind(*[to_float(a[:, i]) for i in range(3)])


def _columns(v) -> np.ndarray:
    """A Dr.Jit 3-vector of width N as an (N, 3) float64 array."""
    arr = np.array(v.numpy(), dtype=np.float64)
    return arr.T if arr.ndim == 2 and arr.shape[0] == 3 else arr.reshape(-1, 3)


def _check_vertex_normals(shape, sid: str, where: str, faces: np.ndarray) -> None:
    """Reject vertex normals that are NaN, Inf or of zero length on vertices that faces use.

    mirad's own normals come from the triangles, but Mitsuba shades (and its path-traced reference
    and renders sample) with these, so a degenerate one would give NaN pixels, not an error.
    """
    normals = np.array(shape.vertex_normals_buffer().numpy(), dtype=np.float64).reshape(-1, 3)
    used = np.unique(faces)
    length = np.linalg.norm(normals[used], axis=1)
    bad = ~np.isfinite(length) | (length < 1e-6)
    if bad.any():
        raise SceneError(
            f"{where}: shape '{sid}' has {int(bad.sum())} degenerate vertex normals (zero length, NaN or "
            "Inf); re-export the mesh with valid normals, or add <boolean name=\"face_normals\" "
            "value=\"true\"/> to the shape to use flat face normals"
        )


def _disk_mesh(segments: int = 32, rings: int = 3):
    """Unit disk in z = 0, normal +z: (V,3), (F,3), uv = (r, phi / 2 pi)."""
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    pts = [np.zeros((1, 3))]
    uvs = [np.zeros((1, 2))]
    for r in np.arange(1, rings + 1) / rings:
        pts.append(np.stack([r * np.cos(phi), r * np.sin(phi), np.zeros_like(phi)], 1))
        uvs.append(np.stack([np.full_like(phi, r), phi / (2 * np.pi)], 1))
    verts = np.concatenate(pts)
    uv = np.concatenate(uvs)
    j = np.arange(segments)
    jn = (j + 1) % segments
    faces = [np.stack([np.zeros(segments, int), 1 + j, 1 + jn], 1)]
    for ring in range(1, rings):
        a = 1 + (ring - 1) * segments
        b = 1 + ring * segments
        faces.append(np.stack([a + j, b + j, b + jn], 1))
        faces.append(np.stack([a + j, b + jn, a + jn], 1))
    return verts, np.concatenate(faces), uv


def _sphere_mesh(n_theta: int = 12, n_phi: int = 24):
    """Unit sphere, outward normals."""
    theta = np.linspace(0, np.pi, n_theta + 1)
    phi = np.linspace(0, 2 * np.pi, n_phi, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    verts = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)
    uv = np.stack([p / (2 * np.pi), t / np.pi], -1).reshape(-1, 2)
    i, j = np.meshgrid(np.arange(n_theta), np.arange(n_phi), indexing="ij")
    jn = (j + 1) % n_phi
    a, b, c, d = i * n_phi + j, i * n_phi + jn, (i + 1) * n_phi + j, (i + 1) * n_phi + jn
    faces = np.concatenate([np.stack([a, c, d], -1).reshape(-1, 3), np.stack([a, d, b], -1).reshape(-1, 3)])
    # Orientation: outward normal needs (c - a) x (d - a) to point away from the centre.
    tv = verts[faces]
    n = np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0])
    outward = np.einsum("ij,ij->i", n, tv.mean(axis=1)) >= 0
    faces[~outward] = faces[~outward][:, ::-1]
    return verts, faces, uv


def _cylinder_mesh(segments: int = 32, rows: int = 4):
    """Open unit cylinder from z = 0 to 1, outward normals."""
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    z = np.linspace(0, 1, rows + 1)
    zz, pp = np.meshgrid(z, phi, indexing="ij")
    verts = np.stack([np.cos(pp), np.sin(pp), zz], -1).reshape(-1, 3)
    uv = np.stack([pp / (2 * np.pi), zz], -1).reshape(-1, 2)
    i, j = np.meshgrid(np.arange(rows), np.arange(segments), indexing="ij")
    jn = (j + 1) % segments
    a, b, c, d = i * segments + j, i * segments + jn, (i + 1) * segments + j, (i + 1) * segments + jn
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    tv = verts[faces]
    n = np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0])
    radial = tv.mean(axis=1) * np.array([1, 1, 0])
    outward = np.einsum("ij,ij->i", n, radial) >= 0
    faces[~outward] = faces[~outward][:, ::-1]
    return verts, faces, uv


# ------------------------------------------------------------------------------------------
# Materials and emission, evaluated by Mitsuba at sample points of every triangle
# ------------------------------------------------------------------------------------------

def _evaluate_materials(scene: Scene, shapes: list, where: str) -> None:
    """Fill tri_rho, back_rho, tri_emission and the approximation record, shape by shape.

    Each triangle gets ``n`` sample points (``_sample_counts``: enough for every texel of a bitmap
    it covers) and, at each, one incident direction drawn cosine-weighted over the hemisphere and
    one BSDF sample (``bsdf.sample`` with random lobe choice). The mean reflected weight is the
    hemispherical-hemispherical albedo (what a diffuse surface of the same reflected power has),
    the mean weight sent to the other side the transmittance, both per side. Every triangle uses
    the same direction samples, so for a non-diffuse BSDF their shared error is removed by scaling
    to a shape-wide estimate from ``_SHAPE_SAMPLES`` lanes (exact for a spatially constant BSDF).
    One vectorised Mitsuba call per batch of ``_BATCH`` lanes.
    """
    for index, shape in enumerate(shapes):
        tris = np.flatnonzero(scene.tri_shape == index)
        if len(tris) == 0:
            continue
        sid = scene.shape_ids[index]
        bsdf, emitter = shape.bsdf(), shape.emitter()
        non_diffuse = bsdf is not None and bool(int(bsdf.flags()) & int(_non_diffuse_flags()))
        leaf = is_leaf(bsdf)
        # a leaf's lobes are evaluated, not sampled (``_leaf_optics``), and exact at every point
        exact = leaf and _lambertian(scene, shape, bsdf, tris)
        # several lobes (a blend of diffuse ones too): the lobe choice is sampled, so it needs samples
        mixed = not exact and (non_diffuse or (bsdf is not None and bsdf.component_count() > 1))
        counts = _sample_counts(scene, tris, (bsdf, emitter), minimum=_DIRECTIONS if mixed else _POINTS)
        scene.tri_leaf[tris] = leaf
        for lo, hi in _batches(counts):
            part = tris[lo:hi]
            owner = np.repeat(np.arange(len(part)), counts[lo:hi])
            index_in_tri = np.arange(len(owner)) - np.repeat(np.cumsum(counts[lo:hi]) - counts[lo:hi], counts[lo:hi])
            si, qmc = _material_interactions(scene, shape, part, owner, index_in_tri,
                                             grid=np.repeat(np.sqrt(counts[lo:hi]).astype(np.int64), counts[lo:hi]))
            if exact:
                _leaf_optics(scene, bsdf, si, owner, part, qmc, f"{where}: shape '{sid}'")
            elif bsdf is not None:
                for side, rho, tau in ((+1.0, scene.tri_rho, scene.tri_transmittance),
                                       (-1.0, scene.back_rho, scene.back_transmittance)):
                    refl, trans, spec, vmin, vmax = _hemispherical(bsdf, si, owner, len(part), qmc, side)
                    if side > 0:
                        if vmin < -1e-6:
                            raise SceneError(f"{where}: shape '{sid}': reflectance {vmin:.3g} < 0; "
                                             "give a reflectance between 0 and 1")
                        if vmax > 1 + 1e-4 and not non_diffuse:
                            raise SceneError(f"{where}: shape '{sid}': reflectance {vmax:.3g} > 1 breaks "
                                             "energy conservation; scale the BSDF's reflectance below 1")
                        scene.tri_specular[part] = spec
                    rho[part], tau[part] = refl, trans
            if emitter is not None:
                si.wi = mi.Vector3f(0, 0, 1)
                radiance = _rows(emitter.eval(si), len(owner))
                if not np.all(np.isfinite(radiance)):
                    raise SceneError(f"{where}: shape '{sid}': emitter radiance is NaN or Inf; give finite values")
                if radiance.min() < 0:
                    raise SceneError(f"{where}: shape '{sid}': emitter radiance {radiance.min():.3g} < 0; "
                                     "radiance must be non-negative; give the emitter a radiance >= 0")
                scene.tri_emission[part] = np.pi * _triangle_means(radiance, owner, len(part))
        if mixed:
            _match_shape_estimate(scene, shape, bsdf, tris)
        for arr in (scene.tri_rho, scene.back_rho, scene.tri_transmittance, scene.back_transmittance,
                    scene.tri_specular):
            arr[tris] = np.clip(arr[tris], 0.0, 1.0)
        if bsdf is not None:
            _record_approximation(scene, sid, bsdf, tris, non_diffuse and not leaf, leaf=leaf)


#: Sample points per triangle: least for a diffuse BSDF (one direction each is exact), least for a
#: non-diffuse one (each point also samples a direction), per texel of a bitmap a triangle covers.
_POINTS, _DIRECTIONS, _PER_TEXEL = 16, 64, 16
#: Lanes of the shape-wide estimate of a non-diffuse BSDF (points by area, directions, lobes).
_SHAPE_SAMPLES = 1 << 15
#: Most samples per triangle, and per Dr.Jit launch.
_MAX_PER_TRIANGLE, _BATCH = 1 << 16, 1 << 21
#: Transmittance or non-diffuse reflectance above which a shape is recorded and warned about.
_APPROX_MIN = 1e-3


def _non_diffuse_flags():
    return (mi.BSDFFlags.Glossy | mi.BSDFFlags.Delta | mi.BSDFFlags.DiffuseTransmission
            | mi.BSDFFlags.Null)


def _texel_density(objects) -> float:
    """Texels per unit of uv area of the finest bitmap in the given BSDF/emitter (0 without one)."""
    density = 0.0
    for obj in objects:
        if obj is None:
            continue
        params = mi.traverse(obj)
        for key in params.keys():
            if not key.endswith("data"):
                continue
            shape = getattr(params[key], "shape", ())
            if len(shape) != 3:
                continue
            scale = 1.0
            to_uv = key[: -len("data")] + "to_uv"
            if to_uv in params.keys():
                m = np.array(params[to_uv].matrix, dtype=np.float64).reshape(3, 3)
                scale = abs(np.linalg.det(m[:2, :2]))
            density = max(density, shape[0] * shape[1] * scale)
    return density


def _sample_counts(scene: Scene, tris: np.ndarray, objects, *, minimum: int) -> np.ndarray:
    """(n,) int samples per triangle: ``minimum``, or ``_PER_TEXEL`` per texel covered if more,
    rounded up to a square (``_grid_points``) and at most ``_MAX_PER_TRIANGLE``."""
    counts = np.full(len(tris), minimum, np.int64)
    density = _texel_density(objects)
    if density > 0 and scene.vertex_uv is not None:
        uv = np.nan_to_num(scene.vertex_uv[scene.faces[tris]])
        e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
        texels = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) * density
        counts = np.maximum(counts, np.ceil(_PER_TEXEL * texels).astype(np.int64))
    side = np.ceil(np.sqrt(np.minimum(counts, _MAX_PER_TRIANGLE))).astype(np.int64)
    return side * side  # a square number: a side x side grid of sub-triangles


def _batches(counts: np.ndarray):
    """(lo, hi) triangle ranges whose samples fit in one launch of ``_BATCH`` lanes."""
    ends = np.cumsum(counts)
    lo = 0
    while lo < len(counts):
        base = ends[lo - 1] if lo else 0
        hi = max(lo + 1, int(np.searchsorted(ends, base + _BATCH, side="right")))
        yield lo, hi
        lo = hi


def _golden(d: int) -> np.ndarray:
    """(d,) steps of the generalised golden-ratio (R_d) low-discrepancy sequence in d dimensions."""
    phi = 2.0
    for _ in range(64):
        phi = (1.0 + phi) ** (1.0 / (d + 1))
    return (1.0 / phi) ** np.arange(1, d + 1)


#: 8 dimensions: 2 for the point on the triangle, 2 for the incident direction, 3 for the BSDF
#: sample, 1 for picking a triangle by area (shape-wide estimate).
_ALPHA = _golden(8)


def _grid_points(m: np.ndarray, k: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Point (a, b) of sub-triangle k of the m x m equal sub-triangles of the unit triangle.

    Returns barycentric (u, v), (N,) each. Row i (along v = 0) holds m - i upward then m - i - 1
    downward sub-triangles, so row i starts at k = i (2m - i). (a, b) is a point of the unit triangle
    (a + b <= 1), the same jittered offset in every sub-triangle would alias against a texel grid,
    so callers pass a low-discrepancy one per lane: stratified sampling, every lane the same area.
    """
    m = m.astype(np.int64)
    i = np.floor(m - np.sqrt(np.maximum(m * m - k, 0))).astype(np.int64)
    i -= (i * (2 * m - i) > k)                                   # float rounding, either way
    i += ((i + 1) * (2 * m - i - 1) <= k) & (i + 1 < m)
    r = k - i * (2 * m - i)
    up = r < m - i
    j = np.where(up, r, r - (m - i))
    u = np.where(up, i + a, i + 1 - a)
    v = np.where(up, j + b, j + 1 - b)
    return u / m, v / m


def _material_interactions(scene: Scene, shape, tris: np.ndarray, owner: np.ndarray, index: np.ndarray,
                           grid: np.ndarray | None = None):
    """SurfaceInteraction3f at sample points: lane k on triangle ``tris[owner[k]]``.

    ``index`` (N,) int is each lane's position in the low-discrepancy sequence. With ``grid`` (N,)
    int each lane gets its own cell of a grid x grid subdivision of the triangle (``index`` then runs
    over grid^2) and a point in it from the sequence; without, the sequence spreads the points over
    the whole triangle (uniform by area). Returns (si, qmc (N, 5)
    float in [0, 1): the remaining dimensions, for the direction and the BSDF sample).
    """
    seq = np.mod(0.5 + index[:, None] * _ALPHA[None, :7], 1.0)               # (N, 7)
    root = np.sqrt(seq[:, 0])                                                # square to triangle,
    u, v = root * (1 - seq[:, 1]), root * seq[:, 1]                          # area-preserving
    if grid is not None:
        u, v = _grid_points(grid, index, u, v)
    w = np.stack([1 - u - v, u, v], 1)                                       # (N, 3) barycentric
    faces = scene.faces[tris][owner]
    pts = np.einsum("nj,njc->nc", w, scene.vertices[faces])
    nrm = scene.tri_normal[tris][owner]
    if scene.vertex_uv is not None:
        uv = np.nan_to_num(np.einsum("nj,njc->nc", w, scene.vertex_uv[faces]))
    else:
        uv = np.zeros((len(pts), 2))
    si = dr.zeros(mi.SurfaceInteraction3f, len(pts))
    si.p = _points(pts)
    si.n = _points(nrm, mi.Normal3f)
    si.sh_frame = mi.Frame3f(si.n)
    si.uv = mi.Point2f(to_float(uv[:, 0]), to_float(uv[:, 1]))
    si.shape = mi.ShapePtr(shape)
    si.prim_index = to_uint(scene.tri_face[tris][owner])
    si.wi = mi.Vector3f(0, 0, 1)
    return si, seq[:, 2:]


def _hemispherical(bsdf, si, owner: np.ndarray, n: int, qmc: np.ndarray, side: float):
    """Hemispherical reflectance and transmittance of one side of every triangle.

    Incident directions are cosine-weighted over the side's hemisphere, and each lane draws one BSDF
    sample (lobe choice included) in importance transport mode (energy, no 1/eta^2 radiance
    scaling), so the mean weight returned to the same side is the albedo and the mean weight
    through to the other side the transmittance; the sampled lobe's type gives the part of the
    reflectance that is not diffuse.

    Returns
    -------
    reflectance, transmittance, non_diffuse : (n, 3) float each; min, max : float over single lanes
    of the reflected weight (for a diffuse BSDF the reflectance itself)
    """
    r = np.sqrt(qmc[:, 0])
    phi = 2 * np.pi * qmc[:, 1]
    z = np.sqrt(np.maximum(0.0, 1 - qmc[:, 0])) * side
    si.wi = mi.Vector3f(to_float(r * np.cos(phi)), to_float(r * np.sin(phi)), to_float(z))
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    bs, weight = bsdf.sample(ctx, si, to_float(qmc[:, 2]), mi.Point2f(to_float(qmc[:, 3]), to_float(qmc[:, 4])))
    lanes = len(owner)
    weight = np.nan_to_num(_rows(weight, lanes), nan=0.0, posinf=0.0, neginf=0.0)
    cos_out = np.broadcast_to(np.array(mi.Frame3f.cos_theta(bs.wo).numpy(), dtype=np.float64).reshape(-1), (lanes,))
    kind = np.broadcast_to(np.array(bs.sampled_type.numpy(), dtype=np.int64).reshape(-1), (lanes,))
    same = (cos_out * side) > 0
    diffuse = (kind & int(mi.BSDFFlags.DiffuseReflection)) != 0
    refl = np.where(same[:, None], weight, 0.0)
    return (_triangle_means(refl, owner, n), _triangle_means(weight - refl, owner, n),
            _triangle_means(np.where(diffuse[:, None], 0.0, refl), owner, n),
            float(refl.min()), float(refl.max()))


#: Slack of the loader's leaf checks: float32 textures and evaluation.
_LEAF_SLACK = 1e-4


def _lobe_albedos(bsdf, si, qmc: np.ndarray, *, swap: bool = False) -> dict:
    """pi * eval / |cos theta_o| per lane for incidence on each side and ``wo`` on each side.

    Returns {(side, out): (N, 3) float}, side +1 front / -1 back incidence, out +1 the incident side
    (reflection) / -1 the other (transmission): the lobes' albedos at each point where they are
    Lambertian in the triangle's frame. The incident direction comes from ``qmc[:, 0:2]``
    (cosine-weighted), the outgoing one from ``qmc[:, 3:5]`` kept away from grazing (cos >= 0.1, where
    float32 would blur the ratio); ``swap`` exchanges the two, for a second, independent pair.
    Importance mode: ``si.wi`` is where the light arrives (a ``twosided`` pair's front BSDF answers
    for light arriving on the front). NaN or Inf values come out as -1 or 2, which the checks refuse.
    """
    a, b = (qmc[:, 3:5], qmc[:, 0:2]) if swap else (qmc[:, 0:2], qmc[:, 3:5])
    lanes = len(qmc)
    r, phi, z = np.sqrt(a[:, 0]), 2 * np.pi * a[:, 1], np.sqrt(np.maximum(0.0, 1 - a[:, 0]))
    z_out = np.sqrt(1 - 0.99 * b[:, 0])
    r_out, phi_out = np.sqrt(np.maximum(0.0, 1 - z_out * z_out)), 2 * np.pi * b[:, 1]
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    values = {}
    for side in (+1.0, -1.0):
        si.wi = mi.Vector3f(to_float(r * np.cos(phi)), to_float(r * np.sin(phi)), to_float(z * side))
        for out in (+1.0, -1.0):
            wo = mi.Vector3f(to_float(r_out * np.cos(phi_out)), to_float(r_out * np.sin(phi_out)), to_float(z_out * side * out))
            value = _rows(bsdf.eval(ctx, si, wo), lanes) * (np.pi / z_out)[:, None]
            values[side, out] = np.nan_to_num(value, nan=-1.0, posinf=2.0, neginf=-1.0)
    return values


#: Points over a shape at which ``_lambertian`` compares two direction pairs.
_PROBE = 4096


def _lambertian(scene: Scene, shape, bsdf, tris: np.ndarray) -> bool:
    """True when a leaf-like BSDF's lobes are Lambertian in the triangles' own frame, so that
    ``_leaf_optics`` reads them exactly: at ``_PROBE`` points spread over the shape by area, two
    independent pairs of directions give the same albedos (``_lobe_albedos``). False for a leaf
    under a normal or bump map, whose lobes follow a tilted normal: the loader then measures it by
    sampling, like any other BSDF."""
    area = scene.tri_area[tris]
    index = np.arange(_PROBE)
    owner = np.minimum(np.searchsorted(np.cumsum(area) / area.sum(), np.mod(0.5 + index * _ALPHA[7], 1.0)),
                       len(tris) - 1)
    si, qmc = _material_interactions(scene, shape, tris, owner, index)
    one, two = _lobe_albedos(bsdf, si, qmc), _lobe_albedos(bsdf, si, qmc, swap=True)
    return all(np.allclose(one[k], two[k], rtol=1e-3, atol=_LEAF_SLACK) for k in one)


def _leaf_optics(scene: Scene, bsdf, si, owner: np.ndarray, part: np.ndarray, qmc: np.ndarray,
                 label: str) -> None:
    """Reflectance and transmittance of both sides of leaf triangles (``leaf.is_leaf``), exact.

    A leaf's lobes are Lambertian (``_lambertian`` checked it): ``eval`` returns albedo / pi *
    |cos theta_o| for any pair of directions, so pi * eval / |cos theta_o| is the albedo of the lobe
    ``wo`` falls in, at that very point (``_lobe_albedos``: one incident direction per lane and one
    outgoing direction on each side). Fills ``tri_rho``, ``back_rho``, ``tri_transmittance``,
    ``back_transmittance`` (per-triangle means of the (N, 3) lane values) and a zero ``tri_specular``
    for the triangles ``part`` (n,) int, lane k on ``part[owner[k]]``. Every lane is checked, so a texture is checked at every sample point
    (``_PER_TEXEL`` per texel): SceneError, named by ``label``, for a value below 0, reflectance +
    transmittance above 1 on either side, or front and back transmittances that differ (Mitsuba's
    ``twosided`` picks the nested BSDF by the side facing the camera in its path tracer and by the
    side the light arrives on in light tracing, which agree only when both transmit alike).
    """
    n = len(part)
    lane_values = _lobe_albedos(bsdf, si, qmc)
    varying = any(np.ptp(v, axis=0).max() > _LEAF_SLACK for v in lane_values.values())
    uv = np.array(si.uv.numpy(), dtype=np.float64).reshape(2, -1).T if varying and scene.vertex_uv is not None else None

    def at(lane: int) -> str:
        return f" (at uv {uv[lane, 0]:.3g}, {uv[lane, 1]:.3g})" if uv is not None else ""

    for side, name in ((+1.0, "front"), (-1.0, "back")):
        refl, trans = lane_values[side, +1.0], lane_values[side, -1.0]
        for what, values in (("reflectance", refl), ("transmittance", trans)):
            lane, channel = np.unravel_index(np.argmin(values), values.shape)
            if values[lane, channel] < -_LEAF_SLACK:
                raise SceneError(f"{label}: {name} {what} {values[lane, channel]:.3g} < 0{at(lane)}; give the "
                                 f"leaf a {what} between 0 and 1 everywhere")
        total = refl + trans
        lane, channel = np.unravel_index(np.argmax(total), total.shape)
        if total[lane, channel] > 1 + _LEAF_SLACK:
            raise SceneError(f"{label}: {name} reflectance {refl[lane, channel]:.3g} + transmittance "
                             f"{trans[lane, channel]:.3g} = {total[lane, channel]:.3g} > 1{at(lane)} breaks energy "
                             "conservation; lower the leaf's textures so that reflectance + transmittance <= 1 "
                             "everywhere (the rest is absorbed)")
    front, back = lane_values[+1.0, -1.0], lane_values[-1.0, -1.0]
    gap = np.abs(front - back)
    lane, channel = np.unravel_index(np.argmax(gap), gap.shape)
    if gap[lane, channel] > _LEAF_SLACK + 1e-3 * max(front[lane, channel], back[lane, channel]):
        raise SceneError(
            f"{label}: its front side transmits {front[lane, channel]:.3g} and its back side "
            f"{back[lane, channel]:.3g}{at(lane)}; light must pass through a leaf alike both ways (Mitsuba's "
            "twosided picks the nested BSDF by the side facing the camera, so the path tracer would apply the "
            "front leaf's transmittance to light arriving on the back): give both leaves of the twosided BSDF "
            "the same transmittance (only the reflectance may differ per side)")
    scene.tri_rho[part] = _triangle_means(lane_values[+1.0, +1.0], owner, n)
    scene.back_rho[part] = _triangle_means(lane_values[-1.0, +1.0], owner, n)
    scene.tri_transmittance[part] = _triangle_means(front, owner, n)
    scene.back_transmittance[part] = _triangle_means(back, owner, n)
    scene.tri_specular[part] = 0.0


def _match_shape_estimate(scene: Scene, shape, bsdf, tris: np.ndarray) -> None:
    """Scale a non-diffuse shape's per-triangle values to a shape-wide estimate of many samples.

    The per-triangle estimates share one set of directions, so their error is common to all of them;
    ``_SHAPE_SAMPLES`` lanes (points by area over the whole shape, each with its own direction and
    lobe choice) fix the area mean, and each triangle keeps its ratio to it (its texture's variation).
    """
    area = scene.tri_area[tris]
    index = np.arange(_SHAPE_SAMPLES)
    pick = np.mod(0.5 + index * _ALPHA[7], 1.0)
    owner = np.minimum(np.searchsorted(np.cumsum(area) / area.sum(), pick), len(tris) - 1)
    si, qmc = _material_interactions(scene, shape, tris, owner, index)
    count = np.bincount(owner, minlength=len(tris))
    for side, pairs in ((+1.0, (scene.tri_rho, scene.tri_transmittance, scene.tri_specular)),
                        (-1.0, (scene.back_rho, scene.back_transmittance))):
        estimates = _hemispherical(bsdf, si, owner, len(tris), qmc, side)
        for arr, est in zip(pairs, estimates):
            wide = (est * count[:, None]).sum(0) / _SHAPE_SAMPLES            # (C,) area mean
            per_tri = (arr[tris] * area[:, None]).sum(0) / area.sum()
            ratio = np.divide(wide, per_tri, out=np.ones_like(wide), where=per_tri > 0)
            arr[tris] = np.where(per_tri > 0, arr[tris] * ratio, wide)


def _triangle_means(values: np.ndarray, owner: np.ndarray, n: int) -> np.ndarray:
    """(N, C) lane values to (n, C) per-triangle means (lanes grouped by ``owner``)."""
    count = np.bincount(owner, minlength=n).astype(np.float64)
    sums = np.stack([np.bincount(owner, weights=values[:, c], minlength=n) for c in range(values.shape[1])], 1)
    return sums / np.maximum(count, 1)[:, None]


def _record_approximation(scene: Scene, sid: str, bsdf, tris: np.ndarray, non_diffuse: bool, *,
                          leaf: bool = False) -> None:
    """Warn and record in ``scene.approximations`` what the diffuse, opaque model loses for a shape.
    A ``leaf`` BSDF's diffuse transmission is modelled (``tri_leaf``: the hierarchical core carries
    it to the other side; a legacy solve counts it in ``model_error`` and says so when it matters),
    so a leaf loses nothing here: it was said lost on every leaf scene while the default solve
    carried it."""
    area = scene.tri_area[tris]
    mean = lambda a: (a[tris] * area[:, None]).sum(0) / area.sum()  # noqa: E731
    rho, spec = mean(scene.tri_rho), mean(scene.tri_specular)
    lost = np.zeros_like(rho) if leaf else np.maximum(mean(scene.tri_transmittance), mean(scene.back_transmittance))
    if not non_diffuse and lost.max() < _APPROX_MIN:
        return
    name = "leaf" if is_leaf(bsdf) else bsdf.class_name()
    cutout = name in ("MaskBSDF", "NullBSDF", "Null")
    parts = []
    if lost.max() >= _APPROX_MIN:
        how = "is an opacity mask" if cutout else "transmits light"
        parts.append(f"BSDF '{name}' {how}: {lost.max():.0%} of the light reaching it passes through in "
                     f"Mitsuba; mirad treats it as an opaque diffuse surface with albedo {rho.max():.3g}, "
                     "so the light through it is lost")
    if spec.max() >= _APPROX_MIN:
        parts.append(f"{'it' if parts else f'BSDF {name!r}'} reflects {spec.max():.0%} specularly or glossily, "
                     "which mirad spreads diffusely")
    if not parts:
        parts.append(f"BSDF '{name}' is not diffuse; mirad uses its hemispherical albedo {rho.max():.3g}")
    what = ("opacity" if cutout else "transmission") if lost.max() >= _APPROX_MIN else (
        "non-diffuse reflection" if spec.max() >= _APPROX_MIN else "none")
    scene.non_diffuse_shapes.append(sid)
    scene.approximations.append({"shape": sid, "bsdf": name, "what": what, "area": float(area.sum()),
                                 "albedo": rho, "transmitted": lost, "non_diffuse": spec})
    _warn_once(scene, f"shape '{sid}': " + "; ".join(parts) + " (see scene.approximations)")


def _rows(spectrum, count: int) -> np.ndarray:
    """A Dr.Jit colour (possibly of width 1) as a (count, 3) float64 array."""
    arr = np.array(spectrum.numpy(), dtype=np.float64)
    arr = arr.T if arr.ndim == 2 and arr.shape[0] == 3 else arr.reshape(-1, 3)
    return np.broadcast_to(arr, (count, 3)).copy() if len(arr) != count else arr
