"""Command line: ``mirad solve | info | validate | render | export | probe``. Parses arguments and calls the Python API only."""

from __future__ import annotations

import argparse
import json
import os
import sys


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mirad", description="Hierarchical radiosity for Mitsuba 3 scenes.")
    sub = parser.add_subparsers(dest="command", required=True)

    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("scene", help="Mitsuba scene XML file")
    common.add_argument("--variant", default=None, help="Mitsuba variant (default: cuda_ad_rgb with a GPU, else llvm_ad_rgb)")
    common.add_argument("--quiet", action="store_true", help="no progress bars")

    solve = sub.add_parser("solve", parents=[common], help="solve the radiosity and write it out")
    solve.add_argument("-o", "--output", required=True, help="output file: .ply (vertex colours) or .npz (full solution)")
    solve.add_argument("--tolerance", type=float, default=0.03, help="target relative error (default 0.03)")
    solve.add_argument("--samples-per-link", type=int, default=16, help="shadow rays per link (default 16)")
    solve.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    solve.add_argument("--solver", choices=["gmres", "gauss-seidel", "jacobi"], default=None,
                       help="linear solver (default gmres)")
    solve.add_argument("--oracle", choices=["kernel", "bf", "bound"], default=None,
                       help="refinement oracle (default kernel; bound: conservative, estimate is a bound)")
    solve.add_argument("--shadow-textures", action="store_true",
                       help="let partly visible links from lights carry a convolution shadow texture "
                            "instead of splitting their receiver")
    solve.add_argument("--stats", default=None, help="also write the solve statistics as JSON here")
    solve.add_argument("--workers", type=int, default=None,
                       help="run the visibility waves on a local Dask cluster of N worker processes")
    solve.add_argument("--scheduler", default=None, metavar="ADDR",
                       help="run the visibility waves on the Dask scheduler at ADDR (e.g. tcp://host:8786)")

    sub.add_parser("info", parents=[common], help="what the scene needs and what mirad switches on")
    _add_output_commands(sub, common)

    val = sub.add_parser("validate", parents=[common],
                         help="error against Mitsuba path tracing: speed-vs-error table, plot and images")
    val.add_argument("-o", "--output", default="validation-out",
                     help="folder for NAME.md, NAME-speed-error.png, NAME-images.png (default validation-out)")
    val.add_argument("--tolerances", default="0.2,0.1,0.05,0.03,0.02,0.01",
                     help="comma-separated mirad tolerances (default 0.2,0.1,0.05,0.03,0.02,0.01)")
    val.add_argument("--pt-samples", default="16,64,256,1024,4096",
                     help="comma-separated path-tracer samples per triangle (default 16,64,256,1024,4096)")
    val.add_argument("--reference-samples", type=int, default=16384,
                     help="reference samples per triangle (default 16384)")
    val.add_argument("--image-spp", type=int, default=64, help="path-traced image samples per pixel (default 64)")
    val.add_argument("--no-images", action="store_true", help="skip the image comparison")
    val.add_argument("--max-seconds", type=float, default=None, help="time budget of each sweep, seconds")
    val.add_argument("--name", default=None, help="file stem of the outputs (default: the scene's folder name)")
    val.add_argument("--cache", default=".mirad-cache", help="reference cache folder (default .mirad-cache)")
    val.add_argument("--no-cache", action="store_true", help="always recompute the reference")
    val.add_argument("--seed", type=int, default=0, help="mirad's random seed (default 0)")
    return parser


def _solve(args) -> int:
    import mirad
    from mirad.solution import atomic_write

    _check_output(args.output, (".ply", ".npz"))
    sol = mirad.solve(args.scene, tolerance=args.tolerance, samples_per_link=args.samples_per_link,
                      seed=args.seed, solver=args.solver, oracle=args.oracle, variant=args.variant,
                      shadow_textures=args.shadow_textures or None,
                      quiet=args.quiet, workers=args.workers, scheduler=args.scheduler)
    sol.save(args.output)
    if args.stats:
        text = json.dumps(sol.stats, indent=2, default=str).encode()
        atomic_write(args.stats, lambda handle: handle.write(text))
    if not args.quiet:
        print(sol.summary())
        print(f"wrote {args.output}")
    return 0


