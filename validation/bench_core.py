"""Core benchmark: speed next to error for the Cornell box at several tolerances.

For each tolerance it prints elements, leaves, links, rays, seconds per phase, the
estimated and the measured error (area-weighted relative L1 against a path-traced
reference), memory per link and per element, and the in-solver visibility
throughput (rays / seconds in the fused link-evaluation waves) next to the raw
``mi.Scene.ray_test`` throughput on the same scene with the same number of rays,
measured in the same run.

Usage (from the repository root)::

    python validation/bench_core.py [--scene PATH] [--tolerances 0.1,0.03,0.01]
                                    [--reference-samples 100000] [--record]

``--record`` appends a dated section (machine, variant, versions) with the table
to validation/RESULTS.md.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import math
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

import mirad  # noqa: E402  (sets up LLVM before mitsuba/drjit are imported)
from mirad.arrays import to_float  # noqa: E402
from mirad.reference import triangle_reference  # noqa: E402
from mirad.solution import atomic_write  # noqa: E402
from mirad.validate import machine  # noqa: E402

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

RESULTS = REPO / "validation" / "RESULTS.md"
#: Most rays traced by one ray_test launch in the raw throughput test (the solver's own launch
#: cap, visibility.MAX_LANES; single launches of ~9.5M rays crashed Dr.Jit 1.5 here).
MAX_RAYS_PER_CALL = 1 << 22
#: Origins are lifted off the surface by this fraction of the scene diagonal (as in the solver).
RAY_OFFSET = 1e-5

HEADER = """# mirad benchmark results

Benchmark figures recorded by the scripts in `validation/` (`python validation/bench_core.py
--record` appends a section). Each section gives the date and the machine (CPU or GPU, core
count, Mitsuba variant, Mitsuba and Dr.Jit versions) it was measured on, and speed is always
reported next to error: every row of timings sits beside the solver's estimated error and the
error measured against a path-traced reference (area-weighted relative L1 over triangles and
colour channels), so that a faster figure bought with a less accurate solution is visible.
Figures from different machines or variants are not comparable with one another.
"""


# ------------------------------------------------------------------------------------------
# Errors
# ------------------------------------------------------------------------------------------

def relative_l1(area: np.ndarray, value: np.ndarray, reference: np.ndarray) -> float:
    """sum(A |B - Bref|) / sum(A Bref) over triangles and channels."""
    a = area[:, None]
    return float((a * np.abs(value - reference)).sum() / max((a * reference).sum(), 1e-300))


def relative_noise(area: np.ndarray, stderr: np.ndarray, reference: np.ndarray) -> float:
    """sum(A stderr) / sum(A Bref): the reference's own noise in the error's norm."""
    a = area[:, None]
    return float((a * stderr).sum() / max((a * reference).sum(), 1e-300))


# ------------------------------------------------------------------------------------------
# Raw ray_test throughput
# ------------------------------------------------------------------------------------------

def _triangle_points(verts: np.ndarray, tri: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Uniform points on triangles tri (square-root warp), float64 (N, 3)."""
    u = np.sqrt(rng.random(len(tri)))[:, None]
    v = rng.random(len(tri))[:, None]
    v0, v1, v2 = verts[tri, 0], verts[tri, 1], verts[tri, 2]
    return v0 * (1 - u) + v1 * (u * (1 - v)) + v2 * (u * v)


def make_rays(scene, count: int, seed: int):
    """``count`` rays between uniform points on random triangles of the scene, uploaded.

    Origins are lifted by RAY_OFFSET * diagonal along the triangle normal, flipped to the
    side the ray leaves from (as the solver only traces rays leaving a patch's front);
    maxt = 0.999 * distance. Returns an mi.Ray3f whose fields are already evaluated.
    """
    rng = np.random.default_rng(seed)
    verts = np.asarray(scene.tri_vertices, dtype=np.float64)
    normal = np.asarray(scene.tri_normal, dtype=np.float64)
    t = scene.triangle_count
    ti = rng.integers(0, t, count)
    tj = rng.integers(0, t, count)
    same = ti == tj
    tj[same] = (tj[same] + 1) % max(t, 1)
    p = _triangle_points(verts, ti, rng)
    q = _triangle_points(verts, tj, rng)
    n = normal[ti]
    side = np.where(np.einsum("ij,ij->i", q - p, n) >= 0, 1.0, -1.0)[:, None]
    o = p + n * side * (RAY_OFFSET * scene.diagonal)
    d = q - o
    dist = np.linalg.norm(d, axis=1)
    dist = np.where(dist > 0, dist, 1.0)
    d /= dist[:, None]
    origin = mi.Point3f(to_float(o[:, 0]), to_float(o[:, 1]), to_float(o[:, 2]))
    direction = mi.Vector3f(to_float(d[:, 0]), to_float(d[:, 1]), to_float(d[:, 2]))
    ray = mi.Ray3f(origin, direction)
    ray.maxt = to_float(0.999 * dist)
    dr.eval(ray.o, ray.d, ray.maxt)
    dr.sync_thread()
    return ray


