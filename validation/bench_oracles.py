"""Refinement oracles side by side: error against Mitsuba path tracing, time, rays, estimate.

For each scene and each oracle (``kernel``, ``bf``, ``bound``) mirad's tolerance is swept
from coarse to fine; every point records seconds, shadow rays, links, the estimated error
and the measured error (area-weighted relative L1 per triangle against the cached path-traced
reference of ``run_all.py``), in the validation norm (over mean B) and in the tolerance's norm
(over mean reflected B). From the sweep: seconds and rays to reach 1 % (log-log
interpolation), whether error <= tolerance held at every point, the estimate / measured
ratios, and whether the error fell monotonically as the tolerance tightened. Writes
``validation/oracles-<scene>.png`` (error against seconds, one curve per oracle) and
appends a table to RESULTS.md.

Usage (from the repository root)::

    python validation/bench_oracles.py [--scenes cornell-box,furnished-room] [--max-seconds 120]
"""

from __future__ import annotations

import argparse
import datetime as _dt
import io
import sys
import time
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import mirad  # noqa: E402
from mirad.metrics import relative_l1  # noqa: E402
from mirad.reference import cached_reference  # noqa: E402
from mirad.solution import atomic_write  # noqa: E402
from mirad.validate import machine, time_at_error  # noqa: E402

HERE = REPO / "validation"
RESULTS = HERE / "RESULTS.md"
ORACLES = ("kernel", "bf", "bound")
TOLERANCES = (0.3, 0.2, 0.1, 0.05, 0.03, 0.02, 0.01, 0.005, 0.002)
#: The bound oracle refines every partially visible link (its lower bound is 0) and its
#: estimate carries 1/(1 - rho_max): it is capped at this many elements (marked "capped").
BOUND_MAX_ELEMENTS = 20_000
#: Reference samples per triangle (the same as run_all.py, so its cache is reused).
REFERENCE_SAMPLES = {"cornell-box": 65536, "furnished-room": 32768, "plant-canopy": 8192,
                     "cornell-box-fine": 32768}


def sweep(scene, ref, oracle: str, max_seconds: float) -> list[dict]:
    """Points of one oracle, coarse to fine, stopping before a step likely to overrun."""
    points = []
    spent = 0.0
    reflected_ref = np.maximum(ref.radiosity - scene.tri_emission[:, : ref.radiosity.shape[1]], 0)
    area = scene.tri_area
    for tol in TOLERANCES:
        if points and (spent + 4 * points[-1]["seconds"] > max_seconds or points[-1]["capped"]):
            break
        t = time.perf_counter()
        extra = {"max_elements": BOUND_MAX_ELEMENTS} if oracle == "bound" else {}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sol = mirad.solve(scene, tolerance=tol, oracle=oracle, quiet=True, core="legacy", **extra)
        seconds = time.perf_counter() - t
        spent += seconds
        b = sol.triangle_radiosity[:, : ref.radiosity.shape[1]]
        error = relative_l1(b, ref.radiosity, area=area)
        # the tolerance's norm: the same absolute error over the mean reflected radiosity
        scale = (ref.radiosity.mean(1) @ area) / max(reflected_ref.mean(1) @ area, 1e-300)
        points.append({"oracle": oracle, "tolerance": tol, "seconds": seconds, "rays": sol.stats["rays"],
                       "links": sol.stats["links"], "elements": sol.stats["elements"], "error": error,
                       "error_reflected": error * scale, "estimate": sol.stats["estimated_error"],
                       "capped": sol.stats["capped"]})
        print(f"  {oracle:6s} tol {tol:<6g} {seconds:7.2f} s  error {100 * error:.3f} %  "
              f"(reflected {100 * error * scale:.3f} %, estimate {100 * sol.stats['estimated_error']:.3f} %)  "
              f"rays {sol.stats['rays']:,}{'  (capped)' if sol.stats['capped'] else ''}", flush=True)
    return points


def at_one_percent(points: list[dict], key: str):
    errors = [p["error"] for p in points]
    values = [p[key] for p in points]
    value, _how = time_at_error(values, errors, 0.01)
    return None if value is None else float(value)


def plot(scene_name: str, by_oracle: dict, noise: float) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for oracle, points in by_oracle.items():
        if points:
            ax.loglog([p["seconds"] for p in points], [100 * p["error"] for p in points], "o-", label=oracle)
    ax.axhline(100 * noise, color="grey", ls=":", label="reference noise")
    ax.axhline(1.0, color="k", lw=0.5)
    ax.set_xlabel("mirad seconds (2 cores)")
    ax.set_ylabel("area-weighted rel. L1 per triangle (%)")
    ax.set_title(f"{scene_name}: refinement oracles")
    ax.legend()
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


