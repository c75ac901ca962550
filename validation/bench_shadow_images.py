"""Shadow textures against pure subdivision at image level (issue 10): elements, links, seconds, image error.

For each scene of scenes/shadow-cases (``leaves``: 400 small leaves over a ground; ``table``: a
table on thin legs), mirad is solved at a sweep of tolerances, coarse to fine, twice: pure
subdivision (``shadow_textures=False``) and with convolution shadow textures
(``shadow_textures=True``: coarse receivers, some links carry a shadow texture). Each solution is
rendered from the scene's sensor with ``mirad.render`` (smooth display, texture detail included
where the display shows it) and compared with a Mitsuba path-traced image of the same sensor
(``mirad.reference.cached_image``, cached in .mirad-cache/):

- image error, over the fully covered pixels (coverage >= 1, the mask of ``mirad.validate``):
  relative MSE (``mirad.metrics.image_relative_mse``) and relative L1 = sum |I - R| / sum R;
  next to each, the reference's own noise floor (``image_noise_floor``; sqrt(2/pi) sum sigma /
  sum R for L1), which should lie well below the errors measured;
- cost: leaves (elements), links, texture links, leaves with texture detail, shadow rays, solve
  seconds (wall clock of ``mirad.solve``, after a JIT warm-up), render seconds (separately), and
  the solver's estimated error.

Equal error: for each texture run and each image metric (relative L1 and relative MSE), the first
subdivision run in sweep order (coarse to fine, so the cheapest) whose error is at most the texture
run's, and the ratios subdivision /
textures of its elements and solve seconds (> 1: textures are cheaper); also the subdivision
seconds interpolated in log-log at exactly that error (``mirad.validate.time_at_error``). Texture
runs that made no texture link are the subdivision solution itself: tabled, marked, and left out
of the reading.

A method's sweep stops before a solve predicted (4x the last) to exceed ``--max-seconds``; the
report says where it stopped, and when a solve overran the cap all the same.

A figure ``shadow-images-<scene>.png`` shows the reference, subdivision and textures side by side
at the nearest image error (the texture run of lowest relative MSE and the subdivision run closest
to it), all tonemapped with one exposure (``display.srgb8``, the reference's 99th luminance
percentile mapped to white).

Usage (from the repository root)::

    python validation/bench_shadow_images.py [--scenes leaves,table] [--tolerances 0.1,0.05]
        [--spp 16] [--ref-spp 8192] [--max-seconds 90] [--out validation] [--record]
    python validation/bench_shadow_images.py --quick        # smoke test, figures in a temp folder

``--record`` appends the tables to validation/RESULTS.md. Timings are wall clock on this machine;
on a shared CPU they are indicative.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import io
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import mirad  # noqa: E402
import mitsuba as mi  # noqa: E402
from mirad.display import srgb8  # noqa: E402
from mirad.metrics import SQRT_2_OVER_PI, image_noise_floor, image_relative_mse  # noqa: E402
from mirad.reference import cached_image  # noqa: E402
from mirad.solution import atomic_write  # noqa: E402
from mirad.validate import machine, time_at_error  # noqa: E402

HERE = REPO / "validation"
RESULTS = HERE / "RESULTS.md"
CACHE = REPO / ".mirad-cache"
#: Tolerance sweeps (coarse to fine). The table's per-triangle error is small where its image
#: error is large (a coarse floor smooths the umbra), so its sweep goes further down.
TOLERANCES = {"leaves": (0.2, 0.1, 0.05, 0.03, 0.02, 0.01),
              "table": (0.05, 0.02, 0.01, 0.005, 0.003, 0.002, 0.0015, 0.001)}
METHODS = (("subdivision", False), ("textures", True))
#: Image errors compared at equal error. Relative MSE is per-pixel relative, so near-black pixels
#: (the umbra under the table, lit only by interreflection) weigh most; relative L1 weighs every
#: pixel by its radiance, where shadow edges on lit ground count. Both are tabled.
METRICS = {"l1": "rel. L1", "relmse": "rel. MSE"}
FULL = {"spp": 16, "ref_spp": 8192, "max_seconds": 90.0}
QUICK = {"tolerances": 2, "spp": 4, "ref_spp": 256, "max_seconds": 30.0}


# ------------------------------------------------------------------------------------------
# Measurements
# ------------------------------------------------------------------------------------------

def image_errors(image, ref, mask) -> dict:
    """Relative MSE and relative L1 of an image against the reference over the masked pixels."""
    diff = np.abs(np.asarray(image, np.float64)[mask] - ref.image[mask])
    return {"relmse": image_relative_mse(image, ref.image, mask=mask), "l1": float(diff.sum() / ref.image[mask].sum())}


def reference(scene, spp: int, seed: int):
    """Cached path-traced image, its mask (fully covered pixels) and noise floors."""
    ref = cached_image(scene, cache_dir=CACHE, spp=spp, seed=seed)
    mask = ref.coverage >= 1.0
    floor = {"relmse": image_noise_floor(ref.stderr, ref.image, mask=mask),
             "l1": float(SQRT_2_OVER_PI * ref.stderr[mask].sum() / ref.image[mask].sum())}
    return ref, mask, floor


def run(scene, ref, mask, tol: float, textures: bool, *, spp: int, seed: int) -> tuple[dict, np.ndarray]:
    """One solve + render; returns (row, image)."""
    t = time.perf_counter()
    sol = mirad.solve(scene, tolerance=tol, shadow_textures=textures, quiet=True, seed=seed,
                      core="legacy")
    seconds = time.perf_counter() - t
    t = time.perf_counter()
    image = np.asarray(mirad.render(scene, sol, spp=spp, smooth=True), np.float64)
    render_seconds = time.perf_counter() - t
    st = sol.stats
    row = {"tolerance": tol, "textures": textures, "elements": int(st["leaves"]), "links": int(st["links"]),
           "texture_links": int(st.get("texture_links", 0)), "detail_leaves": len(sol.detail_leaves),
           "rays": int(st.get("rays", 0)), "seconds": seconds, "render_seconds": render_seconds,
           "estimated": float(st.get("estimated_error", math.nan)), **image_errors(image, ref, mask)}
    return row, image


def sweep(scene, ref, mask, tolerances, textures: bool, *, spp: int, seed: int, max_seconds: float, say):
    """Rows and images of one method, coarse to fine; stops early (see the module docstring)."""
    rows, images, note, extra = [], [], None, []
    for tol in tolerances:
        if rows and 4 * rows[-1]["seconds"] > max_seconds:
            note = (f"{'textures' if textures else 'subdivision'} stopped before tolerance {tol:g}: the solve at "
                    f"{rows[-1]['tolerance']:g} took {rows[-1]['seconds']:.2f} s (cap {max_seconds:g} s, "
                    "next one predicted at 4x)")
            say(note)
            break
        row, image = run(scene, ref, mask, tol, textures, spp=spp, seed=seed)
        rows.append(row)
        images.append(image)
        if row["seconds"] > max_seconds:
            extra.append(f"{'textures' if textures else 'subdivision'} at {tol:g} took {row['seconds']:.1f} s, over "
                         f"the {max_seconds:g} s cap (4x the previous solve predicted less)")
            say(extra[-1])
        say(f"  {'textures' if textures else 'subdivision':11s} tol {tol:<6g} {row['elements']:>7,} elements "
            f"{row['links']:>10,} links {row['texture_links']:>6,} textured  {row['seconds']:7.2f} s  "
            f"rel. MSE {row['relmse']:.4g}  rel. L1 {row['l1']:.4g}")
    return rows, images, extra + ([note] if note else [])


def equal_error(sub: list, tex: list, metric: str) -> list[dict]:
    """Per texture run: the first (cheapest) subdivision run with ``metric`` at most its own."""
    out = []
    for t in tex:
        match = next((s for s in sub if s[metric] <= t[metric]), None)
        interp, how = time_at_error([s["seconds"] for s in sub], [s[metric] for s in sub], t[metric])
        out.append({"tex": t, "sub": match, "interp": interp, "how": how, "metric": metric})
    return out


def measure(name: str, args, say) -> dict:
    scene = mirad.load_scene(REPO / "scenes" / "shadow-cases" / f"{name}.xml")
    tolerances = args.tolerances or TOLERANCES[name][: QUICK["tolerances"] if args.quick else None]
    t = time.perf_counter()
    ref, mask, floor = reference(scene, args.ref_spp, args.ref_seed)
    say(f"{name}: {scene.triangle_count} triangles; reference {args.ref_spp} spp "
        f"({ref.seconds:.1f} s{', cached' if ref.from_cache else ''}, {time.perf_counter() - t:.1f} s here); "
        f"noise floor rel. MSE {floor['relmse']:.2g}, rel. L1 {floor['l1']:.2g}; {mask.mean():.0%} of pixels covered")
    # JIT warm-up: compile the solver, texture and display kernels outside the timings
    for textures in (False, True):
        warm = mirad.solve(scene, tolerance=tolerances[min(1, len(tolerances) - 1)], shadow_textures=textures, core="legacy",
                           quiet=True, seed=args.seed)
        mirad.render(scene, warm, spp=1)
    result = {"name": name, "triangles": scene.triangle_count, "ref": ref, "mask": mask, "floor": floor,
              "notes": [], "rows": {}, "images": {}}
    for method, textures in METHODS:
        rows, images, notes = sweep(scene, ref, mask, tolerances, textures, spp=args.spp, seed=args.seed,
                                   max_seconds=args.max_seconds, say=say)
        result["rows"][method], result["images"][method] = rows, images
        result["notes"] += notes
    errors = [r["relmse"] for rows in result["rows"].values() for r in rows]
    if errors and floor["relmse"] > 0.1 * min(errors):
        result["notes"].append(f"the reference noise floor (rel. MSE {floor['relmse']:.2g}) is over a tenth of the "
                               f"smallest error measured ({min(errors):.2g}); raise --ref-spp")
    result["equal"] = {m: equal_error(result["rows"]["subdivision"], result["rows"]["textures"], m) for m in METRICS}
    return result


# ------------------------------------------------------------------------------------------
# Figure and tables
# ------------------------------------------------------------------------------------------

def figure(result) -> bytes | None:
    """Reference | subdivision | textures: the texture run (with texture links) of lowest relative MSE
    and the subdivision run nearest to it in relative MSE (log scale)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sub, tex = result["rows"]["subdivision"], result["rows"]["textures"]
    if not sub or not tex:
        return None
    textured = [i for i, t in enumerate(tex) if t["texture_links"]] or list(range(len(tex)))
    k = min(textured, key=lambda i: tex[i]["relmse"])
    j = int(np.argmin([abs(np.log(s["relmse"] / tex[k]["relmse"])) for s in sub]))
    ref, mask = result["ref"], result["mask"]
    lum = ref.image.mean(axis=2)
    exposure = -math.log2(max(float(np.percentile(lum[mask], 99)), 1e-300)) if mask.any() else 0.0
    panels = [(ref.image, f"Mitsuba path tracer, {ref.spp} spp"),
              (result["images"]["subdivision"][j], "subdivision", sub[j]),
              (result["images"]["textures"][k], "shadow textures", tex[k])]
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    for ax, (image, title, *row) in zip(axes, panels):
        ax.imshow(srgb8(image, exposure=exposure))
        if row:
            r = row[0]
            title = (f"{title}, tol {r['tolerance']:g}\n{r['elements']:,} elements, {r['seconds']:.1f} s, "
                     f"rel. MSE {r['relmse']:.3g}")
        ax.set_title(title, fontsize=9)
        ax.set_axis_off()
    fig.suptitle(f"{result['name']}: subdivision and shadow textures at the nearest image error", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.94))
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return buf.getvalue()


