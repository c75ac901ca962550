"""Standard skies as Mitsuba emitters: uniform, CIE standard overcast, and sun + sky.

Each function returns a Mitsuba emitter dict (for ``mi.load_dict`` scene dicts) that Mitsuba's
path tracer renders and ``mirad.load_scene`` reads like any other emitter, parameterised by what
a user measures: the horizontal irradiance of the diffuse sky and the sun's direct normal or
horizontal irradiance, in W/m^2 per channel (any linear unit works: give PAR photon flux density
in umol/(m^2 s) and read absorbed power in umol/s; mirad never converts).

Sky models (theta from the zenith, radiance L in W/(m^2 sr)):

``uniform``   L = E_h / pi everywhere above the horizon (a ``constant`` emitter, which also shines
              from below the horizon where the scene has no ground; or, with ``ground``, an
              ``envmap`` whose lower half is the ground's glow).
``overcast``  the CIE standard overcast sky (Moon & Spencer 1942, CIE S 011 type 16):
              L(theta) = L_z (1 + 2 cos theta) / 3, so E_h = 7 pi L_z / 9; an ``envmap`` from a
              latitude-longitude bitmap computed here.
``sun``       a ``directional`` emitter from azimuth and elevation; its ``irradiance`` is the
              direct normal irradiance E_n (E_h = E_n sin(elevation)).

Below the horizon a sky is black (``ground=None``) or, with ``ground=rho_g``, the radiance of a
Lambertian ground of albedo rho_g lit by the horizontal irradiance of sky (and sun):
L_g = rho_g * E_h,total / pi.

Up axis and azimuth: ``up`` names the scene's vertical axis, "+z" by default (the shipped canopy
scenes are z-up; Mitsuba's own envmap is +y-up, handled through its ``to_world``). North is +y,
or -z when the up axis is y; east is north x up (+x for both +z and +y up). The sun's azimuth is
measured from north towards east, in degrees; its elevation from the horizon, in degrees.

The envmap's bitmap (``sky_bitmap``) has rows at theta_i = pi i / (rows - 1), as Mitsuba reads a
latitude-longitude map (row 0 at the zenith, the last at the nadir, linear interpolation between
rows), and its radiance is scaled so that the horizontal irradiance *of the interpolated map* is
exactly the one asked for. The horizon row holds the mean of the radiance just above and just
below it, so the interpolation error is second order in the row spacing on any plane.
See docs/skies.md.

>>> import mitsuba as mi                                                        # doctest: +SKIP
>>> scene = {"type": "scene", "sky": overcast_sky(120.0),                       # doctest: +SKIP
...          **sun_and_sky(azimuth=135, elevation=40, diffuse_irradiance=0, direct_normal=800)}
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from . import _runtime  # noqa: F401  (LLVM set-up before mitsuba)
from .errors import SettingsError
from .files import atomic_write, check_output, exr_bytes

import mitsuba as mi  # noqa: E402

__all__ = ["SKIES", "UP_AXES", "DEFAULT_ROWS", "axes", "sun_direction", "sky_bitmap", "uniform_sky",
           "overcast_sky", "sun", "sun_and_sky", "plane_irradiance", "overcast_tilted_irradiance",
           "uniform_tilted_irradiance", "sky_xml", "write_sky"]

#: Sky models by name (``sun_and_sky(sky=...)``, ``mirad sky MODEL``).
SKIES = ("uniform", "overcast")
#: Accepted names of the scene's up axis.
UP_AXES = ("+x", "-x", "+y", "-y", "+z", "-z", "x", "y", "z")
#: Rows of the latitude-longitude bitmap (odd: one row on the horizon). 257 rows put the
#: interpolation error of a plane's irradiance below 1e-4 (second order in pi / 256).
DEFAULT_ROWS = 257
#: Columns of the bitmap: the skies here do not depend on azimuth, so a few suffice (Mitsuba
#: needs at least 2).
COLUMNS = 8
#: Gauss-Legendre nodes per row interval when integrating the interpolated bitmap.
_QUADRATURE = 8


# ------------------------------------------------------------------------------------------
# Checks and frames
# ------------------------------------------------------------------------------------------

def _channels(value, name: str, fix: str) -> np.ndarray:
    """(3,) float64 from a number or 3 numbers, each finite and >= 0; SettingsError naming ``name``."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise SettingsError(f"{name}={value!r} is not a number; {fix}") from None
    if a.ndim == 0:
        a = np.repeat(a, 3)
    if a.shape != (3,):
        raise SettingsError(f"{name}={value!r} must be one number or 3 (R, G, B); {fix}")
    if not np.all(np.isfinite(a)):
        raise SettingsError(f"{name}={value!r} must be finite; {fix}")
    if np.any(a < 0):
        raise SettingsError(f"{name}={value!r} is negative; irradiance is >= 0 in every channel ({fix})")
    return a


