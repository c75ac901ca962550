"""Several wavebands in one solve: optical properties and emitter strengths per band, from a table.

A band solve is a solve whose channels are wavebands (PAR and NIR, or any list) instead of RGB:
geometry, links, visibility and the direct-light samples are computed once and shared by every
band; reflectance, transmittance and emission are per band. ``with_bands(scene, table)`` returns
a copy of a loaded scene whose channels are the table's bands (``scene.band_names``); solve it as
any scene, and every output names its columns by band (``radiosity_PAR``, ``absorbed_NIR``).
docs/bands.md describes the table; in brief, one row per band and id (CSV, header first):

===================  ====================================================================
column               meaning
===================  ====================================================================
``band``             band name (letters, digits, ``_ . + -``; it becomes a column suffix)
``id``               a shape id, ``*`` (the default row of the band, for shapes without their
                     own row) or the id of a point, spot, directional, constant or envmap
                     emitter (``emitter_K`` for the K-th such emitter without an id)
``reflectance``      rho of the shape's front side in the band, in [0, 1]
``transmittance``    tau of a leaf shape (``leaf`` BSDF, docs/leaves.md), both sides alike
``back_reflectance`` rho of the back side of a two-sided shape (empty: as the front)
``scale``            emitters only: factor on the emitter as the scene defines it (the mean
                     of its RGB values), dimensionless; with a scene emitter of strength 1
                     it is the band's value in the emitter's own unit (W/m^2 for a
                     directional's irradiance, W/(m^2 sr) for a radiance, W/sr for a
                     point or spot intensity)
===================  ====================================================================

The table changes values, never the scene's structure: which shapes are leaves, two-sided or
emitting comes from the scene file. Anything the table cannot mean is refused with a
``BandTableError`` (a ``ValueError``) naming the file, line, band and shape and the fix.
"""

from __future__ import annotations

import csv
import dataclasses
import difflib
import io
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import BandTableError
from .files import read_csv_text

__all__ = ["BandTable", "read_band_table", "band_table", "with_bands", "emitter_ids", "channel_names",
           "BAND_COLUMNS", "DEFAULT_ID"]

#: Columns of a band table, in the order docs/bands.md lists them; ``band`` and ``id`` are required.
BAND_COLUMNS = ("band", "id", "reflectance", "transmittance", "back_reflectance", "scale")
#: The columns holding numbers (empty cells: not given).
VALUE_COLUMNS = BAND_COLUMNS[2:]
#: The id of a band's default row: it holds the optics of every shape without a row of its own.
DEFAULT_ID = "*"
#: Band names become column suffixes (``radiosity_PAR``): a letter or digit first, then these.
_BAND_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$")
#: Slack on rho + tau <= 1 (values typed with few digits; float32 in Mitsuba).
_SLACK = 1e-6


@dataclass(frozen=True)
class BandTable:
    """The rows of a band table, checked for form (not yet against a scene; ``with_bands`` does).

    Attributes
    ----------
    source : str                  the file it came from, or ``"<table>"`` for rows given in code
    band, id : (N,) str           band name and id of each row
    line : (N,) int               the row's line in the file (header: line 1), or its 1-based index
    values : dict                 column name (``VALUE_COLUMNS``) -> (N,) float, NaN where empty
    """

    source: str
    band: np.ndarray
    id: np.ndarray
    line: np.ndarray
    values: dict

    @property
    def bands(self) -> list:
        """Band names in the order of their first row."""
        _, first = np.unique(self.band, return_index=True)
        return [str(b) for b in self.band[np.sort(first)]]

    def where(self, row: int) -> str:
        """``file, line N`` (or ``<table>, row N``) of row ``row``, for messages."""
        kind = "row" if self.source == "<table>" else "line"
        return f"{self.source}, {kind} {int(self.line[row])}"


# ------------------------------------------------------------------------------------------
# Reading
# ------------------------------------------------------------------------------------------