def raw_ray_test(scene, count: int, *, repeats: int = 2, seed: int = 7) -> dict:
    """Fastest of ``repeats`` timings of ray_test over ``count`` rays (2^22 per call at most).

    The rays are built and uploaded before the timer starts; a count above the cap reuses
    the same full batch for every whole chunk and a second, smaller batch for the rest.
    """
    count = max(int(count), 1)
    full, rest = divmod(count, MAX_RAYS_PER_CALL)
    batches = []
    if full:
        batches.append((make_rays(scene, MAX_RAYS_PER_CALL, seed), full))
    if rest:
        batches.append((make_rays(scene, rest, seed + 1), 1))
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        for ray, times in batches:
            for _ in range(times):
                blocked = scene.mi_scene.ray_test(ray)
                dr.eval(blocked)
                dr.sync_thread()
        best = min(best, time.perf_counter() - t0)
    # occlusion statistics (untimed) of the first batch
    ray, _ = batches[0]
    blocked = scene.mi_scene.ray_test(ray)
    blocked_fraction = float(dr.count(blocked)[0]) / dr.width(blocked) if dr.width(blocked) else 0.0
    return {"rays": count, "seconds": best, "rays_per_second": count / best,
            "blocked_fraction": blocked_fraction}


# ------------------------------------------------------------------------------------------
# Benchmark
# ------------------------------------------------------------------------------------------

def run_tolerance(scene, tol: float, ref, area: np.ndarray) -> dict:
    sol = mirad.solve(scene, tolerance=tol, seed=0)
    st = sol.stats
    sec = st["seconds"]
    measured = relative_l1(area, np.asarray(sol.triangle_radiosity, dtype=np.float64), ref.radiosity)
    raw = raw_ray_test(scene, st["rays"])
    in_solver = st["rays"] / sec["visibility"] if sec["visibility"] > 0 else float("nan")
    mem = st["memory_bytes"]
    return {
        "tolerance": tol,
        "elements": st["elements"],
        "leaves": st["leaves"],
        "links": st["links"],
        "rays": st["rays"],
        "seconds": sec,
        "estimated_error": st["estimated_error"],
        "estimated_error_of_mean": st["estimated_error_of_mean"],
        "measured_error": measured,
        "solver_iterations": st["solver_iterations"],
        "bytes_per_link": mem["links"] / max(st["links"], 1),
        "bytes_per_element": mem["elements"] / max(st["elements"], 1),
        "memory_mib": (mem["links"] + mem["elements"]) / 2**20,
        "in_solver_rays_per_second": in_solver,
        "raw_rays_per_second": raw["rays_per_second"],
        "raw_seconds": raw["seconds"],
        "raw_blocked_fraction": raw["blocked_fraction"],
        "ratio": in_solver / raw["rays_per_second"],
        "variant": st["variant"],
    }


def _fmt_int(x) -> str:
    return f"{int(x):,}"


def table(rows: list[dict]) -> str:
    """Markdown table: one column per tolerance, one row per quantity."""
    phases = ["link", "refine", "visibility", "solve", "direct", "total"]
    lines = [("quantity", [f"tol {r['tolerance']:g}" for r in rows])]
    add = lambda name, f: lines.append((name, [f(r) for r in rows]))  # noqa: E731
    add("elements", lambda r: _fmt_int(r["elements"]))
    add("leaves", lambda r: _fmt_int(r["leaves"]))
    add("links", lambda r: _fmt_int(r["links"]))
    add("rays", lambda r: _fmt_int(r["rays"]))
    for p in phases:
        note = " (incl. its visibility waves)" if p == "refine" else ""
        add(f"seconds: {p}{note}", lambda r, p=p: f"{r['seconds'].get(p, 0.0):.3f}")
    add("estimated error (tolerance's norm: over mean B - E)", lambda r: f"{r['estimated_error']:.4f}")
    add("estimated error (over mean B, as measured below)", lambda r: f"{r['estimated_error_of_mean']:.4f}")
    add("measured error vs reference", lambda r: f"{r['measured_error']:.4f}")
    add("solver iterations", lambda r: str(r["solver_iterations"]))
    add("bytes per link", lambda r: f"{r['bytes_per_link']:.1f}")
    add("bytes per element", lambda r: f"{r['bytes_per_element']:.1f}")
    add("memory (elements + links), MiB", lambda r: f"{r['memory_mib']:.2f}")
    add("in-solver visibility, Mrays/s", lambda r: f"{r['in_solver_rays_per_second'] / 1e6:.2f}")
    add("raw ray_test (same ray count), Mrays/s", lambda r: f"{r['raw_rays_per_second'] / 1e6:.2f}")
    add("in-solver / raw (target >= 0.70)", lambda r: f"{r['ratio']:.2f}")
    out = []
    for i, (name, cells) in enumerate(lines):
        out.append("| " + " | ".join([name] + cells) + " |")
        if i == 0:
            out.append("|" + "---|" + "---:|" * len(cells))
    return "\n".join(out)