def _ground(ground) -> float | None:
    if ground is None:
        return None
    if isinstance(ground, bool) or not isinstance(ground, (int, float, np.integer, np.floating)) \
            or not 0.0 <= float(ground) <= 1.0:
        raise SettingsError(f"ground={ground!r} must be a ground albedo between 0 and 1 (0: black below the "
                            "horizon), or None")
    return float(ground)


def axes(up: str = "+z") -> np.ndarray:
    """(3, 3) float: the unit vectors east, north and up (rows) of a scene whose up axis is ``up``.

    ``up`` is one of ``UP_AXES``: "+z" (default), "-z", "+y", "-y", "+x", "-x" ("z" means "+z").
    North is +y, or -z when the up axis is y; east = north x up.

    >>> axes("+z").tolist()
    [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    >>> axes("+y").tolist()
    [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]
    """
    if not isinstance(up, str) or up.strip().lower() not in UP_AXES:
        raise SettingsError(f"up={up!r} is not an axis; give one of +z, -z, +y, -y, +x, -x "
                            "(the scene's vertical; the shipped canopy scenes use +z)")
    text = up.strip().lower()
    sign = -1.0 if text.startswith("-") else 1.0
    index = "xyz".index(text[-1])
    u = np.zeros(3)
    u[index] = sign
    north = np.array([0.0, 0.0, -1.0]) if index == 1 else np.array([0.0, 1.0, 0.0])
    east = np.cross(north, u)
    return np.stack([east, north, u]) + 0.0    # + 0.0: no negative zeros


def sun_direction(azimuth: float, elevation: float, *, up: str = "+z") -> np.ndarray:
    """(3,) float: the unit vector from the scene towards the sun.

    azimuth : degrees from north towards east (any real number; taken modulo 360)
    elevation : degrees above the horizon, in (0, 90]

    >>> np.round(sun_direction(90, 45), 6).tolist()   # east, 45 degrees up
    [0.707107, 0.0, 0.707107]
    """
    if isinstance(azimuth, bool) or not isinstance(azimuth, (int, float, np.integer, np.floating)) \
            or not np.isfinite(azimuth):
        raise SettingsError(f"azimuth={azimuth!r} must be a finite number of degrees from north towards east")
    if isinstance(elevation, bool) or not isinstance(elevation, (int, float, np.integer, np.floating)) \
            or not np.isfinite(elevation) or not 0.0 < float(elevation) <= 90.0:
        raise SettingsError(f"elevation={elevation!r} must be the sun's angle above the horizon in degrees, in "
                            "(0, 90]; a sun at or below the horizon lights nothing: leave it out")
    elevation = float(elevation)
    east, north, u = axes(up)
    a, e = np.radians(float(azimuth)), np.radians(elevation)
    d = math.cos(e) * (math.sin(a) * east + math.cos(a) * north) + math.sin(e) * u
    d = np.where(np.abs(d) < 1e-15, 0.0, d)       # exact zeros along the axes (no -0.0 in files)
    return d / np.linalg.norm(d)


