"""Display of a radiosity solution: from a surface point to the leaf element under it, and images.

The shading of a point is the radiosity of the leaf element that contains it, as
radiance B / pi (flat), or the same values interpolated between the element
corners (smooth). Points are located with Mitsuba itself: the leaves of the
solution are uploaded once as one triangle mesh per side (front, back) in small
*locator* scenes, and a short ray along the surface normal, from just above the
point down through it, hits the leaf that contains it. This works for every
shape the same way: meshes, merged meshes (an ``mi.Scene`` loaded with
``optimize=True``), and analytic shapes whose true surface lies slightly off
their tessellation (the ray runs along the true normal, which is the radial
projection mirad uses for spheres and cylinders). Everything stays in Dr.Jit:
no loop over pixels, elements or links.

``render(scene, solution)`` draws an image from the scene's sensor with the
``radiosity`` integrator (``mirad/integrator.py``) holding that solution.
"""

from __future__ import annotations

import numpy as np

from . import _runtime  # noqa: F401  (LLVM set-up before mitsuba)
from .errors import OutputError, SettingsError

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

#: Locator rays start this fraction of the scene diagonal above the surface point.
LOCATE_OFFSET = 1e-4
#: Leaf slot of leaves without shadow-texture detail.
NO_DETAIL = 0xFFFFFFFF
#: Extra search depth below curved surfaces, relative to their radius (tessellation sagitta).
CURVED_DEPTH = 0.05


def _float(a) -> "mi.Float":
    return mi.Float(np.ascontiguousarray(a, dtype=np.float32))


def _uint(a) -> "mi.UInt32":
    return mi.UInt32(np.ascontiguousarray(a, dtype=np.uint32))


def _leaf_mesh(name: str, verts: np.ndarray):
    """A Mitsuba mesh whose face i is leaf i (verts (L, 3, 3) float)."""
    count = len(verts)
    mesh = mi.Mesh(name, 3 * count, count)
    params = mi.traverse(mesh)
    params["vertex_positions"] = _float(verts.reshape(-1))
    params["faces"] = _uint(np.arange(3 * count))
    params.update()
    return mi.load_dict({"type": "scene", "leaves": mesh})


