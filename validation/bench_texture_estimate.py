"""Does the error estimate account for shadow-texture links? Estimate against measured error.

For the shadow cases with complex occluders (scenes/shadow-cases/table.xml, leaves.xml), solve
with and without ``shadow_textures`` over a sweep of tolerances and compare the solution's
``estimated_error`` with the per-triangle error measured against a Mitsuba path-traced
reference (``cached_reference``), in the tolerance's norm (relative L1 over the mean reflected
radiosity, as validation/bench_oracles.py). The issue's target: estimate within 2x of measured
with texture links. Per-triangle errors see a texture link's mean transfer, not its detail
inside an element (validation/bench_shadow_images.py measures that on images).

Usage (from the repository root)::

    python validation/bench_texture_estimate.py [--tolerances 0.05,0.02,0.01] [--record]
"""

from __future__ import annotations

import argparse
import datetime as _dt
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import mirad  # noqa: E402
import mitsuba as mi  # noqa: E402
from mirad.metrics import relative_l1  # noqa: E402
from mirad.reference import cached_reference  # noqa: E402
from mirad.validate import machine  # noqa: E402

RESULTS = REPO / "validation" / "RESULTS.md"


def sweep(name: str, tolerances, samples: int) -> list[dict]:
    scene = mirad.load_scene(REPO / "scenes" / "shadow-cases" / f"{name}.xml")
    ref = cached_reference(scene, cache_dir=REPO / ".mirad-cache", samples_per_triangle=samples)
    c = ref.radiosity.shape[1]
    area = scene.tri_area
    reflected = np.maximum(ref.radiosity - scene.tri_emission[:, :c], 0)
    scale = (ref.radiosity.mean(1) @ area) / max(reflected.mean(1) @ area, 1e-300)
    noise = relative_l1(ref.radiosity + ref.stderr, ref.radiosity, area=area) * scale
    rows = []
    for tol in tolerances:
        for textures in (False, True):
            t = time.perf_counter()
            sol = mirad.solve(scene, tolerance=tol, shadow_textures=textures, quiet=True, core="legacy")
            seconds = time.perf_counter() - t
            measured = relative_l1(sol.triangle_radiosity[:, :c], ref.radiosity, area=area) * scale
            rows.append({"scene": name, "tolerance": tol, "textures": textures, "seconds": seconds,
                         "leaves": sol.stats["leaves"], "links": sol.stats["links"],
                         "texture_links": sol.stats["texture_links"], "measured": measured,
                         "estimate": sol.stats["estimated_error"], "noise": noise})
            r = rows[-1]
            print(f"{name} tol {tol:<5g} textures {textures!s:5} {seconds:6.2f} s  leaves {r['leaves']:5d}  "
                  f"texture links {r['texture_links']:5d}  measured {100 * measured:.2f} %  "
                  f"estimate {100 * r['estimate']:.2f} %  (reference noise {100 * noise:.2f} %)", flush=True)
    return rows


def markdown(rows: list[dict], samples: int, argv) -> str:
    when = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    lines = [f"## Error estimate with shadow-texture links (issue 10), {when}", "",
             f"`python validation/bench_texture_estimate.py {' '.join(argv)}`; {machine()}, variant "
             f"{mi.variant()}. Per-triangle error against "
             f"a path-traced reference ({samples} samples per triangle), relative L1 over the mean reflected "
             "radiosity (the tolerance's norm); estimate = stats['estimated_error'].", "",
             "| scene | tolerance | textures | seconds | leaves | links | texture links | measured | estimate | est./meas. |",
             "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['tolerance']:g} | {'on' if r['textures'] else 'off'} | {r['seconds']:.2f} | "
                     f"{r['leaves']:,} | {r['links']:,} | {r['texture_links']:,} | {100 * r['measured']:.2f} % | "
                     f"{100 * r['estimate']:.2f} % | {r['estimate'] / max(r['measured'], 1e-300):.2f} |")
    noise = {r["scene"]: r["noise"] for r in rows}
    lines += ["", "Reference noise (same norm): " + ", ".join(f"{k} {100 * v:.2f} %" for k, v in noise.items()), ""]
    return "\n".join(lines)


def main(argv=None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="table,leaves")
    parser.add_argument("--tolerances", default="0.05,0.02,0.01")
    parser.add_argument("--samples", type=int, default=4096, help="reference paths per triangle")
    parser.add_argument("--record", action="store_true", help="append the table to validation/RESULTS.md")
    args = parser.parse_args(argv)
    tolerances = [float(x) for x in args.tolerances.split(",")]
    rows = [r for name in args.scenes.split(",") for r in sweep(name, tolerances, args.samples)]
    text = markdown(rows, args.samples, argv)
    print(text)
    if args.record:
        with open(RESULTS, "a") as f:
            f.write("\n" + text)


if __name__ == "__main__":
    main()