def _to_world(up: str) -> np.ndarray:
    """(4, 4) float: Mitsuba envmap frame (local +y up, u = 0 towards local -z) to the scene.

    Columns: local x -> east, local y -> up, local z -> -north (a rotation), so the map's u = 0
    column faces north and u grows towards east.
    """
    east, north, u = axes(up)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2] = east, u, -north
    return m + 0.0


# ------------------------------------------------------------------------------------------
# Bitmaps
# ------------------------------------------------------------------------------------------

def _profile(kind: str, cos_theta: np.ndarray) -> np.ndarray:
    """Relative sky radiance L / L_z above the horizon (same shape as cos_theta)."""
    if kind == "overcast":
        return (1.0 + 2.0 * cos_theta) / 3.0
    return np.ones_like(cos_theta)


def _row_thetas(rows: int) -> np.ndarray:
    return np.pi * np.arange(rows) / (rows - 1)


def _check_rows(rows) -> int:
    if isinstance(rows, bool) or not isinstance(rows, (int, np.integer)) or rows < 5 or rows % 2 == 0:
        raise SettingsError(f"rows={rows!r} must be an odd integer >= 5 (one row on the horizon), e.g. {DEFAULT_ROWS}")
    return int(rows)


def _row_values(kind: str, rows: int, below: float) -> np.ndarray:
    """(rows,) relative radiance per row: the sky above, ``below`` (relative) under, the mean on the horizon."""
    theta = _row_thetas(rows)
    values = np.where(theta < np.pi / 2, _profile(kind, np.cos(theta)), below)
    h = (rows - 1) // 2
    values[h] = 0.5 * (_profile(kind, np.zeros(1))[0] + below)
    return values


def plane_irradiance(row_radiance: np.ndarray, tilt: float | np.ndarray) -> np.ndarray:
    """Irradiance on planes tilted ``tilt`` (radians from facing up; (K,) or scalar) under an
    azimuth-independent latitude-longitude map whose rows hold ``row_radiance`` ((rows,) or
    (rows, C), W/(m^2 sr)) at theta_i = pi i / (rows - 1), interpolated linearly between rows as
    Mitsuba's ``envmap`` does. Returns (K,) or (K, C) float, W/m^2.

    The azimuthal integral of max(0, n . w) is done in closed form, the polar one with
    Gauss-Legendre nodes per row interval (exact to rounding for this interpolant).

    >>> round(float(plane_irradiance(np.ones(257), 0.0)), 6)    # L = 1 everywhere: pi
    3.141593
    """
    values = np.asarray(row_radiance, dtype=np.float64)
    scalar_c = values.ndim == 1
    values = values.reshape(len(values), -1)
    tilt_arr = np.atleast_1d(np.asarray(tilt, dtype=np.float64))
    rows = len(values)
    theta = _row_thetas(rows)
    x, w = np.polynomial.legendre.leggauss(_QUADRATURE)
    t = 0.5 * (x + 1.0)                                         # (Q,) in [0, 1]
    lo, hi = theta[:-1], theta[1:]
    th = lo[:, None] + (hi - lo)[:, None] * t[None, :]         # (rows-1, Q)
    weight = 0.5 * (hi - lo)[:, None] * w[None, :]              # (rows-1, Q)
    radiance = values[:-1, None, :] * (1 - t)[None, :, None] + values[1:, None, :] * t[None, :, None]
    # azimuthal integral of max(0, a cos(phi) + b), a = sin(tilt) sin(theta) >= 0, b = cos(tilt) cos(theta)
    a = np.sin(tilt_arr)[:, None, None] * np.sin(th)[None]
    b = np.cos(tilt_arr)[:, None, None] * np.cos(th)[None]
    ratio = np.clip(np.divide(-b, a, out=np.where(b >= 0, -np.inf, np.inf), where=a > 1e-300), -1.0, 1.0)
    phi0 = np.arccos(ratio)                                     # pi: lit all round, 0: not at all
    ring = 2.0 * (a * np.sin(phi0) + b * phi0)                  # (K, rows-1, Q)
    e = np.einsum("kiq,iq,iqc->kc", ring * np.sin(th)[None], weight, radiance)
    if scalar_c:
        e = e[:, 0]
    return e[0] if np.ndim(tilt) == 0 else e


