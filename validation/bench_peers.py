"""Per-leaf absorbed light: mirad against the tools plant scientists use (issue 19), back to back.

One canopy of about 1,000 translucent leaves (2,000 leaf triangles from the generator of
``scenes/canopy-scale``, a ``leaf`` BSDF on both sides, a soil ground), lit by a sun and a
uniform sky from ``mirad.sky.sun_and_sky``. The yardstick is one cached high-sample path-traced
reference of both sides of every leaf triangle (``mirad.reference.cached_reference``); a side's
reference radiosity B = rho H_own + tau H_other gives each side's irradiance H, and a leaf
absorbs sum over its triangles and sides of (1 - rho - tau) H A (``export.absorbed_power``).

Each side is warmed up (one untimed run), then timed at a sweep of settings on the same machine:

1. **mirad**, ``core="hierarchical"`` at a sweep of tolerances, measured over the leaf shapes
   (``error_shapes``); per-leaf absorbed power from its per-triangle table
   (``export.triangle_table``, the sum over each leaf's triangles).
2. **Mitsuba's path tracer** as a per-leaf estimator (``mirad.reference.triangle_reference``, an
   independent seed) at a sweep of paths per leaf-triangle side.
3. **Radiance** through ``pyradiance``: the same triangles written as polygons (``rad_text``),
   leaves as ``BRTDfunc`` with the front and back diffuse reflectance and the diffuse
   transmittance of the ``leaf`` BSDF per channel (exact: Radiance's ``trans`` cannot express
   them, see ``rad_text``), the soil as a diffuse ``plastic``, the sun as a distant ``light``
   source whose direct normal irradiance is the Mitsuba sun's, the sky as a ``glow`` over the
   whole sphere (Mitsuba's ``constant`` emitter shines from below the horizon too). ``rtrace -I``
   gives irradiance; per leaf-triangle side, the direct sun at ``points`` stratified points
   (``-ab 0``) plus the ambient (indirect and sky) light at ``ambient`` points, each the full
   irradiance less its direct part at the same point (``-dj 0``: the same shadow ray both times).
4. **Helios** through ``pyhelios3d`` (its radiation model needs an NVIDIA GPU with OptiX, or a
   Vulkan driver: a GPU's, or a software one such as Mesa's lavapipe): a one-patch run in a child
   process first (``helios_blocker``); when that fails or crashes, the script says why and skips it.

A peer that is not installed is skipped with one line (``pip install -e ".[peers]"``).

Error: per leaf, area-weighted relative L1 of absorbed power, sum |P - P_ref| / sum P_ref over
the leaves (P in W, so leaves weigh by their area times their flux), per channel, averaged over
the channels. The time each side needs for 2 % and 1 % is interpolated log-log between its sweep
points. ``--record`` appends the table, date and machine to validation/RESULTS.md.

Usage (from the repository root; the scene, its .rad and the reference cache go to ``--work``)::

    python validation/bench_peers.py --work peers-work [--record]
    python validation/bench_peers.py --work peers-work --quick      # tiny settings, for development
"""

from __future__ import annotations

import argparse
import datetime as _dt
import importlib.util
import math
import os
import re
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

RESULTS = REPO / "validation" / "RESULTS.md"
TARGETS = (0.02, 0.01)

# ---------------- the canopy's optics and light (docs/leaves.md, docs/skies.md) ---------------------------
#: Leaf reflectance and transmittance per RGB channel, the same on both sides (a bare ``leaf``).
LEAF_RHO = (0.08, 0.30, 0.06)
LEAF_TAU = (0.05, 0.22, 0.03)
#: Soil (ground) diffuse reflectance.
SOIL_RHO = (0.25, 0.20, 0.15)
#: Sun: azimuth and elevation (degrees), direct normal irradiance (W/m^2); sky: horizontal W/m^2.
SUN = dict(azimuth=135.0, elevation=50.0, direct_normal=600.0)
SKY_IRRADIANCE = 120.0
#: Radiance's sun: a distant source of this full angle (degrees) and the radiance that gives the
#: Mitsuba sun's direct normal irradiance; shadow rays go to its centre (``-dj 0``), as to
#: Mitsuba's delta sun.
RAD_SUN_ANGLE = 0.533

# ---------------- sweeps -------------------------------------------------------------------------------------
FULL = dict(leaves=1000, reference=65536, tolerances=(0.9, 0.6, 0.4, 0.2, 0.1, 0.05, 0.02),
            pt=(64, 256, 1024, 4096, 16384),
            radiance=("p4 a1 ab2 ad128 as32 aa0.2 ar32", "p16 a4 ab3 ad64 as0 aa0", "p16 a4 ab4 ad128 as0 aa0",
                      "p16 a4 ab5 ad256 as0 aa0"),
            helios=("d100 s100 k3", "d100 s1000 k3", "d1000 s5000 k4"))