def record(section: str) -> None:
    """Append ``section`` to RESULTS.md (header created if missing), atomically."""
    text = RESULTS.read_text() if RESULTS.exists() else HEADER
    text = text.rstrip("\n") + "\n\n" + section.rstrip("\n") + "\n"
    atomic_write(RESULTS, lambda handle: handle.write(text.encode()))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default=str(REPO / "scenes" / "cornell-box" / "scene.xml"))
    ap.add_argument("--tolerances", default="0.1,0.03,0.01",
                    help="comma-separated list of tolerances")
    ap.add_argument("--reference-samples", type=int, default=100000,
                    help="path-traced samples per triangle of the reference")
    ap.add_argument("--record", action="store_true", help="append the results to validation/RESULTS.md")
    args = ap.parse_args(argv)
    tolerances = [float(t) for t in args.tolerances.split(",") if t.strip()]

    scene = mirad.load_scene(args.scene)
    area = np.asarray(scene.tri_area, dtype=np.float64)
    print(f"scene {args.scene}: {scene.triangle_count} triangles, diagonal {scene.diagonal:.4g}")

    t = time.perf_counter()
    mirad.solve(scene, tolerance=0.1, seed=0)                 # warm-up: JIT compilation
    print(f"warm-up solve (tolerance 0.1): {time.perf_counter() - t:.2f} s")

    ref = triangle_reference(scene, samples_per_triangle=args.reference_samples, seed=1)
    ref_noise = relative_noise(area, ref.stderr, ref.radiosity)
    print(f"reference: {args.reference_samples} samples/triangle, {ref.paths:,} paths, "
          f"{ref.seconds:.2f} s, own noise (area-weighted relative stderr) {ref_noise:.5f}")

    rows = []
    for tol in tolerances:
        r = run_tolerance(scene, tol, ref, area)
        rows.append(r)
        print(f"tolerance {tol:g}: {r['elements']} elements, {r['links']} links, {r['rays']:,} rays, "
              f"total {r['seconds']['total']:.2f} s, measured error {r['measured_error']:.4f}, "
              f"in-solver/raw {r['ratio']:.2f} (raw rays blocked: {r['raw_blocked_fraction']:.1%})",
              flush=True)

    md = table(rows)
    print()
    print(md)

    if args.record:
        variant = rows[0]["variant"] if rows else mi.variant()
        try:
            scene_name = str(Path(args.scene).resolve().relative_to(REPO))
        except ValueError:
            scene_name = args.scene
        section = "\n".join([
            f"## bench_core: {scene_name}, {_dt.datetime.now().strftime('%Y-%m-%d %H:%M')}",
            "",
            f"- machine: {machine()}",
            f"- Mitsuba variant: {variant}; mitsuba {mi.__version__}, drjit {dr.__version__}, "
            f"mirad {mirad.__version__}",
            f"- scene: {scene.triangle_count} triangles; seed 0, samples per link 16 (default)",
            f"- reference: `triangle_reference`, {args.reference_samples} samples/triangle, seed 1, "
            f"{ref.seconds:.1f} s; its own noise (area-weighted relative stderr) {ref_noise:.5f}",
            "- in-solver throughput = stats['rays'] / seconds['visibility'] (fused link waves: "
            "sampling + form factor + ray_test + reduction; rays counted are the active shadow "
            "rays); raw = `mi.Scene.ray_test` alone on the same number of random rays between "
            "uniform points on random triangles, uploaded beforehand, faster of two runs",
            "",
            md,
        ])
        record(section)
        print(f"\nappended to {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