def sky_bitmap(kind: str, irradiance, *, ground_radiance=0.0, rows: int = DEFAULT_ROWS,
               columns: int = COLUMNS) -> tuple[np.ndarray, np.ndarray]:
    """Latitude-longitude bitmap of a sky whose horizontal irradiance is ``irradiance``.

    kind : "overcast" or "uniform"
    irradiance : number or (3,), W/m^2: horizontal irradiance of the sky on an unobstructed
        upward plane (the interpolated map gives exactly this)
    ground_radiance : number or (3,), W/(m^2 sr): radiance below the horizon (0: black)
    rows : odd int >= 5; columns : int >= 2

    Returns (bitmap (rows, columns, 3) float32 W/(m^2 sr), zenith radiance L_z (3,) float64):
    row 0 is the zenith, row (rows - 1) / 2 the horizon, the last row the nadir (Mitsuba's
    ``envmap`` convention with its up axis local +y; ``overcast_sky`` sets the ``to_world``).

    >>> image, zenith = sky_bitmap("overcast", 7 * np.pi / 9)
    >>> image.shape, np.round(zenith, 4).tolist()
    ((257, 8, 3), [1.0, 1.0, 1.0])
    """
    if kind not in SKIES:
        raise SettingsError(f"sky {kind!r} is not a sky model; choose one of {', '.join(SKIES)}")
    e_h = _channels(irradiance, "irradiance", "give the sky's horizontal irradiance in W/m^2, e.g. 100")
    ground_l = _channels(ground_radiance, "ground_radiance", "give the radiance below the horizon in W/(m^2 sr)")
    rows = _check_rows(rows)
    if isinstance(columns, bool) or not isinstance(columns, (int, np.integer)) or columns < 2:
        raise SettingsError(f"columns={columns!r} must be an integer >= 2")
    # E_h of the interpolated map is linear in (L_z, L_g): E_h = L_z * A + L_g * B
    unit_sky = _row_values(kind, rows, 0.0)
    a_coef = float(plane_irradiance(unit_sky, 0.0))
    b_coef = float(plane_irradiance(_row_values(kind, rows, 1.0) - unit_sky, 0.0))
    zenith = np.maximum(e_h - ground_l * b_coef, 0.0) / a_coef
    theta = _row_thetas(rows)
    sky = np.where(theta < np.pi / 2, _profile(kind, np.cos(theta)), 0.0)[:, None] * zenith[None, :]
    below = np.where(theta > np.pi / 2, 1.0, 0.0)[:, None] * ground_l[None, :]
    values = sky + below
    h = (rows - 1) // 2
    values[h] = 0.5 * (_profile(kind, np.zeros(1))[0] * zenith + ground_l)
    image = np.repeat(values[:, None, :], columns, axis=1).astype(np.float32)
    return image, zenith


# ------------------------------------------------------------------------------------------
# Emitters
# ------------------------------------------------------------------------------------------

def _rgb(value: np.ndarray) -> dict:
    return {"type": "rgb", "value": [float(v) for v in value]}


def _envmap(kind: str, irradiance: np.ndarray, ground_radiance: np.ndarray, up: str, rows: int) -> dict:
    image, _ = sky_bitmap(kind, irradiance, ground_radiance=ground_radiance, rows=rows)
    return {"type": "envmap", "bitmap": mi.Bitmap(image),
            "to_world": mi.ScalarTransform4f(_to_world(up).tolist())}


