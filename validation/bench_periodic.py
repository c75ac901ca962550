"""Periodic canopies: per-leaf absorbed power of mirad against the periodic path tracer, with times.

Writes a plant-canopy-like pattern (``scenes/periodic-canopy/make.py``: a 4 x 4 m plot, 5 crowns of
120 translucent diamond leaves, a soil ground exactly the plot's size) lit by the sun of
scenes/plant-canopy and a CIE standard overcast sky (100 W/m^2 horizontal) into a work folder, then

1. checks the periodic reference itself: the pattern copied ``--tiles`` x ``--tiles`` times,
   Mitsuba's own ``path`` integrator on the middle tile's triangles against the periodic path
   tracer on the pattern (area-weighted radiosity per side and channel, in standard errors);
2. computes the reference: per triangle side irradiance from the periodic path tracer
   (``--reference-samples`` paths each; cached in the work folder);
3. solves with ``periodic`` at each tolerance and measures the per-leaf absorbed power (both sides
   of a leaf's two triangles, ``export.absorbed_power``) against the reference: relative L1 over
   leaves per channel, the bias of the total, seconds, the estimate; then, at 0.02, the same solve
   without the far field and without wrapping, to show what each part brings;
4. the periodic path tracer itself as a per-leaf estimator at a few path counts (seconds and error
   against the reference, an independent seed): the peer at equal time.

    python validation/bench_periodic.py --work periodic-work --record
"""

from __future__ import annotations

import argparse
import datetime
import importlib.util
import os
import time
import warnings
from pathlib import Path

import numpy as np

import mirad
import drjit as dr
import mitsuba as mi
from mirad import export, far_field, periodic
from mirad import periodic_reference as periodic_reference_module
from mirad import reference as reference_module
from mirad.periodic_reference import periodic_reference
from mirad.reference import triangle_reference
from mirad.report import machine

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "validation" / "RESULTS.md"
BOX = "-2,-2,2,2"
PATTERN = {"half": 2.0, "plants": 5, "leaves_per_plant": 120, "seed": 7, "sky": "overcast"}