def corner_values(solution, values: np.ndarray) -> np.ndarray:
    """(L, 3, C) per-corner values of every leaf for smooth display.

    Corners that coincide (same shape, side and position, and the same normal on flat shapes)
    get the area-weighted mean of the leaf ``values`` around them: (L, C) one value per leaf,
    or (L, 3, C) one per leaf corner.
    """
    values = np.asarray(values)
    if values.ndim == 2:
        values = np.repeat(values[:, None], 3, axis=1)
    a = solution._a
    verts = a["leaf_verts"]
    n_leaf = len(verts)
    tri = a["patch_tri"][a["leaf_patch"]]
    shape = a["triangle_shape"][tri]
    side = a["patch_side"][a["leaf_patch"]]
    curved = a["curve_radius"][tri] > 0
    diag = float(np.linalg.norm(a["vertices"].max(0) - a["vertices"].min(0))) or 1.0
    pos = np.round(verts.reshape(-1, 3) / (1e-6 * diag)).astype(np.int64)
    nrm = np.round(np.repeat(a["leaf_normal"], 3, axis=0) * 1e3).astype(np.int64)
    nrm[np.repeat(curved, 3)] = 0
    key = np.column_stack([np.repeat(shape, 3), np.repeat(side, 3), pos, nrm])
    _, inverse = np.unique(key, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    weight = np.repeat(solution.leaf_area, 3)
    n_key = inverse.max() + 1 if len(inverse) else 0
    c_count = values.shape[2]
    total = np.stack([np.bincount(inverse, weights=weight * values[:, :, c].ravel(), minlength=n_key)
                      for c in range(c_count)], 1)
    mean = total / np.maximum(np.bincount(inverse, weights=weight, minlength=n_key), 1e-300)[:, None]
    return mean[inverse].reshape(n_leaf, 3, c_count)


class Shading:
    """Solution data resident in Dr.Jit, and the point-to-leaf lookup.

    Parameters
    ----------
    solution : Solution with its scene attached (``solution.scene``)
    """

    def __init__(self, solution):
        scene = solution._require_scene()
        self.solution = solution
        self.scene = scene
        a = solution._a
        b = np.asarray(a["leaf_radiosity"], dtype=np.float64)
        if b.shape[1] == 1:
            b = np.repeat(b, 3, axis=1)
        side = a["patch_side"][a["leaf_patch"]]
        tri = a["patch_tri"][a["leaf_patch"]]
        self.n_leaf = len(b)
        self.leaf_tri = tri
        self.leaf_side = side
        # per-side locator scenes and their leaf numbering
        self.locators = []
        self.rows = []
        # Each leaf is lifted a quarter of the lookup offset along its own normal, so leaves of
        # different shapes that coincide (a box standing on the floor: its bottom face and the
        # floor under it) are apart and the downward lookup ray meets its own side's leaf first.
        lift = 0.25 * LOCATE_OFFSET * scene.diagonal
        lifted = a["leaf_verts"] + lift * a["leaf_normal"][:, None, :]
        for s in (0, 1):
            rows = np.flatnonzero(side == s)
            self.rows.append(rows)
            self.locators.append(_leaf_mesh(f"leaves_{s}", lifted[rows]) if len(rows) else None)
        self.row_dr = [_uint(r) if len(r) else None for r in self.rows]
        # values per leaf (flat) and per leaf corner (smooth), radiance = B / pi
        self.flat = [_float(b[:, c] / np.pi) for c in range(3)]
        # a leaf with shadow-texture detail brings its value at each corner, not its mean,
        # so the smooth leaves around a textured one meet its shadow instead of its average
        at_corner = np.repeat(b[:, None], 3, axis=1)
        from .solution import LEAF_CORNER_UV

        rows = solution.detail_leaves
        for k, uv in enumerate(LEAF_CORNER_UV):
            d = solution.detail_at(rows, np.tile(uv, (len(rows), 1)))
            at_corner[rows, k] += np.repeat(d, 3, axis=1) if d.shape[1] == 1 else d
        corners = corner_values(solution, np.maximum(at_corner, 0.0)) / np.pi    # (L, 3, 3)
        self.corners = [_float(corners[:, :, c].reshape(-1)) for c in range(3)]
        # shadow-texture detail (solver shadow_textures): a slot per leaf, bilinear textures
        rows = solution.detail_leaves
        self.detail_res = 0
        if len(rows):
            detail = np.asarray(a["leaf_detail"], np.float64)               # (T, R, R, C)
            if detail.shape[3] == 1:
                detail = np.repeat(detail, 3, axis=3)
            slot = np.full(self.n_leaf, NO_DETAIL, np.uint32)
            slot[rows] = np.arange(len(rows), dtype=np.uint32)
            self.detail_slot = _uint(slot)
            self.detail_res = detail.shape[1]
            self.detail = [_float(detail[..., c].reshape(-1) / np.pi) for c in range(3)]
        # shape of each leaf, and Mitsuba shape pointer -> mirad shape index
        self.leaf_shape = _uint(a["triangle_shape"][tri])
        shapes = list(scene.mi_scene.shapes())
        ids = [int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s))[0]) for s in shapes]
        table = np.full(max(ids) + 1, 0xFFFFFFFF, np.uint32)
        table[ids] = np.arange(len(shapes), dtype=np.uint32)
        self.shape_table = _uint(table)
        radius = np.zeros(len(shapes))
        np.maximum.at(radius, a["triangle_shape"], a["curve_radius"])
        self.shape_depth = _float(CURVED_DEPTH * radius)
        # fallback: mean radiance of each shape side
        means = np.zeros((2, len(shapes), 3))
        area = solution.leaf_area
        shp = a["triangle_shape"][tri]
        for c in range(3):
            for s in (0, 1):
                m = side == s
                tot = np.bincount(shp[m], weights=area[m] * b[m, c], minlength=len(shapes))
                means[s, :, c] = tot / np.maximum(np.bincount(shp[m], weights=area[m], minlength=len(shapes)), 1e-300)
        self.shape_mean = [[_float(means[s, :, c] / np.pi) for c in range(3)] for s in (0, 1)]
        self.offset = LOCATE_OFFSET * scene.diagonal
        # per-leaf reflectance and emission of the side (final gather)
        rho_front = a["triangle_rho"][tri]
        back_rho = a["back_rho"][tri] if "back_rho" in a else rho_front
        self.leaf_rho = np.where(side[:, None] == 1, back_rho, rho_front)
        self.leaf_emission = np.where(side[:, None] == 1, 0.0, a["triangle_emission"][tri])

    # --- lookup ------------------------------------------------------------------------------
    def shape_index(self, shape_ptr) -> "mi.UInt32":
        """mirad shape index of Mitsuba shape pointers (0xFFFFFFFF where none)."""
        reg = dr.reinterpret_array(mi.UInt32, shape_ptr)
        n = dr.width(self.shape_table)
        return dr.gather(mi.UInt32, self.shape_table, dr.minimum(reg, n - 1), reg < n)

    def locate(self, p, n, back, shape, active):
        """Leaf under surface points.

        Parameters
        ----------
        p, n : mi.Point3f, mi.Vector3f   points and their front (geometric) normals
        back : mi.Bool                   True where the back side is seen
        shape : mi.UInt32                mirad shape index of each point
        active : mi.Bool

        Returns
        -------
        (leaf mi.UInt32, barycentric mi.Point2f, found mi.Bool)
        """
        depth = dr.gather(mi.Float, self.shape_depth, dr.minimum(shape, dr.width(self.shape_depth) - 1))
        leaf = dr.zeros(mi.UInt32, dr.width(p))
        uv = dr.zeros(mi.Point2f, dr.width(p))
        found = dr.zeros(mi.Bool, dr.width(p))
        for s, locator in enumerate(self.locators):
            if locator is None:
                continue
            side_active = active & (back if s == 1 else ~back)
            for sign in (1.0, -1.0):  # from above, then (for the rare miss) from below
                todo = side_active & ~found
                ray = mi.Ray3f(p + n * (sign * self.offset), n * (-sign))
                ray.maxt = 2 * self.offset + depth
                pi = locator.ray_intersect_preliminary(ray, todo)
                hit = todo & pi.is_valid()
                row = dr.gather(mi.UInt32, self.row_dr[s], pi.prim_index, hit)
                ok = hit & (dr.gather(mi.UInt32, self.leaf_shape, row, hit) == shape)
                leaf = dr.select(ok, row, leaf)
                uv = dr.select(ok, pi.prim_uv, uv)
                found |= ok
        return leaf, uv, found

    def radiance(self, si, ray_d, active, *, smooth: bool):
        """Displayed radiance (Color3f) at surface interactions seen along ray_d."""
        shape = self.shape_index(si.shape)
        back = dr.dot(si.n, ray_d) > 0
        leaf, uv, found = self.locate(si.p, si.n, back, shape, active)
        vals = [dr.gather(mi.Float, ch, leaf, found) for ch in self.flat]
        textured = dr.zeros(mi.Bool, dr.width(leaf))
        if self.detail_res:
            # a leaf with shadow textures shows its own variation (flat value + texture detail),
            # which interpolating between corners would count a second time
            detail, textured = self.detail_radiance(leaf, uv, found)
            vals = [v + d for v, d in zip(vals, detail)]
        if smooth:
            w0 = 1 - uv.x - uv.y
            base = leaf * 3
            vals = [dr.select(textured, v, w0 * dr.gather(mi.Float, ch, base, found)
                              + uv.x * dr.gather(mi.Float, ch, base + 1, found)
                              + uv.y * dr.gather(mi.Float, ch, base + 2, found))
                    for v, ch in zip(vals, self.corners)]
        # fallback (no leaf found: a crack or a shape without elements): the shape side's mean
        safe = dr.minimum(shape, dr.width(self.shape_mean[0][0]) - 1)
        out = []
        for c in range(3):
            mean = dr.select(back, dr.gather(mi.Float, self.shape_mean[1][c], safe, active),
                             dr.gather(mi.Float, self.shape_mean[0][c], safe, active))
            out.append(dr.select(found, vals[c], mean))
        return mi.Color3f(*out), leaf, found

    def detail_radiance(self, leaf, uv, found) -> list:
        """Shadow-texture detail of the radiance (3 mi.Float) at leaf parameters uv (bilinear,
        clamped at the texture border, as ``shadows.bilinear``; zero on leaves without), and
        which points lie on leaves with detail (mi.Bool)."""
        r = self.detail_res
        slot = dr.gather(mi.UInt32, self.detail_slot, leaf, found)
        has = found & (slot != NO_DETAIL)
        x = dr.clip(uv.x * r - 0.5, 0.0, r - 1.0)
        y = dr.clip(uv.y * r - 0.5, 0.0, r - 1.0)
        i0 = dr.minimum(mi.UInt32(dr.floor(x)), max(r - 2, 0))
        j0 = dr.minimum(mi.UInt32(dr.floor(y)), max(r - 2, 0))
        tx, ty = x - mi.Float(i0), y - mi.Float(j0)
        i1, j1 = dr.minimum(i0 + 1, r - 1), dr.minimum(j0 + 1, r - 1)
        base = slot * (r * r)
        out = []
        for ch in self.detail:
            g = lambda i, j, ch=ch: dr.gather(mi.Float, ch, base + i * r + j, has)  # noqa: E731
            out.append(dr.lerp(dr.lerp(g(i0, j0), g(i0, j1), ty), dr.lerp(g(i1, j0), g(i1, j1), ty), tx))
        return out, has

    def gathered_radiance(self, si, ray_d, leaf, found, active, *, rays: int, seed: int):
        """One bounce of final gathering: (E + rho * H(x)) / pi with H gathered from all leaves."""
        back = dr.dot(si.n, ray_d) > 0
        n = dr.select(back, -si.n, si.n)
        valid = found & active
        dr.eval(si.p, n, leaf, valid)
        mask = np.asarray(valid.numpy(), dtype=bool)
        width = dr.width(si.p)
        pts = np.stack([np.asarray(si.p[i].numpy(), np.float64) for i in range(3)], 1)
        nrm = np.stack([np.asarray(n[i].numpy(), np.float64) for i in range(3)], 1)
        lf = np.asarray(leaf.numpy(), np.int64)
        result = np.zeros((width, 3))
        idx = np.flatnonzero(mask)
        if len(idx):
            h = self.solution.irradiance_at(pts[idx], nrm[idx], rays=rays, seed=seed)
            if h.shape[1] == 1:
                h = np.repeat(h, 3, axis=1)
            result[idx] = (self.leaf_emission[lf[idx]] + self.leaf_rho[lf[idx]] * h) / np.pi
        return mi.Color3f(*[_float(result[:, c]) for c in range(3)])