def uniform_sky(irradiance, *, ground=None, up: str = "+z", rows: int = DEFAULT_ROWS,
                ground_irradiance=None) -> dict:
    """A uniform sky of horizontal irradiance ``irradiance`` (number or (3,), W/m^2): L = E_h / pi.

    ground : None (default) gives Mitsuba's ``constant`` emitter, L in every direction (below the
        horizon too: the scene's ground hides that half, as in the shipped canopy scenes); an
        albedo rho_g in [0, 1] gives an ``envmap`` whose lower half is a Lambertian ground's glow,
        rho_g * (E_h + ground_irradiance) / pi (rho_g = 0: black below the horizon).
    up : the scene's up axis (``axes``); used only by the envmap form
    ground_irradiance : extra horizontal irradiance lighting the ground (the sun's; ``sun_and_sky``)

    Returns a Mitsuba emitter dict.

    >>> uniform_sky(np.pi)["radiance"]["value"]
    [1.0, 1.0, 1.0]
    """
    e_h = _channels(irradiance, "irradiance", "give the sky's horizontal irradiance in W/m^2, e.g. 100")
    rho_g = _ground(ground)
    axes(up)
    if rho_g is None:
        return {"type": "constant", "radiance": _rgb(e_h / np.pi)}
    extra = np.zeros(3) if ground_irradiance is None else _channels(ground_irradiance, "ground_irradiance",
                                                                    "give W/m^2")
    return _envmap("uniform", e_h, rho_g * (e_h + extra) / np.pi, up, rows)


def overcast_sky(irradiance, *, ground=None, up: str = "+z", rows: int = DEFAULT_ROWS,
                 ground_irradiance=None) -> dict:
    """The CIE standard overcast sky, L = L_z (1 + 2 cos theta) / 3, as a Mitsuba ``envmap`` dict.

    irradiance : number or (3,), W/m^2: the sky's horizontal irradiance E_h = 7 pi L_z / 9
    ground : None or 0 (default None): black below the horizon; an albedo rho_g in [0, 1]: the
        glow of a Lambertian ground, rho_g * (E_h + ground_irradiance) / pi
    up : the scene's up axis (``axes``), "+z" by default
    rows : rows of the latitude-longitude bitmap (odd, >= 5)
    ground_irradiance : extra horizontal irradiance lighting the ground (the sun's; ``sun_and_sky``)

    The dict holds the bitmap as an ``mi.Bitmap`` (``"bitmap"``) and the rotation to the up axis
    (``"to_world"``); ``write_sky`` writes it as an EXR file and an XML snippet instead.

    >>> sky = overcast_sky(100.0)
    >>> sky["type"], sky["bitmap"].height()
    ('envmap', 257)
    """
    e_h = _channels(irradiance, "irradiance", "give the sky's horizontal irradiance in W/m^2, e.g. 100")
    rho_g = _ground(ground) or 0.0
    extra = np.zeros(3) if ground_irradiance is None else _channels(ground_irradiance, "ground_irradiance",
                                                                    "give W/m^2")
    axes(up)
    return _envmap("overcast", e_h, rho_g * (e_h + extra) / np.pi, up, _check_rows(rows))


def sun(*, azimuth: float, elevation: float, normal_irradiance=None, horizontal_irradiance=None,
        up: str = "+z") -> dict:
    """The sun as a Mitsuba ``directional`` emitter dict.

    azimuth, elevation : degrees (``sun_direction``)
    normal_irradiance : number or (3,), W/m^2: direct irradiance on a plane facing the sun (E_n)
    horizontal_irradiance : or the direct irradiance on a horizontal plane, E_h = E_n sin(elevation);
        give exactly one of the two
    up : the scene's up axis (``axes``)

    A plane whose normal makes the angle i with the sun then receives E_n cos(i) where lit.

    >>> s = sun(azimuth=180, elevation=30, horizontal_irradiance=400)
    >>> np.round(s["irradiance"]["value"], 6).tolist(), np.round(s["direction"], 6).tolist()
    ([800.0, 800.0, 800.0], [0.0, 0.866025, -0.5])
    """
    toward = sun_direction(azimuth, elevation, up=up)
    if (normal_irradiance is None) == (horizontal_irradiance is None):
        raise SettingsError("give the sun's direct irradiance once: normal_irradiance (on a plane facing the sun) "
                            "or horizontal_irradiance (on a horizontal plane), not both or neither")
    if normal_irradiance is not None:
        e_n = _channels(normal_irradiance, "normal_irradiance", "give the direct normal irradiance in W/m^2, e.g. 800")
    else:
        e_n = _channels(horizontal_irradiance, "horizontal_irradiance",
                        "give the direct horizontal irradiance in W/m^2, e.g. 500") / math.sin(math.radians(elevation))
    return {"type": "directional", "direction": [float(v) for v in -toward + 0.0], "irradiance": _rgb(e_n)}