def _info(args) -> int:
    import mirad

    scene = mirad.load_scene(args.scene, variant=args.variant)
    features = scene.features
    print(f"scene {args.scene}: {features['shapes']} shapes, {features['triangles']} triangles, "
          f"fingerprint {scene.fingerprint}, variant {scene.variant}")
    for sid, kind in zip(scene.shape_ids, scene.shape_types):
        print(f"  shape {sid!r}: {kind}")
    print("switched on:")
    print(f"  channels solved: {features['channels']} ({'grey scene' if features['channels'] == 1 else 'RGB'})")
    print(f"  back-side elements: {features['back_side_patches']} (two-sided BSDFs)")
    print(f"  emitters: {features['emitters']}")
    print(f"  direct-light pass for point/spot/directional/environment lights: "
          f"{'on' if features['direct_light_pass'] else 'off'}")
    print(f"  curved surfaces projected for visibility: {features['curved_shapes']} triangles")
    from mirad.settings import Settings

    patches = len(scene.patch_tri)
    threshold = Settings().cluster_threshold
    print(f"  clusters of patches as link sources (clustering='auto'): "
          f"{'on' if patches > threshold else 'off'} ({patches} patches, threshold {threshold})")
    if features["non_diffuse_approximated"]:
        print(f"  non-diffuse BSDFs approximated by their albedo: {features['non_diffuse_approximated']}")
    if features["dropped_zero_area_triangles"]:
        print(f"  zero-area triangles dropped: {features['dropped_zero_area_triangles']}")
    return 0


