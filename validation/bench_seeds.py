"""How much of mirad's per-triangle error moves with the seed: one solve per seed, against a
cached path-traced reference.

For each scene and tolerance: the area-weighted relative L1 per triangle (over the mean of B,
as ``bench_speed`` measures it) of each seed's solve and their mean; the error of the seeds'
mean solution (what is left once the seed's part averages out: the method's own bias plus the
reference's noise); the spread between seeds (the mean pairwise L1 between two seeds' solutions
over sqrt(2): one solve's seed-dependent part); and the mean estimate. The seed moves the shadow
rays of the passes and of the final gather, the points of the clusters, and through them the
refinement's decisions: a spread that more rays do not shrink is the decisions', not the rays'.

Usage (from the repository root)::

    python validation/bench_seeds.py [--scenes cornell-box-fine,furnished-room] [--tolerances 0.3,0.2]
                                     [--seeds 4] [--record]
"""

from __future__ import annotations

import argparse
import datetime as _dt
import itertools
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_speed import REPO, RESULTS, SCENES, errors  # noqa: E402

import mirad  # noqa: E402
from mirad.reference import cached_reference  # noqa: E402
from mirad.validate import machine  # noqa: E402


def spread(scene, solutions: list[np.ndarray], reference: np.ndarray) -> float:
    """Mean pairwise area-weighted L1 between the solutions (T, C), over the reference's area
    times radiosity, divided by sqrt(2): the seed-dependent part of one solution's error."""
    a = scene.tri_area[:, None]
    total = float((a * reference).sum())
    pairs = [float((a * np.abs(x - y)).sum()) / total for x, y in itertools.combinations(solutions, 2)]
    return float(np.mean(pairs)) / np.sqrt(2.0)


def run(name: str, tolerances: list[float], seeds: int) -> list[str]:
    scene = mirad.load_scene(str(REPO / "scenes" / name / "scene.xml"))
    ref = cached_reference(scene, samples_per_triangle=SCENES[name]["reference"], seed=12345)
    # (the reference's own noise, as bench_speed reads it: its standard errors' mean absolute value)
    noise = errors(scene, ref.radiosity + ref.stderr * np.sqrt(2 / np.pi), ref.radiosity)[0]
    lines = [f"**{name}** ({len(scene.tri_area):,} triangles; reference {SCENES[name]['reference']:,} paths/triangle, "
             f"noise {noise:.2%}), {seeds} seeds:", "",
             "| tolerance | rel. L1 per seed (mean) | lowest, highest | rel. L1 of the seeds' mean | seed spread "
             "| estimate | seconds (median) | rays (mean) |", "|" + "---|" * 8]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mirad.solve(scene, tolerance=tolerances[0], seed=seeds)                    # warm-up
        for tol in tolerances:
            solutions, errs, seconds, rays, estimates = [], [], [], [], []
            for seed in range(seeds):
                t = time.perf_counter()
                sol = mirad.solve(scene, tolerance=tol, seed=seed)
                seconds.append(time.perf_counter() - t)
                solutions.append(sol.triangle_radiosity)
                errs.append(errors(scene, sol.triangle_radiosity, ref.radiosity)[0])
                rays.append(sol.stats["rays"])
                estimates.append(sol.stats["estimated_error"])
            mean_err = errors(scene, np.mean(solutions, axis=0), ref.radiosity)[0]
            lines.append(f"| {tol} | {np.mean(errs):.3%} | {min(errs):.3%}, {max(errs):.3%} | {mean_err:.3%} "
                         f"| {spread(scene, solutions, ref.radiosity):.3%} | {np.mean(estimates):.2%} "
                         f"| {np.median(seconds):.3f} | {np.mean(rays):,.0f} |")
            print(lines[-1], flush=True)
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="cornell-box,cornell-box-fine,furnished-room")
    parser.add_argument("--tolerances", default="0.3,0.2")
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--record", action="store_true")
    args = parser.parse_args(argv)
    if args.seeds < 2:
        parser.error(f"--seeds {args.seeds}: the spread between seeds needs at least 2")
    tolerances = [float(t) for t in args.tolerances.split(",")]
    out = []
    for name in args.scenes.split(","):
        if name not in SCENES:
            parser.error(f"--scenes: unknown scene {name!r}; known: {', '.join(SCENES)}")
        out.append("\n".join(run(name, tolerances, args.seeds) + [""]))
    if args.record:
        stamp = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
        text = (f"\n## The seed's part of the error ({stamp}, {machine()})\n\n"
                "`python validation/bench_seeds.py`: one solve per seed against a cached path-traced reference.\n\n"
                + "\n".join(out))
        with open(RESULTS, "a", encoding="utf-8") as f:
            f.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
