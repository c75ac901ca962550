"""Speed at equal error: mirad's hierarchical core against Mitsuba's path tracer, in one run.

For each scene: a cached high-sample path-traced reference per input triangle; then, both
sides warmed up (one untimed run each; a garbage collection before every timed run, so that
neither side pays for the other's garbage), mirad at a sweep of tolerances and the path tracer as
a per-triangle estimator (independent seed) at a sweep of samples per triangle, each timed
and measured against the reference (area-weighted relative L1 per triangle over the mean of
B, and over the mean of B - E). The time each side needs for 1 % (log-log interpolation
between the sweep points) and their ratio are printed; ``--record`` appends the table with
date and machine to validation/RESULTS.md.

Per shape too: each shape's power (the sum of area times radiosity over its triangles) against
the reference's, as a relative L1 over the shapes. mirad's rows carry it; the path tracer
answers it as a per-shape estimator, its paths spread over each shape's triangles in proportion
to their area (``allocation="area"``; each setting run once untimed and then timed, as a new
path count compiles new kernels), and the time each side needs for 2 % per shape is printed.

Usage (from the repository root)::

    python validation/bench_speed.py [--scenes cornell-box-fine,furnished-room] [--core legacy] [--record]
"""

from __future__ import annotations

import argparse
import datetime as _dt
import gc
import sys
import time
import warnings
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

import mirad  # noqa: E402
from mirad.arrays import group_sum  # noqa: E402
from mirad.measure import time_at_error  # noqa: E402
from mirad.reference import cached_reference, triangle_reference  # noqa: E402
from mirad.validate import machine  # noqa: E402

RESULTS = REPO / "validation" / "RESULTS.md"
SCENES = {
    "cornell-box": dict(tolerances=(0.5, 0.3, 0.2, 0.1, 0.05, 0.03, 0.02, 0.01), pt=(256, 1024, 4096, 16384, 65536),
                        pt_shape=(8, 32, 128, 512), reference=262144),
    "cornell-box-fine": dict(tolerances=(0.4, 0.35, 0.3, 0.25, 0.2, 0.15, 0.1, 0.05, 0.03, 0.02, 0.01), pt=(64, 256, 1024, 4096), reference=16384),
    "furnished-room": dict(tolerances=(0.4, 0.3, 0.2, 0.15, 0.1, 0.05, 0.03, 0.02, 0.01), pt=(64, 256, 1024, 4096),
                           reference=16384),
    "plant-canopy": dict(tolerances=(0.1, 0.05, 0.03, 0.02), pt=(64, 256, 1024, 4096), reference=16384),
    "tiny-bright-room": dict(tolerances=(0.1, 0.05, 0.03, 0.02), pt=(64, 256, 1024, 4096), reference=16384),
    "wall-pierce": dict(tolerances=(0.1, 0.05, 0.03, 0.02), pt=(64, 256, 1024, 4096), reference=16384),
}
TARGET = 0.01
#: The per-shape error each side's time is compared at.
SHAPE_TARGET = 0.02
#: Paths per triangle (their mean, spread by area) of the path tracer as a per-shape estimator.
PT_SHAPE = (8, 32, 128)


def errors(scene, value: np.ndarray, reference: np.ndarray) -> tuple[float, float]:
    """Area-weighted relative L1 per triangle over mean(B) and over mean(B - E)."""
    a = scene.tri_area[:, None]
    diff = float((a * np.abs(value - reference)).sum())
    reflected = np.maximum(reference - scene.tri_emission, 0.0)
    return diff / float((a * reference).sum()), diff / max(float((a * reflected).sum()), 1e-300)


def shape_error(scene, value: np.ndarray, reference: np.ndarray) -> float:
    """Relative L1 of the shapes' power: sum over shapes and channels of |P - P_ref| over the
    sum of P_ref, with P a shape's sum of triangle area times radiosity (W)."""
    count = int(scene.tri_shape.max()) + 1 if len(scene.tri_shape) else 0
    power = group_sum(scene.tri_shape, value, count, weights=scene.tri_area)
    ref = group_sum(scene.tri_shape, reference, count, weights=scene.tri_area)
    return float(np.abs(power - ref).sum() / max(float(ref.sum()), 1e-300))


def time_at(target: float, seconds, errs) -> float:
    """Seconds at which the error first reaches ``target``, log-log interpolated between sweep
    points (``mirad.measure.time_at_error``; nan when it never does)."""
    t, _ = time_at_error(seconds, errs, target)
    return float("nan") if t is None else t


def reached(target: float, seconds, errs) -> str:
    """``time_at`` as text: "at most" where the sweep's quickest point is already under the
    target (the crossing lies before the sweep), "not reached" where no point is."""
    t, how = time_at_error(seconds, errs, target)
    if t is None:
        return "not reached"
    return f"at most {t:.3f} s" if how == "at most" else f"{t:.3f} s"