def sun_and_sky(*, azimuth: float, elevation: float, diffuse_irradiance, direct_normal=None,
                direct_horizontal=None, sky: str = "overcast", ground=None, up: str = "+z",
                rows: int = DEFAULT_ROWS) -> dict:
    """A sun and a sky as ``{"sun": directional dict, "sky": sky dict}``, to merge into a scene dict.

    azimuth, elevation : the sun's position in degrees (``sun_direction``)
    diffuse_irradiance : number or (3,), W/m^2: the sky's horizontal irradiance
    direct_normal, direct_horizontal : the sun's direct normal or horizontal irradiance, W/m^2 (one)
    sky : "overcast" (default) or "uniform"
    ground : None, or a ground albedo whose glow (lit by sky and sun) fills the lower hemisphere
    up : the scene's up axis (``axes``)

    Global horizontal irradiance = diffuse_irradiance + direct normal * sin(elevation).

    >>> lights = sun_and_sky(azimuth=135, elevation=40, diffuse_irradiance=120, direct_normal=700)
    >>> sorted(lights), lights["sky"]["type"]
    (['sky', 'sun'], 'envmap')
    """
    if sky not in SKIES:
        raise SettingsError(f"sky={sky!r} is not a sky model; choose one of {', '.join(SKIES)}")
    s = sun(azimuth=azimuth, elevation=elevation, normal_irradiance=direct_normal,
            horizontal_irradiance=direct_horizontal, up=up)
    sun_h = np.asarray(s["irradiance"]["value"]) * math.sin(math.radians(elevation))
    build = overcast_sky if sky == "overcast" else uniform_sky
    return {"sun": s, "sky": build(diffuse_irradiance, ground=ground, up=up, rows=rows, ground_irradiance=sun_h)}


# ------------------------------------------------------------------------------------------
# Closed forms (docs/skies.md)
# ------------------------------------------------------------------------------------------

def overcast_tilted_irradiance(irradiance, tilt, *, ground_radiance=0.0) -> np.ndarray:
    """Closed form: irradiance (W/m^2) on a plane tilted ``tilt`` radians from facing up under the
    CIE overcast sky of horizontal irradiance ``irradiance``, plus a uniform ``ground_radiance``
    below the horizon:

        E(b) = L_z [pi (1 + cos b) / 6 + 4/9 ((pi - b) cos b + sin b)] + L_g pi (1 - cos b) / 2,

    L_z = 9 E_h / (7 pi). At b = 0 it is E_h; at b = pi/2, L_z (pi/6 + 4/9) = 0.3962 E_h.
    Shapes broadcast: tilt (K,) with irradiance scalar gives (K,).

    >>> round(float(overcast_tilted_irradiance(100.0, np.pi / 2)), 4)
    39.6177
    """
    b = np.asarray(tilt, dtype=np.float64)
    lz = 9.0 * np.asarray(irradiance, dtype=np.float64) / (7.0 * np.pi)
    return (lz * (np.pi * (1 + np.cos(b)) / 6 + 4.0 / 9.0 * ((np.pi - b) * np.cos(b) + np.sin(b)))
            + np.asarray(ground_radiance, dtype=np.float64) * np.pi * (1 - np.cos(b)) / 2)