# ------------------------------------------------------------------------------------------
# Images
# ------------------------------------------------------------------------------------------

def render(scene, solution=None, *, spp: int = 4, seed: int = 0, smooth: bool = True,
           final_gather: bool = False, gather_rays: int = 4, sensor: int = 0, **solve_options) -> np.ndarray:
    """Image (H, W, 3) float32 of the radiosity solution, radiance in W/(m^2 sr), from the scene's sensor.

    Parameters
    ----------
    scene : mirad Scene, XML path, Mitsuba dict or mi.Scene
    solution : Solution or None
        The solution to show (its scene fingerprint must match); None solves the scene first
        with ``solve_options`` (``tolerance``, ``samples_per_link``, ...).
    spp : samples per pixel (>= 1)
    seed : seed of the pixel samples (same seed -> same image)
    smooth : interpolate between element corners (True) or show flat elements (False)
    final_gather : one bounce of gathering from the solution at each pixel's hit point
    gather_rays : shadow rays per leaf element in the final gather
    sensor : index of the sensor in the scene

    >>> img = mirad.render("scenes/cornell-box/scene.xml", spp=1, tolerance=0.1)  # doctest: +SKIP
    >>> img.shape                                                                  # doctest: +SKIP
    (256, 256, 3)
    """
    from . import solve
    from .integrator import make_integrator
    from .scene import load_scene

    check_spp(spp)
    loaded = load_scene(scene)
    if solution is None:
        solution = solve(loaded, **solve_options)
    elif solve_options:
        raise SettingsError(f"options {sorted(solve_options)} only apply when render() solves; "
                            "drop them or pass solution=None")
    if solution.scene is not loaded:
        solution.attach(loaded)
    sensors = loaded.mi_scene.sensors()
    if not sensors:
        raise SettingsError(f"'{loaded.source or '<scene>'}' has no sensor; add a <sensor> to render it")
    if not (0 <= sensor < len(sensors)):
        raise SettingsError(f"sensor={sensor} is out of range; the scene has {len(sensors)} sensor(s)")
    integrator = make_integrator(smooth=smooth, final_gather=final_gather, gather_rays=gather_rays, seed=seed)
    integrator.set_solution(loaded.mi_scene, solution)
    image = mi.render(loaded.mi_scene, integrator=integrator, sensor=sensor, spp=int(spp), seed=int(seed))
    return np.array(image, dtype=np.float32)[..., :3]