QUICK = dict(leaves=60, reference=1024, tolerances=(0.1, 0.05), pt=(16, 64),
             radiance=("p4 a1 ab2 ad64 as16 aa0.2 ar16",), helios=("d10 s50 k2",))


# ------------------------------------------------------------------------------------------
# The scene
# ------------------------------------------------------------------------------------------

def _canopy_module():
    """scenes/canopy-scale/make.py as a module (its ``plan`` and ``leaves``)."""
    spec = importlib.util.spec_from_file_location("canopy_scale_make", REPO / "scenes" / "canopy-scale" / "make.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def lights() -> tuple[dict, dict]:
    """(sun, sky): the Mitsuba emitter dicts of ``mirad.sky.sun_and_sky`` (a ``directional`` sun,
    ``direction`` pointing from the sun; a ``constant`` sky); the scene and its .rad both use them."""
    from mirad import sky

    both = sky.sun_and_sky(**SUN, diffuse_irradiance=SKY_IRRADIANCE, sky="uniform", up="+z")
    return both["sun"], both["sky"]


def make_scene(work, *, leaves: int = 1000, seed: int = 0) -> Path:
    """Write ``work/scene.xml`` (+ ground.ply, plant-K.ply): about ``leaves`` diamond leaves of 2
    triangles each (the canopy-scale generator's plants and crowns), a ``leaf`` BSDF
    (``LEAF_RHO``, ``LEAF_TAU``), a soil ground, and ``mirad.sky.sun_and_sky`` (uniform sky:
    Mitsuba's ``constant`` emitter, and a ``directional`` sun). Returns the XML path."""
    from mirad import sky

    canopy = _canopy_module()
    from meshgen import grid, ply_shape, write_ply  # scenes/_tools, on the path once canopy is loaded

    out = Path(work)
    out.mkdir(parents=True, exist_ok=True)
    plants, per = canopy.plan(2 * leaves)
    rng = np.random.default_rng(seed)
    side = int(math.ceil(math.sqrt(plants)))
    half = 0.5 * side * canopy.SPACING + 1.0
    rgb = lambda v: ", ".join(f"{c:g}" for c in v)  # noqa: E731
    body = (f'    <bsdf type="leaf" id="leaf">\n        <rgb name="reflectance" value="{rgb(LEAF_RHO)}"/>\n'
            f'        <rgb name="transmittance" value="{rgb(LEAF_TAU)}"/>\n    </bsdf>\n'
            f'    <bsdf type="diffuse" id="soil"><rgb name="reflectance" value="{rgb(SOIL_RHO)}"/></bsdf>\n\n')
    sun, uniform = lights()
    body += "    " + sky.write_sky({"sun": sun, "sky": uniform}).strip().replace("\n", "\n    ") + "\n\n"
    cells = max(4, 2 * side)
    write_ply(out / "ground.ply", grid((-half, -half, 0), (2 * half, 0, 0), (0, 2 * half, 0), cells, cells))
    body += ply_shape("ground", "ground.ply", "soil")
    total = 0
    for k in range(plants):
        gx, gy = k % side, k // side
        x = (gx - 0.5 * (side - 1)) * canopy.SPACING + rng.uniform(-0.2, 0.2)
        y = (gy - 0.5 * (side - 1)) * canopy.SPACING + rng.uniform(-0.2, 0.2)
        h = rng.uniform(0.9, 1.3) * max(1.0, per / 210) ** (1 / 3)
        mesh = canopy.leaves(rng, per, (x, y, h))
        write_ply(out / f"plant-{k + 1}.ply", mesh)
        total += len(mesh[1])
        body += ply_shape(f"plant-{k + 1}", f"plant-{k + 1}.ply", "leaf")
    path = out / "scene.xml"
    path.write_text(f'<scene version="3.0.0">\n    <!-- validation/bench_peers.py: {plants} plants x {per} '
                    f'translucent leaves, seed {seed}: {total} leaf triangles. -->\n'
                    f'    <integrator type="path"/>\n\n{body}</scene>\n')
    return path


def leaf_index(scene) -> tuple[np.ndarray, int]:
    """(leaf (T,) int, L): the leaf (connected piece of a leaf shape's mesh, ``mirad.organs``) of
    every input triangle, -1 on triangles that are not leaves; L leaves."""
    from mirad.organs import triangle_components

    comp, _, _ = triangle_components(scene.vertices, scene.faces, scene.tri_shape)
    leafy = np.asarray(scene.tri_leaf, bool)
    _, leaf = np.unique(comp[leafy], return_inverse=True)
    out = np.full(scene.triangle_count, -1, np.int64)
    out[leafy] = leaf.reshape(-1)
    return out, int(leaf.max()) + 1 if leafy.any() else 0


# ------------------------------------------------------------------------------------------
# Absorbed power and its error
# ------------------------------------------------------------------------------------------

def irradiance_from_radiosity(b_front, b_back, rho_front, rho_back, tau) -> tuple[np.ndarray, np.ndarray]:
    """Each side's irradiance (H_front, H_back), (K, C) W/m^2, of a translucent leaf from its
    radiosities (K, C) W/m^2: B_front = rho_front H_front + tau H_back and B_back = rho_back
    H_back + tau H_front (no emission; docs/leaves.md), solved per triangle and channel.

    >>> h = irradiance_from_radiosity(np.array([[0.5]]), np.array([[0.7]]), np.array([[0.1]]),
    ...                               np.array([[0.1]]), np.array([[0.3]]))
    >>> [round(float(x[0, 0]), 6) for x in h]
    [2.0, 1.0]
    """
    b_f, b_b, r_f, r_b, t = (np.asarray(x, np.float64) for x in (b_front, b_back, rho_front, rho_back, tau))
    det = r_f * r_b - t * t
    if np.any(np.abs(det) < 1e-12):
        raise ValueError("reflectance front x back equals transmittance^2: the two sides' radiosities do not "
                         "determine their irradiances; give the leaf other optics")
    return (r_b * b_f - t * b_b) / det, (r_f * b_b - t * b_f) / det


def absorbed_from_irradiance(h_front, h_back, rho_front, rho_back, tau_front, tau_back, area) -> np.ndarray:
    """(K, C) W: (1 - rho - tau) H A per side, front plus back: ``export.absorbed_power``'s
    definition, for any per-triangle irradiances (a reference, a path tracer, a peer)."""
    a = np.asarray(area, np.float64)[:, None]
    return ((1 - np.asarray(rho_front) - np.asarray(tau_front)) * h_front
            + (1 - np.asarray(rho_back) - np.asarray(tau_back)) * h_back) * a


def per_leaf(values: np.ndarray, leaf: np.ndarray, n_leaves: int) -> np.ndarray:
    """(L, C) sums of per-triangle values (K, C) over each leaf (``leaf`` (K,) int, -1 ignored)."""
    values = np.asarray(values, np.float64)
    keep = leaf >= 0
    return np.stack([np.bincount(leaf[keep], weights=values[keep, c], minlength=n_leaves)
                     for c in range(values.shape[1])], 1)


def leaf_error(power: np.ndarray, reference: np.ndarray) -> float:
    """Per-leaf area-weighted relative L1 of absorbed power: per channel, sum over leaves of
    |P - P_ref| over sum of P_ref (P in W: each leaf weighs by its area times its flux), then the
    mean over the channels.

    >>> round(leaf_error(np.array([[1.0, 2.0], [3.0, 2.0]]), np.array([[2.0, 2.0], [2.0, 2.0]])), 6)
    0.25
    """
    p, r = np.asarray(power, np.float64), np.asarray(reference, np.float64)
    return float(np.mean(np.abs(p - r).sum(0) / r.sum(0)))


def time_at(target: float, seconds, errs) -> float:
    """Seconds at which the error first reaches ``target``, log-log interpolated between sweep
    points (``mirad.measure.time_at_error``; nan when it never does)."""
    from mirad.measure import time_at_error

    t, _ = time_at_error(seconds, errs, target)
    return float("nan") if t is None else t


class Leaves:
    """The leaf triangles of a scene and how per-side radiosity becomes per-leaf absorbed power."""

    def __init__(self, scene):
        self.scene = scene
        self.leaf, self.count = leaf_index(scene)
        self.tris = np.flatnonzero(self.leaf >= 0)
        t = self.tris
        self.rho_f, self.rho_b = scene.tri_rho[t], scene.back_rho[t]
        self.tau_f, self.tau_b = scene.tri_transmittance[t], scene.back_transmittance[t]
        if not np.allclose(self.tau_f, self.tau_b):
            raise ValueError("leaves with a different transmittance per side are not reciprocal (docs/leaves.md)")
        self.area = scene.tri_area[t]

    def from_radiosity(self, b_front, b_back) -> np.ndarray:
        """(L, C) W absorbed per leaf from the radiosity of both sides of the leaf triangles (K, C)."""
        h_f, h_b = irradiance_from_radiosity(b_front, b_back, self.rho_f, self.rho_b, self.tau_f)
        return self.from_irradiance(h_f, h_b)

    def from_irradiance(self, h_front, h_back) -> np.ndarray:
        """(L, C) W absorbed per leaf from the irradiance of both sides of the leaf triangles (K, C)."""
        p = absorbed_from_irradiance(h_front, h_back, self.rho_f, self.rho_b, self.tau_f, self.tau_b, self.area)
        return per_leaf(p, self.leaf[self.tris], self.count)


# ------------------------------------------------------------------------------------------
# Radiance: the same geometry as a .rad scene
# ------------------------------------------------------------------------------------------

def rad_text(scene, *, sun_direction, sun_irradiance, sky_radiance, sun_angle: float = RAD_SUN_ANGLE) -> str:
    """The scene as Radiance input: every input triangle a ``polygon`` (the user's frame, m; vertices
    in the triangle's winding, so Radiance's front is Mitsuba's), leaf triangles with one
    ``BRTDfunc`` per distinct optics and the others with a diffuse ``plastic``, plus the lights.

    Materials, and where Radiance differs:

    - leaf: ``BRTDfunc`` with no specular or directional parts and diffuse front reflectance
      ``tri_rho``, back reflectance ``back_rho`` and diffuse transmittance ``tri_transmittance``,
      per channel: the ``leaf`` BSDF exactly. (``trans`` could not: its diffuse reflectance is
      C (1 - t) and transmittance C t with one scalar t for all channels, so the ratio tau/rho
      would have to be the same in every channel; here it is not.)
    - other surfaces: ``plastic`` with specularity and roughness 0, a Lambertian of reflectance
      ``tri_rho``; one-sided surfaces are black behind in mirad, but Radiance's ``plastic`` shades
      both sides alike (the ground's underside is never seen here).
    - sun: a ``light`` on a distant ``source`` of ``sun_angle`` degrees whose radiance gives
      ``sun_irradiance`` (W/m^2, (3,)) on a plane facing it; Mitsuba's directional sun is a delta.
    - sky: a ``glow`` on a ``source`` of 360 degrees (no shadow rays; reached by ambient rays
      only) of radiance ``sky_radiance`` (W/(m^2 sr), (3,)): Mitsuba's ``constant`` emitter.

    Returns the text; ``rad_polygons`` counts what it wrote.
    """
    sun_direction = np.asarray(sun_direction, np.float64)
    omega = 2 * math.pi * (1 - math.cos(math.radians(sun_angle) / 2))
    sun_l = np.asarray(sun_irradiance, np.float64) / omega
    lines = ["# written by validation/bench_peers.py from the mirad scene " + (scene.source or ""),
             f"void light solar 0 0 3 {sun_l[0]:.9g} {sun_l[1]:.9g} {sun_l[2]:.9g}",
             f"solar source sun 0 0 4 {sun_direction[0]:.9g} {sun_direction[1]:.9g} {sun_direction[2]:.9g} "
             f"{sun_angle:g}",
             "void glow skyglow 0 0 4 " + " ".join(f"{x:.9g}" for x in sky_radiance) + " 0",
             "skyglow source skydome 0 0 4 0 0 1 360", ""]
    leafy = np.asarray(scene.tri_leaf, bool)
    optics = np.concatenate([scene.tri_rho, scene.back_rho, scene.tri_transmittance], 1)
    optics[~leafy, 3:] = 0.0
    keys, material = np.unique(np.round(np.c_[leafy, optics], 9), axis=0, return_inverse=True)
    material = material.reshape(-1)
    for m, key in enumerate(keys):
        v = key[1:]
        if key[0]:
            lines.append(f"void BRTDfunc mat{m} 10 0 0 0 0 0 0 0 0 0 . 0 9 "
                         + " ".join(f"{x:.9g}" for x in v[:9]))
        else:
            lines.append(f"void plastic mat{m} 0 0 5 {v[0]:.9g} {v[1]:.9g} {v[2]:.9g} 0 0")
    corners = scene.to_user(scene.tri_vertices)
    for t in range(scene.triangle_count):
        c = corners[t].ravel()
        lines.append(f"mat{material[t]} polygon t{t} 0 0 9 " + " ".join(f"{x:.9g}" for x in c))
    return "\n".join(lines) + "\n"


def rad_polygons(text: str) -> tuple[int, float]:
    """(count, total area m^2) of the polygons in Radiance input ``text`` (a check of ``rad_text``)."""
    count, area = 0, 0.0
    for line in text.splitlines():
        words = line.split()
        if len(words) > 2 and words[1] == "polygon":
            p = np.array(words[6:], np.float64).reshape(-1, 3)
            area += 0.5 * sum(np.linalg.norm(np.cross(p[k] - p[0], p[k + 1] - p[0])) for k in range(1, len(p) - 1))
            count += 1
    return count, area


def triangle_points(corners: np.ndarray, n: int) -> np.ndarray:
    """(K, n, 3) points stratified over each of K triangles (K, 3, 3): n = m^2 sub-triangle
    centroids of the triangle's regular m x m subdivision (its barycentric grid), so every point
    stands for the same area; n must be a square."""
    m = int(round(math.sqrt(n)))
    if m * m != n:
        raise ValueError(f"points per triangle {n}: give a square number (1, 4, 9, 16, ...)")
    bary = []
    for i in range(m):
        for j in range(m - i):
            bary.append(((i + 1 / 3) / m, (j + 1 / 3) / m))          # upward sub-triangle
            if i + j < m - 1:
                bary.append(((i + 2 / 3) / m, (j + 2 / 3) / m))      # downward sub-triangle
    b = np.array(bary)
    w = np.c_[1 - b.sum(1), b]                                        # (n, 3) weights of corners 0, 1, 2
    return np.einsum("nk,tkd->tnd", w, corners)


def parse_radiance(spec: str) -> dict:
    """'p16 a1 ab3 ad256 as64 aa0.1 ar64' -> points 16, ambient points 1, rtrace -ab 3 -ad 256 ..."""
    out = {"points": 1, "ambient": 1, "params": []}
    for word in spec.split():
        if word.startswith("p"):
            out["points"] = int(word[1:])
        elif word.startswith("a") and word[1].isdigit():
            out["ambient"] = int(word[1:])
        else:
            out["params"] += [f"-{word[:2]}", word[2:]]
    return out


class RadiancePeer:
    """Per-leaf absorbed power from Radiance's ``rtrace -I`` (see the module docstring)."""

    name = "Radiance (pyradiance)"

    def __init__(self, scene, leaves: Leaves, work: Path, nproc: int):
        import pyradiance as pr

        self.pr, self.leaves, self.nproc = pr, leaves, nproc
        sun, sky = lights()
        self.text = rad_text(scene, sun_direction=-np.asarray(sun["direction"], np.float64),
                             sun_irradiance=sun["irradiance"]["value"], sky_radiance=sky["radiance"]["value"])
        work.mkdir(parents=True, exist_ok=True)
        (work / "scene.rad").write_text(self.text)
        self.octree = work / "scene.oct"
        self.octree.write_bytes(pr.oconv(str(work / "scene.rad"), warning=False))
        corners = scene.to_user(scene.tri_vertices[leaves.tris])
        self.corners = corners
        self.normal = scene.tri_normal[leaves.tris]
        self.offset = 1e-4 * scene.diagonal

    def _irradiance(self, points: np.ndarray, normals: np.ndarray, params: list) -> np.ndarray:
        """(N, 3) W/m^2 of ``rtrace -I`` at points (N, 3) facing normals (N, 3)."""
        rays = np.c_[points + normals * self.offset, normals].astype(np.float32)
        out = self.pr.rtrace(rays.tobytes(), self.octree, header=False, inform="f", outform="f",
                             irradiance=True, nproc=self.nproc, params=["-h-", *params])
        return np.frombuffer(out, np.float32).reshape(-1, 3).astype(np.float64)

    def run(self, spec: str) -> np.ndarray:
        cfg = parse_radiance(spec)
        k = len(self.corners)
        h = []
        for sign in (1.0, -1.0):                                      # front, back
            n = sign * self.normal
            pd = triangle_points(self.corners, cfg["points"])         # (K, p, 3) direct points
            pa = triangle_points(self.corners, cfg["ambient"])        # (K, a, 3) ambient points
            p_n, a_n = pd.shape[1], pa.shape[1]
            direct = self._irradiance(np.r_[pd.reshape(-1, 3), pa.reshape(-1, 3)],
                                      np.r_[np.repeat(n, p_n, 0), np.repeat(n, a_n, 0)],
                                      ["-ab", "0", "-av", "0", "0", "0", "-dj", "0"])
            full = self._irradiance(pa.reshape(-1, 3), np.repeat(n, a_n, 0),
                                    ["-dj", "0", "-av", "0", "0", "0", *cfg["params"]])
            d_pts = direct[: k * p_n].reshape(k, p_n, 3).mean(1)
            d_amb = direct[k * p_n:].reshape(k, a_n, 3)
            ambient = (full.reshape(k, a_n, 3) - d_amb).mean(1)
            h.append(d_pts + ambient)
        return self.leaves.from_irradiance(h[0], h[1])


# ------------------------------------------------------------------------------------------
# Helios (pyhelios3d)
# ------------------------------------------------------------------------------------------

#: A radiation run on one patch (one band, a sun, a sky, a few rays), run by ``helios_blocker`` in a
#: child process: a Vulkan driver that starts the model may still crash in ``runBand`` (Mesa 22.3's
#: lavapipe ends the process with SIGSEGV there), and a crash in the benchmark's own process would
#: take the other sides' results with it.
HELIOS_PROBE = """
from pyhelios import Context, RadiationModel
with Context() as ctx:
    uuid = ctx.addPatch()
    with RadiationModel(ctx) as rad:
        rad.disableMessages()
        source = rad.addCollimatedRadiationSource((0.0, 0.0, 1.0))
        rad.addRadiationBand("R")
        rad.disableEmission("R")
        rad.setSourceFlux(source, "R", 100.0)
        rad.setDiffuseRadiationFlux("R", 10.0)
        rad.setDirectRayCount("R", 10)
        rad.setDiffuseRayCount("R", 10)
        rad.runBand(["R"])
        flux = rad.getAbsorbedFlux(["R"], [uuid])
print("absorbed", flux)
"""


def helios_blocker(timeout: float = 300.0) -> str | None:
    """None when pyhelios3d's radiation model runs here (``HELIOS_PROBE`` in a child process),
    else the reason it does not."""
    if importlib.util.find_spec("pyhelios") is None:
        return "pyhelios3d is not installed (No module named 'pyhelios'); pip install -e \".[peers]\""
    return probe_blocker(HELIOS_PROBE, "a one-patch radiation run", timeout)


def probe_blocker(code: str, what: str, timeout: float) -> str | None:
    """Run Python ``code`` in a child process: None when it exits cleanly, else why not, naming
    ``what`` it was: its last exception ("module.Type: message", on one line), the signal that
    ended it, or the time it ran past ``timeout`` (s)."""
    try:
        run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return f"{what} did not finish in {timeout:g} s"
    if run.returncode == 0:
        return None
    # (the child's last words: its last exception's line to the end)
    lines = run.stderr.strip().splitlines()
    raised = [i for i, line in enumerate(lines) if re.match(r"[\w.]+: ", line)]
    said = " ".join(" ".join(lines[raised[-1]:]).split())[:700] if raised else ""
    if run.returncode < 0:
        name = signal.Signals(-run.returncode).name
        return f"{what} crashed ({name}): its GPU or Vulkan driver cannot run it here{'; ' + said if said else ''}"
    return said or f"{what} failed (exit status {run.returncode})"


def parse_helios(spec: str) -> dict:
    """'d100 s1000 k3' -> direct rays 100, diffuse rays 1000, scattering depth 3 per primitive."""
    out = {"direct": 100, "diffuse": 1000, "depth": 3}
    names = {"d": "direct", "s": "diffuse", "k": "depth"}
    for word in spec.split():
        out[names[word[0]]] = int(word[1:])
    return out


class HeliosPeer:
    """Per-leaf absorbed power from Helios's radiation model (pyhelios3d).

    The same triangles (the user's frame) in a Helios ``Context``, one band per RGB channel
    ("R", "G", "B") with per-primitive ``reflectivity_<band>`` and ``transmissivity_<band>``
    (leaves: the ``leaf`` BSDF's rho and tau, two-sided; the ground: the soil's rho, one-sided,
    ``twosided_flag`` 0), the sun as a collimated source towards it with the Mitsuba sun's direct
    normal irradiance, the sky as the diffuse flux on a horizontal plane, over the whole sphere
    (``enableBelowHorizonDiffuseRadiation``, as Mitsuba's ``constant`` emitter). Absorbed flux
    per primitive (W/m^2, both faces) times its area is the absorbed power.

    Only the geometry and optics run without a GPU; the radiation model needs OptiX or Vulkan
    (``helios_blocker``). On the 2-core development machine neither was present, and Mesa 22.3's
    lavapipe (Debian 12's software Vulkan) starts the model but ends the process with SIGSEGV in
    ``runBand``: this class has not been run past that point there.
    """

    name = "Helios (pyhelios3d)"
    BANDS = ("R", "G", "B")

    def __init__(self, scene, leaves: Leaves):
        from pyhelios import Context

        self.leaves, self.scene = leaves, scene
        self.ctx = Context()
        corners = scene.to_user(scene.tri_vertices).reshape(-1, 3)
        faces = np.arange(len(corners)).reshape(-1, 3)
        self.uuids = list(self.ctx.addTrianglesFromArrays(corners, faces))
        leafy = np.asarray(scene.tri_leaf, bool)
        for c, band in enumerate(self.BANDS):
            self.ctx.setPrimitiveDataFloat(self.uuids, f"reflectivity_{band}", scene.tri_rho[:, c].tolist())
            tau = np.where(leafy, scene.tri_transmittance[:, c], 0.0)
            self.ctx.setPrimitiveDataFloat(self.uuids, f"transmissivity_{band}", tau.tolist())
        ground = [u for u, leaf in zip(self.uuids, leafy) if not leaf]
        if ground:
            self.ctx.setPrimitiveDataUInt(ground, "twosided_flag", 0)
        self.area = np.asarray(self.ctx.getPrimitiveArea(self.uuids), np.float64)

    def run(self, spec: str) -> np.ndarray:
        from pyhelios import RadiationModel

        cfg = parse_helios(spec)
        sun, sky = lights()
        with RadiationModel(self.ctx) as rad:
            rad.disableMessages()
            source = rad.addCollimatedRadiationSource(tuple(-np.asarray(sun["direction"], np.float64)))
            for c, band in enumerate(self.BANDS):
                rad.addRadiationBand(band)
                rad.disableEmission(band)
                rad.setSourceFlux(source, band, float(sun["irradiance"]["value"][c]))
                rad.setDiffuseRadiationFlux(band, float(math.pi * sky["radiance"]["value"][c]))
                rad.setScatteringDepth(band, cfg["depth"])
                rad.setDirectRayCount(band, cfg["direct"])
                rad.setDiffuseRayCount(band, cfg["diffuse"])
            rad.enableBelowHorizonDiffuseRadiation()
            rad.runBand(list(self.BANDS))
            flux = rad.getAbsorbedFlux(list(self.BANDS), self.uuids)
        power = np.stack([np.asarray(flux[b], np.float64) for b in self.BANDS], 1) * self.area[:, None]
        lv = self.leaves
        return per_leaf(power[lv.tris], lv.leaf[lv.tris], lv.count)


# ------------------------------------------------------------------------------------------
# The run
# ------------------------------------------------------------------------------------------

def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", default="peers-work", help="folder for the scene, .rad, octree and reference cache")
    parser.add_argument("--quick", action="store_true", help="tiny settings (development)")
    parser.add_argument("--leaves", type=int, default=None, help="about this many leaves (default 1,000)")
    parser.add_argument("--reference", type=int, default=None, help="reference paths per leaf-triangle side")
    parser.add_argument("--tolerances", default=None, help="mirad tolerances, comma-separated")
    parser.add_argument("--pt", default=None, help="path-tracer paths per leaf-triangle side, comma-separated")
    parser.add_argument("--radiance", default=None, help="Radiance settings, ';'-separated (see parse_radiance)")
    parser.add_argument("--helios", default=None, help="Helios settings, ';'-separated (see parse_helios)")
    parser.add_argument("--peers", default="mirad,pt,radiance,helios", help="which sides to run")
    parser.add_argument("--nproc", type=int, default=2, help="rtrace processes (Dr.Jit uses every core)")
    parser.add_argument("--record", action="store_true", help="append the table to validation/RESULTS.md")
    args = parser.parse_args(argv)
    cfg = dict(QUICK if args.quick else FULL)
    if args.leaves:
        cfg["leaves"] = args.leaves
    if args.reference:
        cfg["reference"] = args.reference
    if args.tolerances:
        cfg["tolerances"] = tuple(float(x) for x in args.tolerances.split(","))
    if args.pt:
        cfg["pt"] = tuple(int(x) for x in args.pt.split(","))
    if args.radiance:
        cfg["radiance"] = tuple(args.radiance.split(";"))
    if args.helios:
        cfg["helios"] = tuple(args.helios.split(";"))
    sides = set(args.peers.split(","))

    import mirad
    from mirad import export
    from mirad.reference import cached_reference, triangle_reference
    from mirad.validate import machine

    work = Path(args.work).resolve()
    path = make_scene(work / f"canopy-{cfg['leaves']}", leaves=cfg["leaves"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = mirad.load_scene(str(path))
    lv = Leaves(scene)
    print(f"scene {path}: {lv.count:,} leaves, {len(lv.tris):,} leaf triangles, {scene.triangle_count:,} triangles",
          flush=True)

    # ---------------- the reference: both sides of every leaf triangle ------------------------------------
    t0 = time.perf_counter()
    ref_sides = [cached_reference(scene, cache_dir=work / "cache", samples_per_triangle=cfg["reference"],
                                  seed=12345, triangles=lv.tris, side=s, quiet=False) for s in ("front", "back")]
    p_ref = lv.from_radiosity(ref_sides[0].radiosity, ref_sides[1].radiosity)
    # its own noise: the reference's standard error carried through the same (linear) map, as a per-leaf
    # expected |error| (half-normal mean sqrt(2/pi) sigma), relative like leaf_error
    noise = _reference_noise(lv, ref_sides, p_ref)
    print(f"reference: {cfg['reference']:,} paths per leaf-triangle side, "
          f"{'cached' if ref_sides[0].from_cache else f'{time.perf_counter() - t0:.0f} s'}; "
          f"noise {noise:.3%}", flush=True)

    rows, curves, skipped = [], {}, []

    def record(side: str, setting: str, seconds: float, power: np.ndarray, extra: str = "") -> None:
        err = leaf_error(power, p_ref)
        rows.append((side, setting, seconds, err, extra))
        curves.setdefault(side, []).append((seconds, err))
        print(f"| {side} | {setting} | {seconds:.2f} | {err:.2%} | {extra} |", flush=True)

    # ---------------- mirad --------------------------------------------------------------------------------
    if "mirad" in sides:
        # the tolerance over the leaves (``error_shapes``), what this table measures: over every
        # shape the soil's area would dilute their error
        leaf_shapes = sorted({str(scene.shape_ids[k]) for k in np.unique(scene.tri_shape[lv.tris])})

        def solve(tol):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                return mirad.solve(scene, tolerance=tol, seed=0, core="hierarchical", quiet=True,
                                   error_shapes=leaf_shapes)

        solve(cfg["tolerances"][0])                                   # warm-up
        for tol in cfg["tolerances"]:
            t = time.perf_counter()
            sol = solve(tol)
            dt = time.perf_counter() - t
            table = export.triangle_table(sol)
            power = per_leaf(table["absorbed"][lv.tris], lv.leaf[lv.tris], lv.count)
            st = sol.stats
            record("mirad", f"tolerance {tol}", dt, power,
                   f"estimate {st['estimated_error']:.2%}, {st['links']:,} links, {st['rays']:,} rays")

    # ---------------- Mitsuba's path tracer ------------------------------------------------------------------
    if "pt" in sides:
        def trace(spp):
            return [triangle_reference(scene, samples_per_triangle=spp, seed=7, triangles=lv.tris, side=s)
                    for s in ("front", "back")]

        trace(cfg["pt"][0])                                          # warm-up
        for spp in cfg["pt"]:
            t = time.perf_counter()
            est = trace(spp)
            dt = time.perf_counter() - t
            record("Mitsuba path tracer", f"{spp:,} paths per leaf-triangle side", dt,
                   lv.from_radiosity(est[0].radiosity, est[1].radiosity), f"{est[0].paths + est[1].paths:,} paths")

    # ---------------- Radiance -------------------------------------------------------------------------------
    if "radiance" in sides:
        try:
            import pyradiance  # noqa: F401
        except ImportError as exc:
            skipped.append(f"Radiance: skipped, pyradiance is not installed ({exc}); pip install -e \".[peers]\"")
            print(skipped[-1], flush=True)
        else:
            peer = RadiancePeer(scene, lv, work / f"canopy-{cfg['leaves']}", args.nproc)
            peer.run(cfg["radiance"][0])                             # warm-up
            for spec in cfg["radiance"]:
                t = time.perf_counter()
                power = peer.run(spec)
                record("Radiance", spec, time.perf_counter() - t, power)

    # ---------------- Helios ---------------------------------------------------------------------------------
    if "helios" in sides:
        reason = helios_blocker()
        if reason is not None:
            skipped.append(f"Helios: skipped, its radiation model does not start here: {reason}")
            print(skipped[-1], flush=True)
        else:
            peer = HeliosPeer(scene, lv)
            peer.run(cfg["helios"][0])                               # warm-up
            for spec in cfg["helios"]:
                t = time.perf_counter()
                power = peer.run(spec)
                record("Helios", spec, time.perf_counter() - t, power)

    # ---------------- the table ------------------------------------------------------------------------------
    summary = []
    for side, pts in curves.items():
        sec, err = zip(*pts)
        # (where a side's quickest point is already within a target, its time is an upper bound)
        from mirad.measure import time_at_error

        at = [time_at_error(sec, err, t) for t in TARGETS]
        summary.append(f"| {side} | " + " | ".join("not reached" if x is None else
                                                   f"{'at most ' if how == 'at most' else ''}{x:.2f} s" for x, how in at)
                       + f" | {min(err):.2%} |")
    head = (f"Canopy: {lv.count:,} translucent leaves ({len(lv.tris):,} leaf triangles, {scene.triangle_count:,} "
            f"in all), leaf rho {LEAF_RHO}, tau {LEAF_TAU}, soil {SOIL_RHO}; sun {SUN['direct_normal']:g} W/m^2 "
            f"direct normal at elevation {SUN['elevation']:g} deg, uniform sky {SKY_IRRADIANCE:g} W/m^2. "
            f"Reference: {cfg['reference']:,} paths per leaf-triangle side (noise {noise:.2%}).")
    table = ["| side | setting | seconds | per-leaf rel. L1 of absorbed power | notes |", "|---|---|---|---|---|",
             *(f"| {s} | {g} | {sec:.2f} | {e:.2%} | {x} |" for s, g, sec, e, x in rows)]
    summ = ["| side | seconds to 2 % | seconds to 1 % | lowest error |", "|---|---|---|---|", *summary]
    text = "\n".join([head, "", *table, "", *summ, "", *skipped])
    print("\n" + text, flush=True)
    if args.record:
        stamp = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
        with open(RESULTS, "a", encoding="utf-8") as f:
            f.write(f"\n## Peers: per-leaf absorbed light, mirad, Mitsuba's path tracer, Radiance, Helios "
                    f"({stamp}, {machine()})\n\n`python validation/bench_peers.py --record`: each side warmed up, "
                    "timed back to back in one run.\n\n" + text + "\n")
    return 0


def _reference_noise(lv: Leaves, sides, p_ref: np.ndarray) -> float:
    """The reference's own noise as a per-leaf error: its standard errors carried through the linear
    map radiosity -> absorbed power (triangles and sides independent), as the expected L1 of a
    half-normal, sqrt(2/pi) sigma, relative like ``leaf_error``."""
    r_f, r_b, t = lv.rho_f, lv.rho_b, lv.tau_f
    det = r_f * r_b - t * t
    # H_f = (r_b B_f - t B_b)/det, H_b = (r_f B_b - t B_f)/det; P = a [(1-r_f-t) H_f + (1-r_b-t) H_b]
    k_f = (1 - r_f - t) / det
    k_b = (1 - r_b - t) / det
    c_front = lv.area[:, None] * (k_f * r_b - k_b * t)               # dP / dB_front
    c_back = lv.area[:, None] * (k_b * r_f - k_f * t)                # dP / dB_back
    var = (c_front * sides[0].stderr) ** 2 + (c_back * sides[1].stderr) ** 2
    sigma = np.sqrt(per_leaf(var, lv.leaf[lv.tris], lv.count))
    return leaf_error(p_ref + sigma * math.sqrt(2 / math.pi), p_ref)


if __name__ == "__main__":
    sys.exit(main())
