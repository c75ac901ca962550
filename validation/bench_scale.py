"""Scale benchmark: procedural canopies of 1k, 10k and 100k leaf triangles (issue 8).

Measures, each solve in its own child process (so peak RSS is that solve's own):
- links against elements (log-log slope over the sizes; target <= 1.2);
- memory: array bytes per link and per element (``stats["memory_bytes"]``; targets <= 100 and
  <= 200 B) and the peak resident set size of the process (``resource.getrusage``);
- time, links, rays and the estimated error of each solve (the 100k canopy: "2 % in minutes");
- at ~1k triangles, the legacy core's clustering on against off at equal tolerance: seconds and the error against
  a path-traced reference (``mirad.reference``, area-weighted relative L1 / RMS per triangle);
- Dask: rays/s of one visibility wave on a LocalCluster of 2 worker processes against the same
  wave in-process (warm: second call of each), and the per-link results compared bitwise.

The scenes are generated on demand (scenes/canopy-scale/make.py) into its git-ignored
``generated/`` folder.

    python validation/bench_scale.py                     # everything, print only
    python validation/bench_scale.py --record            # and append to validation/RESULTS.md
    python validation/bench_scale.py --sizes 1000,10000 --skip-dask
    python validation/bench_scale.py --core legacy --sizes 1000,3000,10000 --skip-dask --skip-compare
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import importlib.util
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

RESULTS = REPO / "validation" / "RESULTS.md"
GENERATED = REPO / "scenes" / "canopy-scale" / "generated"
REFERENCE_SAMPLES = 4096


def _make_module():
    spec = importlib.util.spec_from_file_location("canopy_make", REPO / "scenes" / "canopy-scale" / "make.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def canopy(triangles: int, seed: int = 0) -> Path:
    """The generated canopy of about ``triangles`` leaf triangles (written if missing)."""
    make = _make_module()
    out = GENERATED / f"canopy-{triangles}"
    if not (out / "scene.xml").exists():
        plants, per = make.plan(triangles)
        make.make_canopy(out, plants=plants, leaves_per_plant=per, seed=seed)
    return out / "scene.xml"


# ------------------------------------------------------------------------------------------
# One solve in a child process
# ------------------------------------------------------------------------------------------

def child(scene_path: str, options: dict, reference: str | None) -> dict:
    """Solve (inside the child): stats, wall seconds, peak RSS, and the error if a reference is given."""
    import mirad
    from mirad import metrics
    from mirad.reference import Reference

    scene = mirad.load_scene(scene_path)
    t = time.perf_counter()
    sol = mirad.solve(scene, **options)
    wall = time.perf_counter() - t
    st = sol.stats
    out = {"wall": wall, "peak_rss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
           "triangles": int(scene.triangle_count), "patches": int(len(scene.patch_tri)),
           **{k: st[k] for k in ("elements", "leaves", "links", "rays", "estimated_error", "estimated_error_of_mean",
                                  "refine_passes", "clusters", "seconds", "memory_bytes", "capped")}}
    out["radiosity_digest"] = hashlib.sha256(np.ascontiguousarray(sol.triangle_radiosity).tobytes()).hexdigest()[:16]
    if reference:
        ref = Reference.load(reference)
        cmp = metrics.compare(sol.triangle_radiosity[:, :3] if sol.triangle_radiosity.shape[1] == 3
                              else np.repeat(sol.triangle_radiosity, 3, axis=1), ref.radiosity, ref.stderr,
                              area=scene.tri_area)
        out["error"] = {"l1": cmp["l1"], "rms": cmp["rms"], "noise_l1": cmp["noise"]["l1"]}
    return out


def run_child(scene: Path, options: dict, reference: Path | None = None, timeout: float = 3600) -> dict:
    cmd = [sys.executable, __file__, "--child", str(scene), json.dumps(options), str(reference or "")]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        raise RuntimeError(f"child failed: {proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


# ------------------------------------------------------------------------------------------
# Benchmarks
# ------------------------------------------------------------------------------------------

def scale_sweep(sizes, tolerance: float, core: str = "hierarchical") -> list[dict]:
    rows = []
    for n in sizes:
        path = canopy(n)
        print(f"solving {path.parent.name} at tolerance {tolerance} ({core} core) ...", flush=True)
        row = run_child(path, {"tolerance": tolerance, "core": core})
        row["name"] = path.parent.name
        row["tolerance"] = tolerance
        row["core"] = core
        print(json.dumps(row), flush=True)
        rows.append(row)
    return rows


def slope(x, y) -> float:
    return float(np.polyfit(np.log(np.asarray(x, float)), np.log(np.asarray(y, float)), 1)[0])


def clustering_on_off(triangles: int, tolerance: float) -> dict:
    import mirad
    from mirad.reference import cached_reference, cache_path

    path = canopy(triangles)
    scene = mirad.load_scene(path)
    ref = cached_reference(scene, samples_per_triangle=REFERENCE_SAMPLES, seed=11,
                           cache_dir=REPO / ".mirad-cache")
    ref_file = cache_path(scene, cache_dir=REPO / ".mirad-cache", samples_per_triangle=REFERENCE_SAMPLES,
                          seed=11, max_depth=-1, method="outgoing", triangles=None)
    out = {"name": path.parent.name, "tolerance": tolerance, "reference_seconds": ref.seconds,
           "reference_paths": ref.paths}
    for mode in ("on", "off"):
        print(f"clustering {mode} on {path.parent.name} ...", flush=True)
        out[mode] = run_child(path, {"tolerance": tolerance, "clustering": mode, "core": "legacy"}, ref_file)
        print(json.dumps(out[mode]), flush=True)
    # where the measured error comes from: it falls like 1/sqrt(samples per link)
    for spl in (64, 256):
        out[f"on, {spl} samples/link"] = run_child(path, {"tolerance": tolerance, "clustering": "on", "core": "legacy",
                                                          "samples_per_link": spl}, ref_file)
    return out


def dask_solve(triangles: int, tolerance: float, workers: int = 2) -> dict:
    """A whole solve in-process and with ``workers`` Dask workers: times and bitwise identity."""
    path = canopy(triangles)
    out = {"name": path.parent.name, "tolerance": tolerance, "workers": workers}
    for key, extra in (("in_process", {}), ("dask", {"workers": workers})):
        print(f"solve {path.parent.name} {key} ...", flush=True)
        out[key] = run_child(path, {"tolerance": tolerance, **extra})
        print(json.dumps(out[key]), flush=True)
    a, b = out["in_process"], out["dask"]
    out["identical"] = all(a[k] == b[k] for k in ("links", "rays", "elements", "estimated_error", "radiosity_digest"))
    return out


def dask_wave(triangles: int, links: int = 1_000_000, workers: int = 2) -> dict:
    """Rays/s of one visibility wave, in-process against a LocalCluster of ``workers`` processes."""
    import mirad
    from mirad.distributed import DaskEvaluator
    from mirad.solver import Problem
    from mirad.visibility import LinkWave, evaluate_links

    path = canopy(triangles)
    scene = mirad.load_scene(path)
    prob = Problem(scene, mirad.make_settings(clustering="on", core="legacy"))
    geo = prob.geometry()
    rng = np.random.default_rng(1)
    p = len(prob.patch_normal)
    recv = rng.integers(0, p, links).astype(np.int32)
    src = rng.integers(0, p, links).astype(np.int32)
    keep = prob.facing_pairs(recv, src) & (recv != src)
    recv, src = recv[keep], src[keep]
    kw = dict(samples=16, seed=3, clusters=prob.clusters)

    def timed(fn):
        fn()                                           # warm-up: JIT, scene load on workers, caches
        best = np.inf
        for _ in range(2):
            t = time.perf_counter()
            wave = fn()
            best = min(best, time.perf_counter() - t)
        return wave, best

    local, t_local = timed(lambda: evaluate_links(scene.mi_scene, geo, recv, src, **kw))
    t0 = time.perf_counter()
    with DaskEvaluator(scene, workers=workers) as ev:
        t_start = time.perf_counter() - t0
        remote, t_remote = timed(lambda: ev.evaluate_links(None, geo, recv, src, **kw))
        batches = ev.batches // 3
    same = all(np.array_equal(getattr(local, f), getattr(remote, f)) for f in LinkWave.FIELDS)
    return {"name": path.parent.name, "links": int(len(recv)), "rays": int(local.rays), "workers": workers,
            "batches": int(batches), "in_process_s": t_local, "dask_s": t_remote, "cluster_start_s": t_start,
            "in_process_mrays": local.rays / t_local / 1e6, "dask_mrays": remote.rays / t_remote / 1e6,
            "ratio": t_local / t_remote, "bitwise_equal": bool(same and local.rays == remote.rays)}


# ------------------------------------------------------------------------------------------
# Report
# ------------------------------------------------------------------------------------------

def _mb(x) -> str:
    return f"{x / 2**20:,.0f}"


def _row(r) -> str:
    s = r["seconds"]
    return (f"| {r['name']} | {r['triangles']:,} | {r['patches']:,} | {r['elements']:,} | {r['links']:,} | "
            f"{r['rays']:,} | {100 * r['estimated_error']:.2f} % | {r['refine_passes']} | "
            f"{r['wall']:.1f} ({s.get('refine', 0):.1f} / {s.get('visibility', 0):.1f} / {s.get('solve', 0):.1f} / "
            f"{s.get('direct', 0):.1f}) | {r['memory_bytes']['links'] / max(r['links'], 1):.0f} | "
            f"{r['memory_bytes']['elements'] / max(r['elements'], 1):.0f} | {_mb(r['peak_rss'])} |")


def markdown(sweep, onoff, dask, tolerance, extra=(), dask_full=None) -> str:
    from mirad.validate import machine

    import drjit
    import mitsuba

    lines = [f"## bench_scale: procedural canopies 1k-100k leaf triangles, "
             f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC", "",
             f"- machine: {machine()}; mitsuba {mitsuba.__version__}, drjit {drjit.__version__}; llvm_ad_rgb",
             "- seconds are indicative (other work may share the cores), counts and bytes are exact",
             "- scenes: `scenes/canopy-scale/make.py` (two-sided diamond leaves in ellipsoid crowns on a grid of "
             "plants, ground grid, directional sun + constant sky; seed 0), generated by the benchmark", ""]
    if sweep:
        core = sweep[0].get("core", "hierarchical")
        lines += [f"### Scale sweep (tolerance {tolerance}, {core} core, clustering auto = on, default settings)", "",
                  "| scene | triangles | patches | elements | links | rays | est. error | passes | seconds "
                  "(refine / visibility / solve / direct) | B/link | B/element | peak RSS MB |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|"]
        for r in sweep:
            lines.append(_row(r))
        if len(sweep) >= 2:
            tri = [r["triangles"] for r in sweep]
            lines += ["", f"- log-log slope of links against elements: **{slope([r['elements'] for r in sweep], [r['links'] for r in sweep]):.3f}**"
                      f" (target <= 1.2); links against input triangles: {slope(tri, [r['links'] for r in sweep]):.3f}; "
                      f"seconds against input triangles: {slope(tri, [r['wall'] for r in sweep]):.3f}"]
        lines += ["- B/link and B/element: `stats[\"memory_bytes\"]` (numpy arrays of links and elements) over "
                  "their counts (targets <= 100 and <= 200); peak RSS: the whole solve process (Python, "
                  "Mitsuba, LLVM JIT, scene) from `resource.getrusage`", ""]
    if extra:
        lines += ["### Further solves (tighter tolerance)", "",
                  "| scene | tolerance | triangles | patches | elements | links | rays | est. error | passes | seconds "
                  "(refine / visibility / solve / direct) | B/link | B/element | peak RSS MB |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|"]
        lines += [_row(r).replace(f"| {r['name']} |", f"| {r['name']} | {r['tolerance']} |", 1) for r in extra]
        lines.append("")
    if onoff:
        lines += [f"### Clustering on vs off, {onoff['name']} at tolerance {onoff['tolerance']}", "",
                  f"Reference: Mitsuba `path`, {REFERENCE_SAMPLES} paths per triangle "
                  f"({onoff['reference_paths']:,} paths, {onoff['reference_seconds']:.1f} s). Error: area-weighted "
                  "relative L1 / RMS of per-triangle radiosity against it.", "",
                  "| clustering | seconds | elements | links | rays | est. error | L1 error | RMS error | "
                  "reference noise (L1) | peak RSS MB |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for mode in [k for k in onoff if isinstance(onoff[k], dict)]:
            r = onoff[mode]
            e = r["error"]
            lines.append(f"| {mode} | {r['wall']:.2f} | {r['elements']:,} | {r['links']:,} | {r['rays']:,} | "
                         f"{100 * r['estimated_error_of_mean']:.2f} % | {100 * e['l1']:.2f} % | {100 * e['rms']:.2f} % | "
                         f"{100 * e['noise_l1']:.2f} % | {_mb(r['peak_rss'])} |")
        lines += ["", "(est. error here is `estimated_error_of_mean`, the estimate in the L1 metric's norm; rows "
                  "without a sample count use the default 16 samples per link.)", ""]
    if dask_full:
        a, b = dask_full["in_process"], dask_full["dask"]
        lines += [f"### Dask: a whole solve of {dask_full['name']} at tolerance {dask_full['tolerance']}", "",
                  "| run | seconds | visibility s | links | rays | est. error | peak RSS MB (client) |",
                  "|---|---:|---:|---:|---:|---:|---:|",
                  *(f"| {name} | {r['wall']:.1f} | {r['seconds'].get('visibility', 0):.1f} | {r['links']:,} | "
                    f"{r['rays']:,} | {100 * r['estimated_error']:.2f} % | {_mb(r['peak_rss'])} |"
                    for name, r in (("in-process", a), (f"Dask, {dask_full['workers']} workers", b))),
                  "", f"- per-triangle radiosity, links, rays and estimate bitwise identical: "
                  f"{'yes' if dask_full['identical'] else 'NO'} (sha256 of the radiosity array: {a['radiosity_digest']} "
                  f"/ {b['radiosity_digest']}); the Dask time includes starting the LocalCluster", ""]
    if dask:
        lines += [f"### Dask: one visibility wave on {dask['name']}", "",
                  f"{dask['links']:,} links x 16 rays ({dask['rays']:,} rays traced), {dask['batches']} batches on a "
                  f"LocalCluster of {dask['workers']} worker processes (1 Dr.Jit thread each) against the same wave "
                  "in-process (Dr.Jit on both cores); second call of each (warm).", "",
                  "| run | seconds | Mrays/s |", "|---|---:|---:|",
                  f"| in-process | {dask['in_process_s']:.2f} | {dask['in_process_mrays']:.2f} |",
                  f"| Dask, {dask['workers']} workers | {dask['dask_s']:.2f} | {dask['dask_mrays']:.2f} |", "",
                  f"- throughput ratio Dask / in-process: **{dask['ratio']:.2f}** on the same cores; cluster start "
                  f"{dask['cluster_start_s']:.1f} s (once per solve); per-link results bitwise equal: "
                  f"{'yes' if dask['bitwise_equal'] else 'NO'}", ""]
    return "\n".join(lines) + "\n"


def record(section: str) -> None:
    from mirad.solution import atomic_write

    text = RESULTS.read_text() if RESULTS.exists() else "# Validation results\n"
    text = text.rstrip("\n") + "\n\n" + section
    atomic_write(RESULTS, lambda handle: handle.write(text.encode()))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="1000,10000,100000", help="leaf triangle counts (comma-separated)")
    ap.add_argument("--tolerance", type=float, default=0.02, help="solve tolerance of the sweep (default 0.02)")
    ap.add_argument("--compare-size", type=int, default=1000, help="canopy of the clustering on/off comparison")
    ap.add_argument("--compare-tolerance", type=float, default=0.02)
    ap.add_argument("--dask-size", type=int, default=10000)
    ap.add_argument("--skip-sweep", action="store_true")
    ap.add_argument("--skip-compare", action="store_true")
    ap.add_argument("--skip-dask", action="store_true")
    ap.add_argument("--extra", default="", help="further solves SIZE:TOLERANCE[,...] (e.g. 100000:0.01)")
    ap.add_argument("--dask-solve", default="", help="SIZE:TOLERANCE: a whole solve in-process and on 2 "
                    "Dask workers, compared bitwise (e.g. 100000:0.02)")
    ap.add_argument("--core", default="hierarchical", choices=("legacy", "hierarchical"), help="the sweep's solver core")
    ap.add_argument("--json", default=None, help="also write every figure as JSON here")
    ap.add_argument("--record", action="store_true", help="append the results to validation/RESULTS.md")
    args = ap.parse_args(argv)
    sizes = [int(x) for x in args.sizes.split(",") if x.strip()]
    sweep = [] if args.skip_sweep else scale_sweep(sizes, args.tolerance, args.core)
    extra = [scale_sweep([int(x.split(":")[0])], float(x.split(":")[1]), args.core)[0]
             for x in args.extra.split(",") if x.strip()]
    onoff = None if args.skip_compare else clustering_on_off(args.compare_size, args.compare_tolerance)
    dask = None
    if not args.skip_dask:
        dask = dask_wave(args.dask_size)
        print(json.dumps(dask), flush=True)
    dask_full = None
    if args.dask_solve:
        size, tol = args.dask_solve.split(":")
        dask_full = dask_solve(int(size), float(tol))
    if args.json:
        Path(args.json).write_text(json.dumps({"sweep": sweep, "extra": extra, "onoff": onoff, "dask": dask,
                                                "dask_solve": dask_full}, indent=1, default=str))
    section = markdown(sweep, onoff, dask, args.tolerance, extra, dask_full)
    print(section)
    if args.record:
        record(section)
        print(f"appended to {RESULTS}")
    return 0


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        result = child(sys.argv[2], json.loads(sys.argv[3]), sys.argv[4] or None)
        print(json.dumps(result, default=float))
        sys.exit(0)
    sys.exit(main())