def check_spp(spp) -> int:
    if isinstance(spp, bool) or int(spp) != spp or spp < 1:
        raise SettingsError(f"spp={spp!r} must be an integer >= 1 (samples per pixel, e.g. 4)")
    return int(spp)


def srgb8(image: np.ndarray, *, exposure: float = 0.0) -> np.ndarray:
    """Tonemap linear radiance (H, W, 3) to 8-bit sRGB: scale by 2^exposure, clip, sRGB curve."""
    x = np.clip(np.nan_to_num(np.asarray(image, np.float64) * 2.0 ** exposure), 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(srgb * 255).astype(np.uint8)


def write_image(path, image: np.ndarray, *, png: bool = True, exposure: float = 0.0) -> list:
    """Write an image as OpenEXR (linear float RGB), and a tonemapped sRGB PNG beside it. Atomic.

    Returns the paths written.
    """
    from pathlib import Path

    from .export import exr_bytes, png_bytes
    from .solution import atomic_write

    path = Path(path)
    if path.suffix.lower() != ".exr":
        raise OutputError(f"image output '{path}' must end in .exr (linear float RGB)")
    data = exr_bytes({"R": image[..., 0], "G": image[..., 1], "B": image[..., 2]})
    written = []
    png_path = path.with_suffix(".png")
    png_data = png_bytes(srgb8(image, exposure=exposure)) if png else None
    atomic_write(path, lambda handle: handle.write(data))
    written.append(path)
    if png:
        atomic_write(png_path, lambda handle: handle.write(png_data))
        written.append(png_path)
    return written
