"""The plant canopy under the CIE standard overcast sky: mirad's estimated against measured error.

Writes the canopy of ``scenes/plant-canopy`` with its sun and constant sky replaced by an overcast
sky (``mirad.sky.overcast_sky``, 100 W/m^2 horizontal, z up) into a work folder, computes a
path-traced reference of both leaf sides (``mirad.reference.cached_reference``, paths allocated by
area), then solves with ``core="hierarchical"`` at each tolerance and prints, per tolerance: seconds,
the estimated error, the measured area-weighted relative L1 against the reference (and the
reference's own noise), and how many direct-light points the leaves got (the core caps them at
``MAX_DIRECT_SAMPLES``). It also measures the direct-light estimator alone: the direct irradiance of
every input triangle (front) from ``direct_irradiance`` at 64 and 1024 points against a 65,536-point
estimate, with the standard error it reports.

    python validation/bench_sky.py --work sky-canopy --reference-samples 32768
"""

from __future__ import annotations

import argparse
import os
import shutil
import time
from pathlib import Path

import numpy as np

import mirad
from mirad import emitters
from mirad.core import MAX_DIRECT_SAMPLES  # (a safety cap, far above what the tolerances ask)
from mirad.metrics import compare
from mirad.reference import cached_reference

ROOT = Path(__file__).resolve().parents[1]
CANOPY = ROOT / "scenes" / "plant-canopy"


def overcast_canopy(work: Path, irradiance: float) -> Path:
    """scene.xml in ``work``: the plant canopy lit by an overcast sky only (meshes copied beside it)."""
    from mirad import sky

    work.mkdir(parents=True, exist_ok=True)
    for ply in CANOPY.glob("*.ply"):
        shutil.copyfile(ply, work / ply.name)
    text = (CANOPY / "scene.xml").read_text()
    start = text.index('    <emitter type="directional"')
    stop = text.index("</emitter>", text.index('<emitter type="constant"')) + len("</emitter>")
    snippet = sky.write_sky({"sky": sky.overcast_sky(irradiance, up="+z")}, work / "sky.exr")
    snippet = snippet.replace(f'value="{work / "sky.exr"}"', 'value="sky.exr"')
    (work / "scene.xml").write_text(text[:start] + "    " + snippet.replace("\n", "\n    ") + text[stop:])
    return work / "scene.xml"


def both_sides(scene, *, samples: int, cache: Path):
    back = np.asarray(scene.back_triangles, dtype=np.int64)
    front = cached_reference(scene, cache_dir=cache, samples_per_triangle=samples, seed=1, allocation="area",
                             quiet=False)
    b = cached_reference(scene, cache_dir=cache, samples_per_triangle=samples, seed=1, allocation="area",
                         quiet=False, triangles=back, side="back")
    area = np.concatenate([scene.tri_area, scene.tri_area[back]])
    return (np.concatenate([front.radiosity, b.radiosity]), np.concatenate([front.stderr, b.stderr]), area, back,
            front.seconds + b.seconds)


def direct_points(scene, samples: int, seed: int):
    tv = scene.vertices[scene.faces]
    n = len(tv)
    curve = (scene.curve_center, scene.curve_axis, scene.curve_radius)
    h, err, _ = emitters.direct_irradiance(scene, tv, scene.tri_normal, curve, samples=samples, seed=seed,
                                           keys=np.arange(n), with_error=True)
    return h[:, 1], err[:, 1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", default="sky-canopy", help="folder for the scene, its EXR and the reference cache")
    parser.add_argument("--irradiance", type=float, default=100.0, help="horizontal sky irradiance, W/m^2")
    parser.add_argument("--reference-samples", type=int, default=32768)
    parser.add_argument("--tolerances", default="0.05,0.02,0.01")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--direct-only", action="store_true", help="measure the direct-light estimator only")
    args = parser.parse_args()
    work = Path(args.work)
    path = work / "scene.xml" if (work / "scene.xml").exists() else overcast_canopy(work, args.irradiance)
    scene = mirad.load_scene(path)
    print(f"{path}: {scene.triangle_count} triangles, fingerprint {scene.fingerprint}")

    # --- the direct-light estimator alone (front sides) -------------------------------------
    truth = np.mean([direct_points(scene, 16384, 100 + s)[0] for s in range(4)], axis=0)
    for samples in (64, 1024):
        h, err = direct_points(scene, samples, args.seed)
        lit = truth > 0
        dev = h[lit] - truth[lit]
        print(f"direct light, {samples} points per triangle: RMS relative deviation "
              f"{np.sqrt(np.mean((dev / truth[lit]) ** 2)):.4%}, reported {np.sqrt(np.mean((err[lit] / truth[lit]) ** 2)):.4%}"
              f" (ratio reported/measured {np.sqrt(np.mean(err[lit] ** 2)) / np.sqrt(np.mean(dev ** 2)):.2f}); "
              f"area-weighted L1 {np.sum(np.abs(dev) * scene.tri_area[lit]) / np.sum(truth[lit] * scene.tri_area[lit]):.4%}")

    if args.direct_only:
        return
    # --- reference and the tolerance sweep ---------------------------------------------------
    ref_b, ref_se, area, back, seconds = both_sides(scene, samples=args.reference_samples, cache=work / "cache")
    noise = compare(ref_b, ref_b, ref_se, area=area)["noise"]
    print(f"reference: {args.reference_samples} paths per triangle side on average, {seconds:.0f} s, "
          f"noise floor L1 {noise['l1']:.3%}")
    mirad.solve(scene, core="hierarchical", tolerance=0.1, seed=args.seed)     # JIT warm-up
    counts = {}
    original = emitters.direct_irradiance

    def counting(scene_, verts, normals, curve, *, samples, seed, keys, with_error=False):
        for key in np.asarray(keys):
            counts[int(key)] = int(samples)
        return original(scene_, verts, normals, curve, samples=samples, seed=seed, keys=keys, with_error=with_error)

    emitters.direct_irradiance = counting
    try:
        for tol in [float(t) for t in args.tolerances.split(",")]:
            counts.clear()
            t0 = time.perf_counter()
            sol = mirad.solve(scene, core="hierarchical", tolerance=tol, seed=args.seed)
            seconds = time.perf_counter() - t0
            value = np.concatenate([sol.triangle_radiosity, sol.back_radiosity[back]])
            err = compare(value, ref_b, ref_se, area=area)
            samples = np.array(list(counts.values()))
            print(f"tolerance {tol:g}: {seconds:.1f} s, estimated {sol.stats['estimated_error']:.3%}, measured L1 "
                  f"{err['l1']:.3%} (reference noise {noise['l1']:.3%}); direct points per leaf: median "
                  f"{int(np.median(samples))}, at the cap ({MAX_DIRECT_SAMPLES}) "
                  f"{np.mean(samples >= MAX_DIRECT_SAMPLES):.1%} of {len(samples)} elements")
    finally:
        emitters.direct_irradiance = original


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    main()