def _ratio(a, b) -> str:
    return f"{a / b:.2f}x" if b else "–"


def markdown(result) -> str:
    f, ref = result["floor"], result["ref"]
    lines = [f"### {result['name']} ({result['triangles']} triangles)", "",
             f"Reference: {ref.spp} spp ({ref.seconds:.1f} s), noise floor rel. MSE {f['relmse']:.2g}, "
             f"rel. L1 {f['l1']:.2g}; errors over the {result['mask'].mean():.0%} fully covered pixels.", "",
             "| method | tolerance | elements | links | texture links | detail leaves | rays | solve s | render s | "
             "estimated | rel. MSE | rel. L1 |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for method, _ in METHODS:
        for r in result["rows"][method]:
            lines.append(f"| {method} | {r['tolerance']:g} | {r['elements']:,} | {r['links']:,} | "
                         f"{r['texture_links']:,} | {r['detail_leaves']:,} | {r['rays']:,} | {r['seconds']:.2f} | "
                         f"{r['render_seconds']:.2f} | {r['estimated']:.3g} | {r['relmse']:.4g} | {r['l1']:.4g} |")
    for metric, label in METRICS.items():
        lines += ["", f"Equal image error in {label} (first subdivision run, coarse to fine, with {label} at most "
                  "the texture run's; ratios subdivision / textures, > 1 means textures are cheaper):", "",
                  f"| textures tol | elements | solve s | {label} | subdivision tol | elements | solve s | {label} | "
                  "elements ratio | seconds ratio | subdivision s interpolated |",
                  "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for e in result["equal"][metric]:
            t, s = e["tex"], e["sub"]
            tol = f"{t['tolerance']:g}" + ("" if t["texture_links"] else " (no texture link)")
            interp = f"{e['interp']:.2f} ({e['how']})" if e["interp"] is not None else e["how"]
            if s is None:
                lines.append(f"| {tol} | {t['elements']:,} | {t['seconds']:.2f} | {t[metric]:.4g} | "
                             f"none reached | – | – | – | – | – | {interp} |")
            else:
                lines.append(f"| {tol} | {t['elements']:,} | {t['seconds']:.2f} | {t[metric]:.4g} | "
                             f"{s['tolerance']:g} | {s['elements']:,} | {s['seconds']:.2f} | {s[metric]:.4g} | "
                             f"{_ratio(s['elements'], t['elements'])} | {_ratio(s['seconds'], t['seconds'])} | {interp} |")
    lines.append("")
    lines += [f"- note: {n}" for n in result["notes"]]
    return "\n".join(lines).rstrip() + "\n"


def reading(result) -> str:
    return "\n".join(_reading(result, metric, label) for metric, label in METRICS.items())


def _reading(result, metric: str, label: str) -> str:
    """A plain summary derived from the equal-error rows (no judgement is hard-coded).

    Texture runs without a single texture link are the subdivision solution itself; they are
    left out of the verdict (and said so)."""
    name, tex = result["name"], result["rows"]["textures"]
    real = [e for e in result["equal"][metric] if e["tex"]["texture_links"]]
    skipped = len(result["equal"][metric]) - len(real)
    head = f"- {name}, equal {label}:" + (f" {skipped} texture run(s) made no texture link (left out);" if skipped else "")
    if not tex or not real:
        return f"{head} no texture run with texture links finished; nothing to compare."
    pairs = [e for e in real if e["sub"] is not None]
    if len(pairs) < len(real):
        best = min(result["rows"]["subdivision"], key=lambda r: r[metric], default=None)
        head += (f" subdivision did not reach the image error of {len(real) - len(pairs)} of {len(real)} texture "
                 f"run(s) with texture links" + (f" (its best {label} {best[metric]:.3g});" if best else ";"))
    if not pairs:
        return f"{head} no equal-error ratio."
    fewer = sum(e["sub"]["elements"] > e["tex"]["elements"] for e in pairs)
    faster = sum(e["sub"]["seconds"] > e["tex"]["seconds"] for e in pairs)
    el = [e["sub"]["elements"] / e["tex"]["elements"] for e in pairs]
    sec = [e["sub"]["seconds"] / e["tex"]["seconds"] for e in pairs]
    verdict = ("textures win on elements and time" if fewer == faster == len(pairs) else
               "textures win on elements but NOT on time" if fewer == len(pairs) else
               "textures win on time but NOT on elements" if faster == len(pairs) else
               "textures do NOT win consistently")
    return (f"{head} at {len(pairs)} equal-error point(s) textures used fewer elements at {fewer} and less solve "
            f"time at {faster}; subdivision / textures: elements {min(el):.2f}-{max(el):.2f}x, seconds "
            f"{min(sec):.2f}-{max(sec):.2f}x: {verdict}.")


# ------------------------------------------------------------------------------------------

def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="leaves,table", help="comma-separated: leaves, table")
    ap.add_argument("--tolerances", default=None,
                    help="comma-separated, coarse to fine, for every scene (default per scene: "
                         + "; ".join(f"{k} {','.join(map(str, v))}" for k, v in TOLERANCES.items()) + ")")
    ap.add_argument("--spp", type=int, help=f"samples per pixel of mirad's render (default {FULL['spp']})")
    ap.add_argument("--ref-spp", type=int,
                    help=f"samples per pixel of the path-traced reference (default {FULL['ref_spp']})")
    ap.add_argument("--ref-seed", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0, help="mirad's seed (solve and render)")
    ap.add_argument("--max-seconds", type=float,
                    help=f"solve-time cap per run, see the docstring (default {FULL['max_seconds']:g})")
    ap.add_argument("--out", default=None, help="folder of the figures (default validation/; --quick: a temp folder)")
    ap.add_argument("--quick", action="store_true", help="smoke test: 2 tolerances, %d spp, reference %d spp, cap %g s"
                    % (QUICK["spp"], QUICK["ref_spp"], QUICK["max_seconds"]))
    ap.add_argument("--record", action="store_true", help="append the tables to validation/RESULTS.md")
    args = ap.parse_args(argv)
    if args.quick and args.record:
        ap.error("--quick is a smoke test; it does not --record")
    for key, value in (QUICK if args.quick else FULL).items():
        if getattr(args, key, None) is None:
            setattr(args, key, value)
    args.tolerances = tuple(float(x) for x in args.tolerances.split(",")) if args.tolerances else None
    out = Path(args.out) if args.out else (Path(tempfile.gettempdir()) / "mirad-shadow-images" if args.quick else HERE)
    out.mkdir(parents=True, exist_ok=True)
    say = lambda *a: print(*a, flush=True)  # noqa: E731
    start = time.perf_counter()
    results = []
    for name in args.scenes.split(","):
        result = measure(name.strip(), args, say)
        png = figure(result)
        if png is not None:
            path = out / f"shadow-images-{result['name']}.png"
            atomic_write(path, lambda fh, data=png: fh.write(data))
            result["notes"].append(f"figure: {path.relative_to(REPO) if path.is_relative_to(REPO) else path}")
        results.append(result)
    command = "python validation/bench_shadow_images.py " + " ".join(argv if argv is not None else sys.argv[1:])
    text = "\n".join(
        [f"## Shadow textures at image level (issue 10), {_dt.datetime.now().strftime('%Y-%m-%d %H:%M')}", "",
         f"`{command.strip()}`; {machine()}, variant {mi.variant()}; render {args.spp} spp (smooth), solve seed "
         f"{args.seed}; {time.perf_counter() - start:.0f} s in all. Image errors against the Mitsuba path-traced "
         "image of the scene's sensor over fully covered pixels: relative MSE (metrics.image_relative_mse) and "
         "relative L1 sum |I - R| / sum R. Solve seconds are wall clock after a JIT warm-up; render seconds apart.",
         ""] + [markdown(r) for r in results] + ["Reading:", ""] + [reading(r) for r in results] + [""])
    print("\n" + text)
    if args.record:
        old = RESULTS.read_text() if RESULTS.exists() else ""
        atomic_write(RESULTS, lambda fh: fh.write((old.rstrip("\n") + "\n\n" + text).encode()))
        print(f"appended to {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