def path_tracer_sweep(scene, ref, spps, lines: list, *, per_shape: bool) -> tuple[list, list]:
    """The path tracer as an estimator (seed 7, independent of the reference's) at each of
    ``spps`` paths per triangle: per triangle (the same paths on every triangle) or, with
    ``per_shape``, per shape (paths spread by area, each setting run once untimed first); each
    timed after a garbage collection. Appends its table rows to ``lines``; returns the seconds
    and the errors (per triangle over the mean of B, or per shape)."""
    options = {"allocation": "area"} if per_shape else {}
    seconds, errs = [], []
    for spp in spps:
        if per_shape:
            triangle_reference(scene, samples_per_triangle=spp, seed=7, **options)       # warm-up
        gc.collect()
        t = time.perf_counter()
        est = triangle_reference(scene, samples_per_triangle=spp, seed=7, **options)
        dt = time.perf_counter() - t
        e_s = shape_error(scene, est.radiosity, ref.radiosity)
        if per_shape:
            lines.append(f"| path tracer, per shape | {spp} paths/triangle by area | {dt:.3f} | | | {e_s:.2%} "
                         f"| | | | | {est.paths:,} | |")
            errs.append(e_s)
        else:
            e_b, e_r = errors(scene, est.radiosity, ref.radiosity)
            lines.append(f"| path tracer | {spp} paths/triangle | {dt:.3f} | {e_b:.2%} | {e_r:.2%} | {e_s:.2%} "
                         f"| | | | | {est.paths:,} | |")
            errs.append(e_b)
        print(lines[-1], flush=True)
        seconds.append(dt)
    return seconds, errs


def run(name: str, cfg: dict, core: str) -> tuple[list, str]:
    scene = mirad.load_scene(str(REPO / "scenes" / name / "scene.xml"))
    ref = cached_reference(scene, samples_per_triangle=cfg["reference"], seed=12345)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mirad.solve(scene, tolerance=cfg["tolerances"][0], core=core)           # warm-up
    triangle_reference(scene, samples_per_triangle=cfg["pt"][0], seed=1)        # warm-up
    lines = ["| side | setting | seconds | rel. L1 / mean B | rel. L1 / mean (B-E) | rel. L1 per shape | estimate "
             "| leaves | links | links/leaf | rays | where the time goes |", "|" + "---|" * 12]
    m_sec, m_err, m_shape = [], [], []
    for tol in cfg["tolerances"]:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            gc.collect()
            t = time.perf_counter()
            sol = mirad.solve(scene, tolerance=tol, seed=0, core=core)
            dt = time.perf_counter() - t
        e_b, e_r = errors(scene, sol.triangle_radiosity, ref.radiosity)
        e_s = shape_error(scene, sol.triangle_radiosity, ref.radiosity)
        st = sol.stats
        sec = st["seconds"]
        busy = ", ".join(f"{k} {v:.3f}" for k, v in sec.items() if k != "total" and v >= 0.001)
        lines.append(f"| mirad | tol {tol} | {dt:.3f} | {e_b:.2%} | {e_r:.2%} | {e_s:.2%} | {st['estimated_error']:.2%} | "
                     f"{st['leaves']:,} | {st['links']:,} | {st['links'] / max(st['leaves'], 1):.1f} | "
                     f"{st['rays']:,} | {busy} |")
        print(lines[-1], flush=True)
        m_sec.append(dt)
        m_err.append(e_b)
        m_shape.append(e_s)
    p_sec, p_err = path_tracer_sweep(scene, ref, cfg["pt"], lines, per_shape=False)
    s_sec, s_err = path_tracer_sweep(scene, ref, cfg.get("pt_shape", PT_SHAPE), lines, per_shape=True)
    noise = errors(scene, ref.radiosity + ref.stderr * np.sqrt(2 / np.pi), ref.radiosity)[0]
    tm, tp = time_at(TARGET, m_sec, m_err), time_at(TARGET, p_sec, p_err)
    sm, sp_ = time_at(SHAPE_TARGET, m_sec, m_shape), time_at(SHAPE_TARGET, s_sec, s_err)
    summary = (f"**{name}** ({scene.triangle_count:,} triangles; reference {cfg['reference']:,} paths/triangle, "
               f"noise {noise:.2%}): 1 % rel. L1 per triangle: mirad ({core} core) {tm:.3f} s, path tracer {tp:.3f} s, "
               f"ratio {tp / tm:.1f}x; 2 % per shape: mirad {reached(SHAPE_TARGET, m_sec, m_shape)}, path tracer "
               f"{reached(SHAPE_TARGET, s_sec, s_err)}, ratio {sp_ / sm:.1f}x")
    print(summary, flush=True)
    return lines, summary


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="cornell-box,cornell-box-fine,furnished-room")
    parser.add_argument("--record", action="store_true")
    parser.add_argument("--core", default="hierarchical", choices=("hierarchical", "legacy"))
    args = parser.parse_args(argv)
    out = []
    for name in args.scenes.split(","):
        lines, summary = run(name, SCENES[name], args.core)
        out.append("\n".join([summary, "", *lines, ""]))
    if args.record:
        stamp = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
        text = (f"\n## The {args.core} core against the path tracer ({stamp}, {machine()})\n\n"
                "`python validation/bench_speed.py`: both sides warmed up, timed in one run; errors against a "
                "cached path-traced reference.\n\n" + "\n".join(out))
        with open(RESULTS, "a", encoding="utf-8") as f:
            f.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