def markdown(results: dict, stamp: str) -> str:
    lines = [f"## Refinement oracles: speed against error, {stamp}", "",
             f"- machine: {machine()}; CPU shared with other work while measuring (timings indicative)",
             "- error: area-weighted relative L1 per triangle against the cached path-traced reference; "
             "'reflected' is the same error over mean reflected radiosity (the tolerance's norm)", "",
             "| scene | oracle | tolerance | seconds | rays | links | error | reflected | estimate | est./meas. |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for scene_name, by_oracle in results.items():
        for oracle, points in by_oracle.items():
            for p in points:
                ratio = p["estimate"] / max(p["error_reflected"], 1e-300)
                capped = " (capped)" if p["capped"] else ""
                lines.append(f"| {scene_name} | {oracle}{capped} | {p['tolerance']:g} | {p['seconds']:.2f} | {p['rays']:,} | "
                             f"{p['links']:,} | {100 * p['error']:.3f} % | {100 * p['error_reflected']:.3f} % | "
                             f"{100 * p['estimate']:.3f} % | {ratio:.2f} |")
    lines += ["", "| scene | oracle | seconds to 1 % | rays to 1 % | error <= tolerance at every point | "
              "monotone | estimate within 2x |", "|---|---|---:|---:|---|---|---|"]
    for scene_name, by_oracle in results.items():
        for oracle, points in by_oracle.items():
            if not points:
                continue
            sec, rays = at_one_percent(points, "seconds"), at_one_percent(points, "rays")
            within = all(p["error_reflected"] <= p["tolerance"] for p in points)
            errs = [p["error"] for p in points]
            monotone = all(b <= a * 1.05 for a, b in zip(errs, errs[1:]))
            two_x = all(0.5 <= p["estimate"] / max(p["error_reflected"], 1e-300) <= 2.0 for p in points)
            lines.append(f"| {scene_name} | {oracle} | {'n/a' if sec is None else f'{sec:.2f}'} | "
                         f"{'n/a' if rays is None else f'{rays:,.0f}'} | {'yes' if within else 'no'} | "
                         f"{'yes' if monotone else 'no'} | {'yes' if two_x else 'no'} |")
    return "\n".join(lines) + "\n"


def bound_on_closed_forms() -> str:
    """The bound oracle's estimate against the exact error on the closed-form scenes."""
    sys.path.insert(0, str(REPO / "tests"))
    from conftest import F_PARALLEL, F_PERPENDICULAR, closed_box

    lines = ["Bound oracle on closed-form cases (tolerance 0.3, two passes; error in the tolerance's norm):", "",
             "| case | seconds | elements | rays | links proven visible / tested | measured error | bound estimate |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    cases = [("parallel squares", REPO / "scenes/closed-form/parallel-squares.xml", F_PARALLEL),
             ("perpendicular squares", REPO / "scenes/closed-form/perpendicular-squares.xml", F_PERPENDICULAR),
             ("furnace rho 0.5", closed_box(0.5, 1 / np.pi), None)]
    for name, source, exact_f in cases:
        scene = mirad.load_scene(source)
        t = time.perf_counter()
        sol = mirad.solve(scene, tolerance=0.3, oracle="bound", max_refine_passes=2, quiet=True, core="legacy")
        seconds = time.perf_counter() - t
        b, area = sol.triangle_radiosity[:, 0], sol.triangle_area
        if exact_f is None:
            measured = float(np.abs(b - 2.0) @ area / area.sum())        # exact B = 2, reflected 1
        else:
            mask = sol.triangle_shape == scene.shape_index("receiver")
            got = b[mask] @ area[mask] / area[mask].sum()
            reflected = (b - scene.tri_emission[:, 0]) @ area / area.sum()
            measured = abs(got - 0.5 * exact_f) * area[mask].sum() / (area.sum() * reflected)
        vc = sol.stats["visibility_classes"]
        lines.append(f"| {name} | {seconds:.2f} | {sol.stats['elements']:,} | {sol.stats['rays']:,} | "
                     f"{vc['visible']:,} / {vc['tested']:,} | {measured:.2e} | {sol.stats['estimated_error']:.3f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", default="cornell-box,furnished-room")
    parser.add_argument("--oracles", default="kernel,bf",
                        help="oracles swept on the scenes (bound is measured on the closed-form cases; "
                             "on the Cornell box one pass of it takes ~40 s and 1.4 M links)")
    parser.add_argument("--max-seconds", type=float, default=120.0, help="per oracle and scene")
    parser.add_argument("--no-record", action="store_true")
    args = parser.parse_args(argv)
    results = {}
    for name in args.scenes.split(","):
        scene = mirad.load_scene(REPO / "scenes" / name / "scene.xml")
        ref = cached_reference(scene, cache_dir=REPO / ".mirad-cache",
                               samples_per_triangle=REFERENCE_SAMPLES.get(name, 16384))
        noise = relative_l1(ref.radiosity + ref.stderr, ref.radiosity, area=scene.tri_area)
        print(f"{name}: reference noise {100 * noise:.3f} %", flush=True)
        results[name] = {o: sweep(scene, ref, o, args.max_seconds) for o in args.oracles.split(",")}
        png = plot(name, results[name], noise)
        atomic_write(HERE / f"oracles-{name}.png", lambda f, data=png: f.write(data))
    text = markdown(results, _dt.datetime.now().strftime("%Y-%m-%d %H:%M")) + "\n" + bound_on_closed_forms()
    print(text)
    if not args.no_record:
        old = RESULTS.read_text() if RESULTS.exists() else ""
        atomic_write(RESULTS, lambda f: f.write((old.rstrip("\n") + "\n\n" + text).encode()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