def _make():
    spec = importlib.util.spec_from_file_location("periodic_canopy_make", ROOT / "scenes" / "periodic-canopy" / "make.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def reference(scene, box, samples: int, seed: int, cache: Path):
    """(front, back) irradiance references, (T, 3) each with stderr, cached by fingerprint."""
    path = cache / f"periodic-ref-{scene.fingerprint[:16]}-{samples}-{seed}.npz"
    if path.exists():
        data = np.load(path)
        return (data["front"], data["front_se"]), (data["back"], data["back_se"]), float(data["seconds"])
    t0 = time.perf_counter()
    f = periodic_reference(scene, box, samples_per_triangle=samples, seed=seed, quantity="irradiance")
    b = periodic_reference(scene, box, samples_per_triangle=samples, seed=seed + 1, quantity="irradiance",
                           side="back")
    seconds = time.perf_counter() - t0
    cache.mkdir(parents=True, exist_ok=True)
    np.savez(path, front=f.value, front_se=f.stderr, back=b.value, back_se=b.stderr, seconds=seconds)
    return (f.value, f.stderr), (b.value, b.stderr), seconds


class Leaves:
    """Per-leaf sums of per-triangle values on the ``leaves`` shape (a leaf: its 2 triangles)."""

    def __init__(self, scene):
        self.tris = np.flatnonzero(scene.tri_shape == scene.shape_index("leaves"))
        n = len(self.tris) // 2          # diamond leaves: every leaf's first triangles, then its second ones
        self.organ = np.concatenate([np.arange(n), np.arange(n)])
        self.n = n

    def sum(self, values: np.ndarray) -> np.ndarray:
        out = np.zeros((self.n, values.shape[1]))
        np.add.at(out, self.organ, values[self.tris])
        return out


def absorbed(sol, front, back):
    return export.absorbed_power(sol, front, back)


def leaf_errors(leaves: Leaves, mine: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, r = leaves.sum(mine), leaves.sum(ref)
    return np.abs(a - r).sum(0) / r.sum(0), (a - r).sum(0) / r.sum(0)


def pct(v) -> str:
    return " / ".join(f"{100 * x:.2f}" for x in np.atleast_1d(v))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default="periodic-work")
    ap.add_argument("--reference-samples", type=int, default=4096, help="paths per triangle side")
    ap.add_argument("--tolerances", default="0.1,0.05,0.02,0.01")
    ap.add_argument("--tiles", type=int, default=15, help="tiles per side of the brute-force check (0: skip)")
    ap.add_argument("--tiled-samples", type=int, default=1024)
    ap.add_argument("--pt-samples", default="16,64,256", help="path counts of the path tracer as an estimator")
    ap.add_argument("--record", action="store_true", help="append the tables to validation/RESULTS.md")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    work = Path(args.work)
    make = _make()
    scene = mirad.load_scene(str(make.write_canopy(work / "pattern", **PATTERN)))
    box = periodic.box_for(scene, mirad.Settings(periodic=BOX, core="hierarchical"))
    leaves = Leaves(scene)
    lines = [f"## bench_periodic: periodic canopy pattern under sun + overcast sky, "
             f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC", "",
             f"- machine: {machine()}; Mitsuba variant {scene.variant}, mitsuba {mi.__version__}, drjit {dr.__version__}",
             f"- scene: `scenes/periodic-canopy/make.py` {PATTERN}: {scene.triangle_count} triangles "
             f"({leaves.n} leaves of 2 triangles), box {BOX} (x, y; z up)"]

    # --- 1. the periodic reference against a large tiled field ----------------------------------
    if args.tiles:
        tiled = mirad.load_scene(str(make.write_canopy(work / f"tiled-{args.tiles}", tiles=args.tiles, **PATTERN)))
        middle = np.flatnonzero(np.isin(tiled.tri_shape, [tiled.shape_index("ground"), tiled.shape_index("leaves")]))
        # the same absolute ray offset as the pattern's (the reference lifts rays by a fraction of the
        # scene's diagonal: on the 31 x 31 field 1.75 cm, which put the undersides 0.5-0.8 % off)
        reference_module.OFFSET = periodic_reference_module.OFFSET * scene.diagonal / tiled.diagonal
        rows = []
        for side in ("front", "back"):
            t0 = time.perf_counter()
            brute = triangle_reference(tiled, samples_per_triangle=args.tiled_samples, seed=2, side=side,
                                       triangles=middle)
            t_brute = time.perf_counter() - t0
            t0 = time.perf_counter()
            wrapped = periodic_reference(scene, box, samples_per_triangle=args.tiled_samples, seed=1, side=side)
            t_wrapped = time.perf_counter() - t0
            area = scene.tri_area[:, None] * ((scene.back_rho.max(axis=1) > 0)[:, None] if side == "back" else 1.0)
            diff = ((wrapped.value - brute.radiosity) * area).sum(0) / (brute.radiosity * area).sum(0)
            se = np.sqrt(((wrapped.stderr ** 2 + brute.stderr ** 2) * area ** 2).sum(0)) / (brute.radiosity * area).sum(0)
            rows.append(f"| {side} | {pct(diff)} | {pct(se)} | {np.abs(diff / se).max():.1f} | {t_wrapped:.1f} | "
                        f"{t_brute:.1f} |")
        lines += ["", f"### The periodic path tracer against Mitsuba's `path` on a {args.tiles} x {args.tiles} tiled "
                  f"field ({tiled.triangle_count:,} triangles), middle tile, {args.tiled_samples} paths per triangle side "
                  "(both with the pattern's ray offset)",
                  "", "| side | radiosity difference, area-weighted (R / G / B, %) | its standard error (%) | "
                  "max abs z | periodic PT s | tiled Mitsuba s |", "|---|---:|---:|---:|---:|---:|", *rows]
        print("\n".join(lines))

    # --- 2. reference -------------------------------------------------------------------------
    (f, f_se), (b, b_se), ref_seconds = reference(scene, box, args.reference_samples, 11, work / "cache")
    solve_kw = {"core": "hierarchical", "quiet": True}
    probe = mirad.solve(scene, tolerance=0.2, periodic=BOX, **solve_kw)      # JIT warm-up, and the optics
    ref = absorbed(probe, f, b)
    k_f = 1 - probe.triangle_reflectance - probe.triangle_transmittance
    k_b = 1 - probe.back_reflectance - probe.back_transmittance
    var = ((k_f * f_se) ** 2 + (k_b * b_se) ** 2) * probe.triangle_area[:, None] ** 2
    noise = np.sqrt(leaves.sum(var)).sum(0) / leaves.sum(ref).sum(0)
    reference_module.OFFSET = periodic_reference_module.OFFSET
    lines += ["", f"### mirad per-leaf absorbed power against the periodic path tracer ({args.reference_samples} paths "
              f"per triangle side, {ref_seconds:.0f} s; its noise as a per-leaf L1: {pct(noise)} %)", "",
              "| run | seconds | estimated | per-leaf L1 (R / G / B, %) | bias of the total (%) | links |",
              "|---|---:|---:|---:|---:|---:|"]

    def run(label, tol, **extra):
        t0 = time.perf_counter()
        sol = mirad.solve(scene, tolerance=tol, **solve_kw, **extra)
        seconds = time.perf_counter() - t0
        l1, bias = leaf_errors(leaves, absorbed(sol, sol.triangle_irradiance, sol.back_irradiance), ref)
        row = (f"| {label} | {seconds:.1f} | {100 * sol.stats['estimated_error']:.2f} | {pct(l1)} | {pct(bias)} | "
               f"{sol.stats['links']:,} |")
        print(row)
        lines.append(row)

    for tol in [float(t) for t in args.tolerances.split(",") if t.strip()]:
        run(f"periodic, tolerance {tol:g}", tol, periodic=BOX)
    saved = far_field.FAR_ITERATIONS
    far_field.FAR_ITERATIONS = 0
    try:
        run("periodic without the far field, tolerance 0.02", 0.02, periodic=BOX)
    finally:
        far_field.FAR_ITERATIONS = saved
    run("not periodic (the plot alone), tolerance 0.02", 0.02)

    # --- 4. the periodic path tracer as a per-leaf estimator -------------------------------------
    lines += ["", "### The periodic path tracer as a per-leaf estimator (independent seed)", "",
              "| paths per triangle side | seconds | per-leaf L1 (R / G / B, %) |", "|---:|---:|---:|"]
    for spp in [int(s) for s in args.pt_samples.split(",") if s.strip()]:
        t0 = time.perf_counter()
        pf = periodic_reference(scene, box, samples_per_triangle=spp, seed=101, quantity="irradiance")
        pb = periodic_reference(scene, box, samples_per_triangle=spp, seed=102, quantity="irradiance", side="back")
        seconds = time.perf_counter() - t0
        l1, _ = leaf_errors(leaves, absorbed(probe, pf.value, pb.value), ref)
        row = f"| {spp} | {seconds:.1f} | {pct(l1)} |"
        print(row)
        lines.append(row)
    text = "\n".join(lines)
    print(text)
    if args.record:
        from mirad.files import atomic_write

        body = RESULTS.read_text().rstrip("\n") + "\n\n" + text + "\n"
        atomic_write(RESULTS, lambda handle: handle.write(body.encode()))


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    main()