def uniform_tilted_irradiance(irradiance, tilt, *, ground_radiance=0.0) -> np.ndarray:
    """Closed form: irradiance (W/m^2) on a plane tilted ``tilt`` radians from facing up under a
    uniform upper hemisphere of horizontal irradiance E_h and a uniform ground radiance L_g:
    E(b) = E_h (1 + cos b) / 2 + L_g pi (1 - cos b) / 2.

    >>> float(uniform_tilted_irradiance(100.0, np.pi / 2))
    50.0
    """
    b = np.asarray(tilt, dtype=np.float64)
    return (np.asarray(irradiance, dtype=np.float64) * (1 + np.cos(b)) / 2
            + np.asarray(ground_radiance, dtype=np.float64) * np.pi * (1 - np.cos(b)) / 2)


# ------------------------------------------------------------------------------------------
# XML
# ------------------------------------------------------------------------------------------

def _numbers(values) -> str:
    return ", ".join(f"{float(v):.9g}" for v in np.asarray(values, dtype=np.float64).reshape(-1))


def _matrix(transform) -> np.ndarray:
    m = transform.matrix
    return np.array(m.numpy() if hasattr(m, "numpy") else m, dtype=np.float64).reshape(4, 4)


def sky_xml(emitters: dict, *, filename: str | None = None) -> str:
    """Mitsuba XML for emitter dicts ``{id: dict}`` made here (constant, envmap, directional).

    An envmap is written with ``<string name="filename" value=filename>`` (its bitmap must be
    written there, see ``write_sky``); its rotation as a ``to_world`` matrix.

    >>> print(sky_xml({"sky": uniform_sky(np.pi)}))
    <emitter type="constant" id="sky">
        <rgb name="radiance" value="1, 1, 1"/>
    </emitter>
    """
    out = []
    for eid, d in emitters.items():
        kind = d["type"]
        if kind == "constant":
            body = [f'    <rgb name="radiance" value="{_numbers(d["radiance"]["value"])}"/>']
        elif kind == "directional":
            body = [f'    <vector name="direction" value="{_numbers(d["direction"])}"/>',
                    f'    <rgb name="irradiance" value="{_numbers(d["irradiance"]["value"])}"/>']
        elif kind == "envmap":
            if filename is None:
                raise SettingsError(f"emitter '{eid}' is an envmap: give the file name its bitmap is written to "
                                    "(write_sky writes both)")
            body = [f'    <string name="filename" value="{filename}"/>',
                    '    <transform name="to_world">',
                    f'        <matrix value="{_numbers(_matrix(d["to_world"]))}"/>',
                    '    </transform>']
        else:
            raise SettingsError(f"emitter '{eid}' has type {kind!r}; sky_xml writes constant, envmap and directional")
        out.append("\n".join([f'<emitter type="{kind}" id="{eid}">', *body, "</emitter>"]))
    return "\n".join(out)


def write_sky(emitters: dict, path=None) -> str:
    """Write the bitmap of the envmap among ``emitters`` ({id: dict}) to ``path`` (.exr, atomically)
    and return the XML snippet that loads them all (the filename as given, relative to the scene
    file when relative). ``path`` may be None when no emitter is an envmap.
    """
    maps = [d for d in emitters.values() if d["type"] == "envmap"]
    if len(maps) > 1:
        raise SettingsError("more than one envmap: write each with its own write_sky call")
    if maps:
        if path is None:
            raise SettingsError("this sky is an envmap: give the .exr path to write its bitmap to (e.g. sky.exr)")
        check_output(path, (".exr",))
        image = np.array(maps[0]["bitmap"], dtype=np.float32)
        blob = exr_bytes({"R": image[..., 0], "G": image[..., 1], "B": image[..., 2]})
        atomic_write(Path(path), lambda handle: handle.write(blob))
    return sky_xml(emitters, filename=None if path is None else str(path))