def _numbers(text: str, option: str, kind) -> list:
    from mirad.errors import SettingsError

    try:
        return [kind(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise SettingsError(f"{option} {text!r}: give comma-separated numbers, e.g. 0.1,0.03") from None


def _validate(args) -> int:
    import mirad
    from mirad.validate import validate

    scene = mirad.load_scene(args.scene, variant=args.variant)
    validate(scene, tolerances=_numbers(args.tolerances, "--tolerances", float),
             pt_samples=_numbers(args.pt_samples, "--pt-samples", int),
             reference_samples=args.reference_samples, images=not args.no_images, image_spp=args.image_spp,
             output_dir=args.output, name=args.name, cache_dir=None if args.no_cache else args.cache,
             seed=args.seed, max_seconds=args.max_seconds, quiet=args.quiet)
    return 0


# --- render, export, probe -------------------------------------------------------------------

def _add_output_commands(sub, common) -> None:
    solved = argparse.ArgumentParser(add_help=False)
    solved.add_argument("--solution", default=None,
                        help="use this saved solution (.npz from 'mirad solve') instead of solving again")
    solved.add_argument("--tolerance", type=float, default=None, help="target relative error (default 0.03)")
    solved.add_argument("--samples-per-link", type=int, default=None, help="shadow rays per link (default 16)")
    solved.add_argument("--seed", type=int, default=None, help="random seed (default 0)")

    render = sub.add_parser("render", parents=[common, solved],
                            help="image of the solution from the scene's sensor (EXR + PNG)")
    render.add_argument("-o", "--output", required=True, help="image.exr (linear RGB float); a tonemapped "
                        "sRGB PNG is written beside it")
    render.add_argument("--spp", type=int, default=4, help="samples per pixel (default 4)")
    render.add_argument("--final-gather", action="store_true",
                        help="one bounce of gathering at each pixel (crisp contact shadows, slower)")
    render.add_argument("--flat", action="store_true", help="show flat elements instead of smooth shading")
    render.add_argument("--exposure", type=float, default=0.0, help="PNG exposure in stops (default 0)")
    render.add_argument("--no-png", action="store_true", help="write the EXR only")

    export = sub.add_parser("export", parents=[common, solved],
                            help="PLY mesh, per-triangle table, per-shape summary, lightmaps")
    export.add_argument("-o", "--output", action="append", default=[],
                        help="by suffix: .ply (mesh, vertex colours and float radiosity), .csv or .npz "
                             "(per-triangle table with absorbed power); may be repeated")
    export.add_argument("--shapes", default=None, help="per-shape summary .csv (mean radiosity, absorbed power)")
    export.add_argument("--lightmaps", default=None,
                        help="folder for one radiosity lightmap <shape id>.exr per shape with UVs")
    export.add_argument("--lightmap-res", type=int, default=256, help="lightmap size in texels (default 256)")
    export.add_argument("--error-maps", action="store_true",
                        help="with --lightmaps, also write <shape>.error.exr: the estimated error map (W/m^2)")

    probe = sub.add_parser("probe", parents=[common, solved], help="irradiance at sensor points")
    probe.add_argument("--points", required=True, help="CSV file with a header and columns x,y,z,nx,ny,nz")
    probe.add_argument("-o", "--output", required=True,
                       help="CSV out: x,y,z,nx,ny,nz and irradiance_r,g,b (W/m^2)")
    probe.add_argument("--rays", type=int, default=16, help="shadow rays per element and point (default 16)")


def _solution(args):
    """The scene and its solution: loaded from --solution (fingerprint checked) or solved now."""
    import mirad
    from mirad.errors import SettingsError, SolutionMismatch

    scene = mirad.load_scene(args.scene, variant=args.variant)
    if args.solution:
        given = [f"--{n.replace('_', '-')}" for n in ("tolerance", "samples_per_link", "seed")
                 if getattr(args, n) is not None]
        if given:
            raise SettingsError(f"{', '.join(given)} cannot be combined with --solution (the saved "
                                "solution is used as it is); drop one of them")
        if not os.path.exists(args.solution):
            raise SolutionMismatch(f"solution file '{args.solution}' does not exist; write one with "
                                   "'mirad solve SCENE -o sol.npz'")
        return scene, mirad.load_solution(args.solution, scene=scene)
    options = {n: getattr(args, n) for n in ("tolerance", "samples_per_link", "seed") if getattr(args, n) is not None}
    return scene, mirad.solve(scene, quiet=args.quiet, **options)


def _render(args) -> int:
    from mirad.display import check_spp, render, write_image

    _check_output(args.output, (".exr",))
    if not args.no_png:
        _check_output(os.path.splitext(args.output)[0] + ".png", (".png",))
    check_spp(args.spp)
    scene, sol = _solution(args)
    image = render(scene, sol, spp=args.spp, smooth=not args.flat, final_gather=args.final_gather,
                   seed=args.seed or 0)
    written = write_image(args.output, image, png=not args.no_png, exposure=args.exposure)
    if not args.quiet:
        print(f"wrote {', '.join(map(str, written))} ({image.shape[1]}x{image.shape[0]}, {args.spp} spp)")
    return 0


def _export(args) -> int:
    from mirad import export
    from mirad.errors import OutputError

    if not (args.output or args.shapes or args.lightmaps):
        raise OutputError("nothing to export; give -o FILE (.ply, .csv, .npz), --shapes FILE.csv or --lightmaps DIR")
    for path in args.output:
        _check_output(path, (".ply",) + export.TABLE_SUFFIXES)
    if args.shapes:
        _check_output(args.shapes, (".csv",))
    if args.lightmaps and not os.path.isdir(args.lightmaps):
        raise OutputError(f"lightmap folder '{args.lightmaps}' does not exist; create it first")
    if args.lightmap_res < 1:
        raise OutputError(f"--lightmap-res {args.lightmap_res} must be >= 1 (e.g. 256)")
    scene, sol = _solution(args)
    written = []
    for path in args.output:
        written.append(export.write_ply(sol, path) if path.lower().endswith(".ply") else export.write_table(sol, path))
    if args.shapes:
        written.append(export.write_shape_summary(sol, args.shapes))
    if args.lightmaps:
        written += export.write_lightmaps(sol, args.lightmaps, resolution=args.lightmap_res,
                                          error=args.error_maps)
    if not args.quiet:
        print(f"wrote {', '.join(map(str, written))}")
    return 0


def _probe(args) -> int:
    from mirad.errors import SettingsError
    from mirad.export import read_points, write_probe_table

    _check_output(args.output, (".csv",))
    if args.rays < 1:
        raise SettingsError(f"--rays {args.rays} must be >= 1")
    points, normals = read_points(args.points)
    scene, sol = _solution(args)
    irradiance = sol.irradiance_at(points, normals, rays=args.rays)
    write_probe_table(args.output, points, normals, irradiance)
    if not args.quiet:
        print(f"wrote {args.output} ({len(points)} points)")
    return 0


def _check_output(path: str, suffixes: tuple) -> None:
    from mirad.errors import OutputError

    if os.path.splitext(path)[1].lower() not in suffixes:
        raise OutputError(f"output '{path}' must end in one of {', '.join(suffixes)}")
    folder = os.path.dirname(path) or "."
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise OutputError(f"cannot write '{path}': '{folder}' is a file, not a folder; choose another output path")
    if os.path.isdir(path):
        raise OutputError(f"cannot write '{path}': it is a folder; give a file name such as {path.rstrip('/')}/out{suffixes[0]}")
    if not os.path.isdir(folder):
        raise OutputError(f"cannot write '{path}': folder '{folder}' does not exist; create it first")
    if not os.access(folder, os.W_OK):
        raise OutputError(f"cannot write '{path}': folder '{folder}' is not writable; choose another output path")


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings as one line each, 'mirad: warning: ...' (no source path or code line)."""
    print(f"mirad: warning: {message}", file=sys.stderr if file is None else file)


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    import warnings

    warnings.showwarning = _show_warning
    try:
        from mirad.errors import MiradError
    except Exception as exc:  # pragma: no cover - broken installation
        print(f"mirad: error: cannot import mirad ({exc})", file=sys.stderr)
        return 2
    try:
        return {"solve": _solve, "info": _info, "validate": _validate, "render": _render,
                "export": _export, "probe": _probe}[args.command](args)
    except MiradError as exc:
        print(f"mirad: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mirad: interrupted; no output was written", file=sys.stderr)
        return 130
    except Exception as exc:  # never a traceback for users; MIRAD_DEBUG=1 shows it
        if os.environ.get("MIRAD_DEBUG"):
            raise
        print(f"mirad: error: {type(exc).__name__}: {exc} (set MIRAD_DEBUG=1 for a traceback)", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