def did_you_mean(word: str, choices) -> str:
    """" (did you mean 'X'?)" for the closest of ``choices`` to ``word``, or ""."""
    close = difflib.get_close_matches(word, list(choices), n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""


def read_band_table(path) -> BandTable:
    """A band table from a CSV file (UTF-8; a header naming ``band``, ``id`` and value columns;
    ``#`` lines are comments; blank lines skipped). BandTableError naming the file and line for an
    unreadable file, missing or unknown columns, or a cell that is not a finite number."""
    path = Path(path)
    text = read_csv_text(path, "band table", f"{','.join(BAND_COLUMNS)} (docs/bands.md)", BandTableError)
    reader = csv.reader(io.StringIO(text, newline=""))
    rows, lines = [], []
    for row in reader:                       # parsing text: one row at a time
        if not row or not any(cell.strip() for cell in row) or row[0].lstrip().startswith("#"):
            continue
        rows.append([cell.strip() for cell in row])
        lines.append(reader.line_num)
    if not rows:
        raise BandTableError(f"band table '{path}' is empty; give a header {','.join(BAND_COLUMNS)} and one "
                             "row per band and shape")
    header = [cell.lower() for cell in rows[0]]
    _check_header(str(path), header)
    records = []
    for row, line in zip(rows[1:], lines[1:]):
        if len(row) > len(header) and any(row[len(header):]):
            raise BandTableError(f"band table '{path}', line {line}: {len(row)} cells but the header names "
                                 f"{len(header)} columns; remove the extra cells or name their column")
        records.append(dict(zip(header, row + [""] * (len(header) - len(row)))))
    if not records:
        raise BandTableError(f"band table '{path}' has a header but no rows; give one row per band and shape")
    return _table(records, lines[1:], str(path))


def band_table(rows, *, source: str = "<table>") -> BandTable:
    """A band table from rows given in code: an iterable of mappings whose keys are column names
    (``{"band": "PAR", "id": "leaf", "reflectance": 0.08, "transmittance": 0.05}``), or a pandas
    DataFrame with those columns. Missing keys, None, NaN and "" are empty cells; checked as
    ``read_band_table`` checks a file, rows numbered from 1."""
    if hasattr(rows, "to_dict") and not isinstance(rows, dict):
        rows = rows.to_dict("records")                   # a pandas DataFrame
    if isinstance(rows, (str, bytes, dict)):
        raise BandTableError(f"a band table in code is a list of rows (dicts with keys {', '.join(BAND_COLUMNS)}), "
                             f"not a {type(rows).__name__}; give a file path to read a CSV")
    records = [dict(r) for r in rows]
    if not records:
        raise BandTableError(f"band table {source} has no rows; give one row per band and shape")
    header = []
    for r in records:
        header += [str(k).lower() for k in r if str(k).lower() not in header]
    _check_header(source, header)
    cells = [{str(k).lower(): _cell(v) for k, v in r.items()} for r in records]
    return _table(cells, list(range(1, len(cells) + 1)), source)


def _cell(value) -> str:
    """A value given in code as the text of a CSV cell ("" for None or NaN)."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    return repr(float(value)) if isinstance(value, (int, float, np.number)) and not isinstance(value, bool) \
        else str(value).strip()


def _check_header(source: str, header: list) -> None:
    missing = [c for c in ("band", "id") if c not in header]
    if missing:
        hint = " (a shape's or emitter's id goes in column 'id')" if "id" in missing and "shape" in header else ""
        raise BandTableError(f"band table {source!r} lacks column(s) {', '.join(missing)}{hint} (its header is "
                             f"{','.join(header)}); the header names band, id and some of "
                             f"{', '.join(VALUE_COLUMNS)}")
    unknown = [c for c in header if c not in BAND_COLUMNS]
    if unknown:
        hint = did_you_mean(unknown[0], BAND_COLUMNS)
        raise BandTableError(f"band table {source!r}: unknown column '{unknown[0]}'{hint}; the columns are "
                             f"{', '.join(BAND_COLUMNS)}")
    if len(set(header)) != len(header):
        twice = next(c for c in header if header.count(c) > 1)
        raise BandTableError(f"band table {source!r}: column '{twice}' appears twice in the header; keep one")


def _table(records: list, lines: list, source: str) -> BandTable:
    """Rows of text cells to a BandTable, checking names, numbers and duplicates."""
    n = len(records)
    band = np.array([r.get("band", "") for r in records], dtype=object).astype(str)
    ids = np.array([r.get("id", "") for r in records], dtype=object).astype(str)
    line = np.asarray(lines, np.int64)
    table = BandTable(source=source, band=band, id=ids, line=line, values={})
    values = {c: np.full(n, np.nan) for c in VALUE_COLUMNS}
    for k, r in enumerate(records):          # the cells of a table of a few rows per shape and band
        where = table.where(k)
        if not band[k]:
            raise BandTableError(f"{where}: the band is empty; name the band of every row (e.g. PAR)")
        if not _BAND_NAME.match(band[k]):
            raise BandTableError(f"{where}: band name {str(band[k])!r} must start with a letter or digit and hold only "
                                 "letters, digits and _ . + - (it becomes a column name, e.g. radiosity_PAR); "
                                 "rename it")
        if not ids[k]:
            raise BandTableError(f"{where} (band '{band[k]}'): the id is empty; give a shape id, an emitter id "
                                 f"or {DEFAULT_ID} for the band's default row")
        for column in VALUE_COLUMNS:
            text = r.get(column, "")
            if text == "":
                continue
            try:
                value = float(text)
            except ValueError:
                raise BandTableError(f"{where} (band '{band[k]}', id '{ids[k]}'): {column} {text!r} is not a "
                                     "number; give a number such as 0.08, or leave the cell empty") from None
            if not math.isfinite(value):
                raise BandTableError(f"{where} (band '{band[k]}', id '{ids[k]}'): {column} {text} is not a "
                                     "finite number; give a number such as 0.08, or leave the cell empty")
            if value < 0:
                raise BandTableError(f"{where} (band '{band[k]}', id '{ids[k]}'): {column} {value:g} < 0; "
                                     f"give a {column} >= 0")
            values[column][k] = value
    table.values.update(values)
    # ---------------- band names differing only in case, duplicate rows --------------------------
    names = table.bands
    lower = [b.lower() for b in names]
    clash = next((b for b in names if lower.count(b.lower()) > 1), None)
    if clash is not None:
        other = next(b for b in names if b.lower() == clash.lower() and b != clash)
        raise BandTableError(f"band table {source!r}: bands '{clash}' and '{other}' differ only in case (their "
                             "columns would clash in tools that ignore case); spell each band one way")
    key = np.char.add(np.char.add(band, "\0"), ids)
    _, first, count = np.unique(key, return_index=True, return_counts=True)
    if np.any(count > 1):
        k = int(first[np.flatnonzero(count > 1)[0]])
        again = int(np.flatnonzero(key == key[k])[1])
        raise BandTableError(f"{table.where(again)}: band '{band[k]}', id '{ids[k]}' has a row already "
                             f"(line {int(line[k])}); keep one row per band and id")
    return table


# ------------------------------------------------------------------------------------------
# Applying a table to a scene
# ------------------------------------------------------------------------------------------

def emitter_ids(scene) -> list:
    """Ids of the scene's point, spot, directional, constant and envmap emitters (``light_emitters``,
    in that order): the Mitsuba id, or ``emitter_K`` (K: index in ``light_emitters``) for one
    without an id or whose id a shape or an earlier emitter already has."""
    ids, taken = [], set(scene.shape_ids)
    for k, emitter in enumerate(scene.light_emitters):
        name = emitter.id() or ""
        if not name or name in taken or name == DEFAULT_ID:
            name = f"emitter_{k}"
        taken.add(name)
        ids.append(name)
    return ids


def with_bands(scene, table, *, bands=None):
    """A copy of a loaded scene whose channels are the wavebands of a band table.

    Parameters
    ----------
    scene : mirad Scene, or anything ``mirad.load_scene`` takes (a path, a dict, an ``mi.Scene``)
    table : a CSV path (``read_band_table``), rows given in code (``band_table``) or a ``BandTable``
    bands : list of str or None
        the bands to solve, in this order (their columns come out in it); None: every band of
        the table, in the order of their first row

    Returns
    -------
    mirad Scene with C = len(bands) channels: ``band_names`` (C,) str; per triangle
    ``tri_rho``, ``back_rho``, ``tri_transmittance``, ``back_transmittance`` (T, C), dimensionless,
    and ``tri_emission`` (T, C) W/m^2 = scale x the RGB mean of the scene's emission; per
    non-area emitter ``light_band_scale`` (E, C), dimensionless, the factor on its RGB mean
    (``emitters.direct_irradiance`` samples each emitter once and weighs it per band). The mesh,
    ``mi_scene``, shape ids and emitters are the scene's own (shared, not copied).

    Raises BandTableError (a ValueError) for ids the scene does not have, bands the table does
    not have, a shape or emitter without a row in some band (and no default row), a value the
    shape cannot take (transmittance on a shape that is not a leaf, a back side on a one-sided
    shape, a scale on a shape that does not emit), a missing value, or reflectance +
    transmittance > 1; the message names the file, line, band and id and the fix.

    >>> scene = with_bands(mirad.load_scene("canopy.xml"), "bands.csv")   # doctest: +SKIP
    >>> scene.band_names                                                   # doctest: +SKIP
    ['PAR', 'NIR']
    """
    from .scene import load_scene

    scene = load_scene(scene)
    if getattr(scene, "band_names", None):
        raise BandTableError(f"the scene already has bands {', '.join(scene.band_names)}; apply a band table "
                             "to the scene as loaded (mirad.load_scene), not to a band scene")
    if not isinstance(table, BandTable):
        table = read_band_table(table) if isinstance(table, (str, Path)) or hasattr(table, "__fspath__") \
            else band_table(table)
    names = _select_bands(table, bands)
    optics = _resolve(scene, table, names)
    return _band_scene(scene, names, optics)


def _select_bands(table: BandTable, bands) -> list:
    known = table.bands
    if bands is None:
        return known
    if isinstance(bands, str):
        bands = [b for b in bands.split(",") if b.strip()]
    bands = [str(b).strip() for b in bands]
    if not bands:
        raise BandTableError(f"no bands chosen from band table {table.source!r}; name some of {', '.join(known)}")
    unknown = [b for b in bands if b not in known]
    if unknown:
        hint = did_you_mean(unknown[0], known)
        raise BandTableError(f"band '{unknown[0]}' is not in band table {table.source!r}{hint}; its bands are "
                             f"{', '.join(known)}")
    if len(set(bands)) != len(bands):
        raise BandTableError(f"bands {', '.join(bands)}: a band is named twice; name each once")
    return bands


def _shape_structure(scene) -> dict:
    """Per shape (S,): what the scene file makes of it. ``leaf`` (a leaf BSDF), ``two_sided`` (a back
    side: a two-sided BSDF or a leaf), ``emits`` (an area emitter), and the RGB means of the lost
    light Mitsuba sends through or reflects non-diffusely (per triangle, (T,))."""
    S, tri_shape = len(scene.shape_ids), scene.tri_shape
    count = np.bincount(tri_shape, minlength=S)
    any_of = lambda mask: np.bincount(tri_shape, weights=mask.astype(np.float64), minlength=S) > 0  # noqa: E731
    leaf = any_of(scene.tri_leaf)
    two_sided = any_of(scene.back_rho.max(axis=1) > 0) | leaf
    shapes = list(scene.mi_scene.shapes())
    emits = np.array([s.emitter() is not None for s in shapes], bool) if len(shapes) == S else \
        any_of(scene.tri_emission.max(axis=1) > 0)
    return {"leaf": leaf, "two_sided": two_sided, "emits": emits, "empty": count == 0}


def _resolve(scene, table: BandTable, names: list) -> dict:
    """Per shape and band (S, C) and per emitter and band (E, C) values, every refusal checked."""
    shape_ids, light_ids = list(scene.shape_ids), emitter_ids(scene)
    S, E, C = len(shape_ids), len(light_ids), len(names)
    structure = _shape_structure(scene)
    # ---------------- rows: which band, which shape or emitter ----------------------------------
    chosen = np.isin(table.band, names)
    band_of = {b: c for c, b in enumerate(names)}
    shape_of = {sid: s for s, sid in enumerate(shape_ids)}
    light_of = {lid: e for e, lid in enumerate(light_ids)}
    for k in np.flatnonzero(~np.isin(table.id, shape_ids + light_ids + [DEFAULT_ID])):
        known = shape_ids + light_ids
        hint = did_you_mean(table.id[k], known)
        shown = ", ".join(f"'{i}'" for i in known[:12]) + (f" and {len(known) - 12} more" if len(known) > 12 else "")
        raise BandTableError(f"{table.where(k)} (band '{table.band[k]}'): the scene has no shape or emitter "
                             f"'{table.id[k]}'{hint}; its ids are {shown} (or {DEFAULT_ID} for a band's default "
                             "row)")
    v = table.values
    rho, tau, back, scale = (np.full((S, C), np.nan) for _ in range(4))
    light = np.full((E, C), np.nan)
    given = np.zeros((S, C), np.int64) - 1               # the row each shape's values came from
    default = {}                                         # band -> row of its default row
    for k in np.flatnonzero(chosen):                     # rows of the table: a few per shape and band
        c, rid, where = band_of[table.band[k]], table.id[k], table.where(k)
        label = f"{where} (band '{table.band[k]}', "
        if rid in light_of:
            extra = [col for col in ("reflectance", "transmittance", "back_reflectance") if not np.isnan(v[col][k])]
            if extra:
                raise BandTableError(f"{label}emitter '{rid}'): an emitter has no {extra[0]}; give it only a scale "
                                     "(the factor on its emission in this band) and leave the other cells empty")
            if np.isnan(v["scale"][k]):
                raise BandTableError(f"{label}emitter '{rid}'): the scale is missing; give the factor on the "
                                     "emitter's emission in this band (e.g. 1)")
            light[light_of[rid], c] = v["scale"][k]
            continue
        if rid == DEFAULT_ID:
            if not np.isnan(v["scale"][k]):
                raise BandTableError(f"{label}default row {DEFAULT_ID}): a default row cannot give a scale; give "
                                     "each emitter its own row with its scale")
            default[c] = k
            continue
        s = shape_of[rid]
        _check_shape_row(table, k, rid, structure, s, label)
        rho[s, c], tau[s, c], back[s, c], scale[s, c] = (v[col][k] for col in VALUE_COLUMNS)
        given[s, c] = k
    # ---------------- shapes without a row: the band's default row -----------------------------
    for c, k in default.items():                         # one per band
        missing = given[:, c] < 0
        rho[missing, c] = v["reflectance"][k]
        tau[missing, c] = np.where(structure["leaf"][missing], v["transmittance"][k], 0.0)
        back[missing, c] = np.where(structure["two_sided"][missing], v["back_reflectance"][k], np.nan)
        given[missing, c] = k
    _check_coverage(scene, table, names, given, light, light_ids, structure)
    # ---------------- missing values, then energy ----------------------------------------------
    for s, c in zip(*np.nonzero(np.isnan(rho) & ~structure["empty"][:, None])):
        k = given[s, c]
        raise BandTableError(f"{table.where(k)} (band '{names[c]}', shape '{shape_ids[s]}'): the reflectance is "
                             "missing; give the shape's reflectance in this band (0 for a black surface)")
    leaf_missing = np.isnan(tau) & structure["leaf"][:, None] & ~structure["empty"][:, None]
    for s, c in zip(*np.nonzero(leaf_missing)):
        raise BandTableError(f"{table.where(given[s, c])} (band '{names[c]}', shape '{shape_ids[s]}'): the shape "
                             "is a leaf and its transmittance is missing; give it (0 for an opaque leaf)")
    emit_missing = np.isnan(scale) & structure["emits"][:, None]
    for s, c in zip(*np.nonzero(emit_missing)):
        raise BandTableError(f"{table.where(given[s, c])} (band '{names[c]}', shape '{shape_ids[s]}'): the shape "
                             "emits light (an area emitter) and its scale is missing; give it a row of its own "
                             "with the scale, the factor on its emission in this band (e.g. 1)")
    rho, tau, scale = np.nan_to_num(rho), np.nan_to_num(tau), np.nan_to_num(scale)
    back = np.where(np.isnan(back), rho, back)
    back = np.where(structure["two_sided"][:, None], back, 0.0)
    for side, r in (("", rho), ("back ", back)):
        over = (r + tau > 1 + _SLACK) & ~structure["empty"][:, None]
        for s, c in zip(*np.nonzero(over)):
            raise BandTableError(
                f"{table.where(given[s, c])} (band '{names[c]}', shape '{shape_ids[s]}'): {side}reflectance "
                f"{r[s, c]:g} + transmittance {tau[s, c]:g} = {r[s, c] + tau[s, c]:g} > 1 breaks energy "
                "conservation; lower them so that reflectance + transmittance <= 1 (the rest is absorbed)")
    return {"rho": rho, "tau": tau, "back": back, "scale": scale, "light": light, "structure": structure}


def _check_shape_row(table: BandTable, k: int, sid: str, structure: dict, s: int, label: str) -> None:
    """Refuse what a shape's row gives that the scene's shape cannot take."""
    v = table.values
    if v["transmittance"][k] > 0 and not structure["leaf"][s]:
        raise BandTableError(f"{label}shape '{sid}'): transmittance {v['transmittance'][k]:g} on a shape whose BSDF "
                             "is not a leaf; only leaves pass light diffusely to their other side: give the "
                             "shape a leaf BSDF in the scene (docs/leaves.md) or a transmittance of 0")
    if not np.isnan(v["back_reflectance"][k]) and not structure["two_sided"][s]:
        raise BandTableError(f"{label}shape '{sid}'): back_reflectance on a one-sided shape (its BSDF reflects on "
                             "the front only); make its BSDF twosided in the scene or leave the cell empty")
    if not np.isnan(v["scale"][k]) and not structure["emits"][s]:
        raise BandTableError(f"{label}shape '{sid}'): a scale on a shape that emits no light; scale applies to "
                             "emitters only (an area emitter's shape, or a point/spot/directional/sky emitter): "
                             "leave the cell empty")


def _check_coverage(scene, table: BandTable, names: list, given: np.ndarray, light: np.ndarray,
                    light_ids: list, structure: dict) -> None:
    """Every shape (directly or through the band's default row) and every emitter in every band."""
    shape_ids = scene.shape_ids
    for s, c in zip(*np.nonzero(given < 0)):
        rows = np.flatnonzero(table.id == shape_ids[s])
        has = sorted({str(b) for b in table.band[rows]} & set(names))
        if has:
            raise BandTableError(
                f"band table {table.source!r}: shape '{shape_ids[s]}' has rows for band(s) {', '.join(has)} "
                f"(line {int(table.line[rows[0]])}) but none for band '{names[c]}', which other rows have; give "
                f"it a row '{names[c]},{shape_ids[s]},...' or the band a default row '{names[c]},{DEFAULT_ID},...'")
        raise BandTableError(
            f"band table {table.source!r}: shape '{shape_ids[s]}' has no row for band '{names[c]}' and the band has "
            f"no default row; add a row '{names[c]},{shape_ids[s]},...' or '{names[c]},{DEFAULT_ID},...' (the "
            "optics of every shape without a row of its own)")
    for e, c in zip(*np.nonzero(np.isnan(light))):
        kind = scene.light_kinds[e]
        raise BandTableError(
            f"band table {table.source!r}: emitter '{light_ids[e]}' ({kind}) has no row for band '{names[c]}'; "
            f"add a row '{names[c]},{light_ids[e]},,,,SCALE' with the factor on its emission in that band (0 "
            "for none)")


def _band_scene(scene, names: list, optics: dict):
    """The copy of ``scene`` with per-band arrays (see ``with_bands``)."""
    tri_shape = scene.tri_shape
    C = len(names)
    leaf = scene.tri_leaf[:, None]
    grey = lambda a: np.repeat(a.mean(axis=1, keepdims=True), C, axis=1)   # noqa: E731  (T, 3) -> (T, C)
    # glass, masks and glossy lobes keep the RGB mean of what the diffuse model loses (model_error)
    tri_tau = np.where(leaf, optics["tau"][tri_shape], grey(scene.tri_transmittance))
    back_tau = np.where(leaf, optics["tau"][tri_shape], grey(scene.back_transmittance))
    emission = optics["scale"][tri_shape] * scene.tri_emission.mean(axis=1, keepdims=True)
    return dataclasses.replace(
        scene, tri_rho=optics["rho"][tri_shape], back_rho=optics["back"][tri_shape],
        tri_emission=emission, tri_transmittance=tri_tau, back_transmittance=back_tau,
        tri_specular=grey(scene.tri_specular), warnings=list(scene.warnings),
        non_diffuse_shapes=list(scene.non_diffuse_shapes), approximations=list(scene.approximations),
        band_names=list(names), light_band_scale=optics["light"].copy())


# ------------------------------------------------------------------------------------------
# Naming outputs
# ------------------------------------------------------------------------------------------

#: Column suffixes of an RGB solution's channels.
RGB = ("r", "g", "b")


def channel_names(result) -> list:
    """Names of a solution's (or scene's) channels: its band names (``sol.stats["bands"]``,
    ``scene.band_names``), else ``r, g, b`` (the first C of them)."""
    stats = getattr(result, "stats", None)
    if isinstance(stats, dict) and stats.get("bands"):
        return list(stats["bands"])
    scene = getattr(result, "scene", result)
    names = getattr(scene, "band_names", None)
    if names:
        return list(names)
    return list(RGB[: getattr(result, "channels", 3)])


def is_band_result(result) -> bool:
    """True for a band solution or scene (its channels are named bands, not RGB)."""
    stats = getattr(result, "stats", None)
    if isinstance(stats, dict) and stats.get("bands"):
        return True
    return bool(getattr(getattr(result, "scene", result), "band_names", None))
