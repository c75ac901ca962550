"""Command line: ``mirad solve | info | validate | render | export | probe | sky``. Parses arguments and calls the Python API only."""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys


#: Solver options the CLI takes elsewhere: --variant and --quiet are common to every command.
_COMMON = ("variant", "quiet")


def parser() -> argparse.ArgumentParser:
    """The ``mirad`` argument parser, every command's options built from ``mirad.options``."""
    from mirad import options as _options

    parser = argparse.ArgumentParser(prog="mirad", description="Hierarchical radiosity for Mitsuba 3 scenes.")
    sub = parser.add_subparsers(dest="command", required=True)

    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("scene", help="Mitsuba scene XML file")
    common.add_argument("--variant", default=None, help="Mitsuba variant (default: cuda_ad_rgb with a GPU, else llvm_ad_rgb)")
    common.add_argument("--quiet", action="store_true", help="no progress bars")

    solver = argparse.ArgumentParser(add_help=False)
    group = solver.add_argument_group("solver options (mirad.Settings; unset: the default shown)")
    _options.add_arguments(group, _options.SOLVE, skip=_COMMON)

    banded = argparse.ArgumentParser(add_help=False)
    banded.add_argument("--bands", default=None, metavar="TABLE.csv",
                        help="solve in the wavebands of this band table instead of RGB (CSV: band, id, "
                             "reflectance, transmittance, back_reflectance, scale; docs/bands.md); every "
                             "output gets one column per band, e.g. absorbed_PAR")

    solve = sub.add_parser("solve", parents=[common, banded, solver], help="solve the radiosity and write it out")
    solve.add_argument("-o", "--output", required=True, help="output file: .ply (vertex colours) or .npz (full solution)")
    solve.add_argument("--stats", default=None, help="also write the solve statistics as JSON here")

    sub.add_parser("info", parents=[common], help="what the scene needs and what mirad switches on")
    _add_output_commands(sub, common, solver, banded)

    val = sub.add_parser("validate", parents=[common],
                         help="error against Mitsuba path tracing: speed-vs-error table, plot and images")
    val.add_argument("-o", "--output", default="validation-out",
                     help="folder for NAME.md, NAME-speed-error.png, NAME-images.png (default validation-out)")
    val.add_argument("--tolerances", default=None,
                     help="comma-separated mirad tolerances (default: a cheap sweep, "
                          "mirad.validate.DEFAULT_TOLERANCES)")
    val.add_argument("--pt-samples", default=None,
                     help="comma-separated path-tracer samples per triangle (default mirad.validate.DEFAULT_PT_SAMPLES)")
    val.add_argument("--reference-samples", type=int, default=None,
                     help="reference samples per triangle on average, allocated by area "
                          "(default mirad.validate.DEFAULT_REFERENCE_SAMPLES)")
    val.add_argument("--image-spp", type=int, default=64, help="path-traced image samples per pixel (default 64)")
    val.add_argument("--no-images", action="store_true", help="skip the image comparison")
    val.add_argument("--max-seconds", type=float, default=None, help="time budget of each sweep, seconds")
    val.add_argument("--name", default=None, help="file stem of the outputs (default: the scene's folder name)")
    val.add_argument("--cache", default=None,
                     help="reference cache folder (default: the platform's cache folder, see mirad.reference; "
                          "or set MIRAD_CACHE)")
    val.add_argument("--no-cache", action="store_true", help="always recompute the reference")
    val.add_argument("--seed", type=int, default=0, help="mirad's random seed (default 0)")
    _add_sky_command(sub)
    return parser


def _solve(args) -> int:
    import mirad
    from mirad import options as _options
    from mirad.files import atomic_write, check_output

    check_output(args.output, (".ply", ".npz"))
    if args.stats:
        check_output(args.stats)
    scene = _load(args) if args.bands else args.scene
    sol = mirad.solve(scene, variant=args.variant, quiet=args.quiet,
                      **_options.given(args, _options.SOLVE, skip=_COMMON))
    sol.save(args.output)
    if args.stats:
        text = json.dumps(sol.stats, indent=2, default=str).encode()
        atomic_write(args.stats, lambda handle: handle.write(text))
    if not args.quiet:
        print(sol.summary())
        print(f"wrote {args.output}")
    return 0


def _info(args) -> int:
    import numpy as np

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
    defaults = Settings()
    print(f"  solver core (core={defaults.core!r}, the default): face clusters over each planar group and "
          f"volume clusters above them, always")
    print(f"  with core='legacy', clusters of patches as link sources (clustering='auto'): "
          f"{'on' if patches > defaults.cluster_threshold else 'off'} ({patches} patches, "
          f"threshold {defaults.cluster_threshold})")
    if features["non_diffuse_approximated"]:
        print(f"  non-diffuse BSDFs approximated by their albedo: {features['non_diffuse_approximated']}")
    if features["translucent_leaf_triangles"]:
        print(f"  translucent leaves (transmittance read per side, docs/leaves.md): "
              f"{features['translucent_leaf_triangles']} triangles")
    if scene.tri_leaf.any():
        # the tolerance is over every shape's area by default: where the leaves are a small part
        # of it, their own error can be several times the estimate (error_shapes)
        import os.path

        leafy = sorted({str(scene.shape_ids[k]) for k in np.unique(scene.tri_shape[scene.tri_leaf])})
        # (over both sides of two-sided triangles, as the estimate counts area)
        patch_area = scene.tri_area[scene.patch_tri]
        share = float(patch_area[scene.tri_leaf[scene.patch_tri]].sum() / patch_area.sum())
        prefix = os.path.commonprefix(leafy)
        covers = prefix and all(str(i) in leafy for i in scene.shape_ids if str(i).startswith(prefix))
        named = prefix + "*" if covers and len(leafy) > 1 else ",".join(leafy)
        print(f"  leaf shapes: {len(leafy)} ({share:.0%} of the area); to hold the tolerance on their light "
              f"alone: --error-shapes '{named}'")
    if features["dropped_zero_area_triangles"]:
        print(f"  zero-area triangles dropped: {features['dropped_zero_area_triangles']}")
    return 0


def _numbers(text, option: str, kind):
    from mirad.errors import SettingsError

    if text is None:
        return None
    try:
        return [kind(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise SettingsError(f"{option} {text!r}: give comma-separated numbers, e.g. 0.1,0.03") from None


def _validate(args) -> int:
    import mirad
    from mirad.reference import DEFAULT_CACHE
    from mirad.validate import validate

    scene = mirad.load_scene(args.scene, variant=args.variant)
    given = {k: v for k, v in (("tolerances", _numbers(args.tolerances, "--tolerances", float)),
                               ("pt_samples", _numbers(args.pt_samples, "--pt-samples", int)),
                               ("reference_samples", args.reference_samples)) if v is not None}
    validate(scene, images=not args.no_images, image_spp=args.image_spp, output_dir=args.output, name=args.name,
             cache_dir=None if args.no_cache else (args.cache or DEFAULT_CACHE), seed=args.seed, max_seconds=args.max_seconds,
             quiet=args.quiet, **given)
    return 0


# --- render, export, probe -------------------------------------------------------------------

def _load(args, scene=None):
    """The scene of the command (``scene`` if already loaded), in the bands of ``--bands`` if given
    (the table is read before the scene loads, so a malformed one fails at once)."""
    import mirad

    table = mirad.read_band_table(args.bands) if getattr(args, "bands", None) else None
    scene = scene if scene is not None else mirad.load_scene(args.scene, variant=args.variant)
    return mirad.with_bands(scene, table) if table is not None and not scene.band_names else scene


def _add_output_commands(sub, common, solver, banded) -> None:
    from mirad import options as _options
    from mirad.solution import PROBE_MAX_SAMPLES

    solved = argparse.ArgumentParser(add_help=False)
    solved.add_argument("--solution", default=None,
                        help="use this saved solution (.npz from 'mirad solve') instead of solving again")

    render = sub.add_parser("render", parents=[common, solved, solver],
                            help="image of the solution from the scene's sensor (EXR + PNG); the XML's "
                                 "<integrator type=\"radiosity\"> parameters apply unless given here")
    render.add_argument("-o", "--output", required=True, help="image.exr (linear RGB float); a tonemapped "
                        "sRGB PNG is written beside it")
    display = render.add_argument_group("display options")
    _options.add_arguments(display, _options.RENDER)
    render.add_argument("--flat", action="store_true", help="show flat elements (same as --no-smooth)")
    render.add_argument("--exposure", type=float, default=0.0, help="PNG exposure in stops (default 0)")
    render.add_argument("--no-png", action="store_true", help="write the EXR only")

    export = sub.add_parser("export", parents=[common, solved, banded, solver],
                            help="PLY mesh, per-triangle table, per-shape summary, lightmaps")
    export.add_argument("-o", "--output", action="append", default=[],
                        help="by suffix: .ply (mesh, vertex colours and float radiosity), .csv or .npz "
                             "(per-triangle table with absorbed power); may be repeated")
    export.add_argument("--ply-mesh", choices=("input", "refined"), default="input",
                        help="PLY of the input mesh (vertex values averaged) or of the refined solution "
                             "mesh (one flat colour per element) (default input)")
    export.add_argument("--ply-exposure", choices=("scene", "all"), default="scene",
                        help="PLY colours: the 99th percentile of the non-emitting surfaces maps to white "
                             "(scene) or of all surfaces, lights included (all) (default scene)")
    export.add_argument("--shapes", default=None, help="per-shape summary .csv (mean radiosity, absorbed power)")
    export.add_argument("--organs", default=None,
                        help="per-organ table, .csv or .npz: absorbed and incident power (W), area, mean "
                             "radiosity and irradiance, triangle count and centroid of each organ "
                             "(see --organs-by)")
    export.add_argument("--organs-by", default=None,
                        help="what an organ is: component (each connected piece of a shape's mesh, such as "
                             "a leaf; the default), group (face groups of the mesh files: a PLY face property "
                             "named by --groups-property, or OBJ g/o groups) or shape")
    export.add_argument("--groups-property", default=None,
                        help="with --organs-by group: the integer PLY face property that numbers the organs, "
                             "e.g. organ")
    export.add_argument("--lightmaps", default=None,
                        help="folder for one radiosity lightmap per shape with UVs and lightmaps.csv "
                             "naming the file of each shape id")
    export.add_argument("--lightmap-res", type=int, default=256, help="lightmap size in texels (default 256)")
    export.add_argument("--lightmap-supersample", type=int, default=None,
                        help="points per texel side (default: at least 2 and 256 across the map)")
    export.add_argument("--error-maps", action="store_true",
                        help="with --lightmaps, also write <shape>.error.exr: the estimated error map (W/m^2)")

    probe = sub.add_parser("probe", parents=[common, solved, banded, solver], help="irradiance at sensor points")
    probe.add_argument("--points", required=True, help="CSV file with a header and columns x,y,z,nx,ny,nz")
    probe.add_argument("-o", "--output", required=True,
                       help="CSV out: x,y,z,nx,ny,nz, irradiance_r,g,b and its standard error err_r,g,b (W/m^2)")
    probe.add_argument("--rays", type=int, default=16, help="shadow rays per element and point (default 16)")
    probe.add_argument("--probe-tolerance", type=float, default=None,
                       help="relative standard error per probe: direct light of point, spot, directional and "
                            f"environment emitters is sampled until each probe is within it (up to "
                            f"{PROBE_MAX_SAMPLES} samples; default: the solve's tolerance)")


def _xml_integrator(scene) -> dict:
    """Parameters of a ``<integrator type="radiosity">`` in the scene file, else {}."""
    from mirad.integrator import integrator_class

    integ = scene.mi_scene.integrator()
    if not isinstance(integ, integrator_class()):
        return {}
    from mirad import options as _options

    return {o.name: getattr(integ, o.name) for o in _options.PLUGIN}


def _solution(args, defaults=None, scene=None):
    """The scene and its solution: loaded from --solution (fingerprint checked) or solved now.

    ``defaults``: solver options that apply unless given on the command line (the XML's plugin)."""
    import mirad
    from mirad import options as _options
    from mirad.errors import SettingsError, SolutionMismatch

    scene = _load(args, scene)
    given = _options.given(args, _options.SOLVE, skip=_COMMON)
    if args.solution:
        if given:
            flags = ", ".join(o.flag for o in _options.SOLVE if o.name in given)
            raise SettingsError(f"{flags} cannot be combined with --solution (the saved "
                                "solution is used as it is); drop one of them")
        if not os.path.exists(args.solution):
            raise SolutionMismatch(f"solution file '{args.solution}' does not exist; write one with "
                                   "'mirad solve SCENE -o sol.npz'")
        saved = mirad.load_solution(args.solution)
        solved_in = saved.stats.get("bands")
        if solved_in and not scene.band_names:
            fix = ("give the band table it was solved with (--bands TABLE.csv)" if hasattr(args, "bands") else
                   "render shows RGB radiance; write its bands with 'mirad export --bands TABLE.csv' (tables, "
                   "lightmaps) instead")
            raise SolutionMismatch(f"solution '{args.solution}' was solved in bands {', '.join(solved_in)}; {fix}")
        if scene.band_names and not solved_in:
            raise SolutionMismatch(f"solution '{args.solution}' was solved in RGB, not in bands; drop --bands, or "
                                   "solve again with --bands")
        return scene, saved.attach(scene)
    options = {k: v for k, v in (defaults or {}).items() if k not in _COMMON}
    options.update(given)
    return scene, mirad.solve(scene, quiet=args.quiet, **options)


def _render(args) -> int:
    from mirad import options as _options
    from mirad.display import render, write_image
    from mirad.files import check_output

    check_output(args.output, (".exr",))
    if not args.no_png:
        check_output(os.path.splitext(args.output)[0] + ".png", (".png",))
    display = _options.given(args, _options.RENDER)
    _options.check_render(**display)
    if args.flat:
        display["smooth"] = False
    import mirad

    loaded = mirad.load_scene(args.scene, variant=args.variant)
    plugin = _xml_integrator(loaded)          # <integrator type="radiosity"> in the XML: its parameters
    shown = {o.name for o in _options.RENDER}
    display = {**{k: v for k, v in plugin.items() if k in shown}, **display}
    scene, sol = _solution(args, {k: v for k, v in plugin.items() if k not in shown}, scene=loaded)
    spp = display.pop("spp", _options.default("spp"))
    image = render(scene, sol, spp=spp, seed=args.seed if args.seed is not None else plugin.get("seed", 0),
                   quiet=args.quiet, **display)
    written = write_image(args.output, image, png=not args.no_png, exposure=args.exposure)
    if not args.quiet:
        print(f"wrote {', '.join(map(str, written))} ({image.shape[1]}x{image.shape[0]}, {spp} spp)")
    return 0


def _export(args) -> int:
    from mirad import export
    from mirad.errors import OutputError
    from mirad.files import check_output

    if not (args.output or args.shapes or args.lightmaps or args.organs):
        raise OutputError("nothing to export; give -o FILE (.ply, .csv, .npz), --shapes FILE.csv, "
                          "--organs FILE (.csv, .npz) or --lightmaps DIR")
    for path in args.output:
        check_output(path, (".ply",) + export.TABLE_SUFFIXES)
    if args.shapes:
        check_output(args.shapes, (".csv",))
    if args.lightmaps:
        if not os.path.isdir(args.lightmaps):
            raise OutputError(f"lightmap folder '{args.lightmaps}' does not exist; create it first")
        check_output(os.path.join(args.lightmaps, export.LIGHTMAP_INDEX))
    if args.lightmap_res < 1:
        raise OutputError(f"--lightmap-res {args.lightmap_res} must be >= 1 (e.g. 256)")
    loaded = _check_organs(args)
    scene, sol = _solution(args, scene=loaded)
    written = []
    for path in args.output:
        if path.lower().endswith(".ply"):
            written.append(export.write_ply(sol, path, mesh=args.ply_mesh, exposure=args.ply_exposure))
        else:
            written.append(export.write_table(sol, path))
    if args.shapes:
        written.append(export.write_shape_summary(sol, args.shapes))
    if args.organs:
        written.append(export.write_organ_table(sol, args.organs, by=args.organs_by or "component",
                                                property=args.groups_property))
    if args.lightmaps:
        written += export.write_lightmaps(sol, args.lightmaps, resolution=args.lightmap_res,
                                          supersample=args.lightmap_supersample, error=args.error_maps,
                                          quiet=args.quiet)
    if not args.quiet:
        print(f"wrote {', '.join(map(str, written))}")
    return 0


def _check_organs(args):
    """Check --organs, --organs-by and --groups-property before any work; with face groups, load
    the scene and read its groups once (a wrong property is refused before solving). Returns
    the loaded scene, or None."""
    from mirad import export
    from mirad.errors import SettingsError
    from mirad.files import check_output

    if not args.organs:
        given = [flag for flag, value in (("--organs-by", args.organs_by), ("--groups-property", args.groups_property))
                 if value is not None]
        if given:
            raise SettingsError(f"{' and '.join(given)} need{'s' if len(given) == 1 else ''} --organs FILE "
                                "(.csv or .npz), the per-organ table to write")
        return None
    check_output(args.organs, export.TABLE_SUFFIXES)
    by = args.organs_by or "component"
    if by not in export.ORGAN_KINDS:
        raise SettingsError(f"--organs-by {by} is unknown; choose component (connected pieces of each mesh, "
                            "such as leaves), group (face groups of the mesh files) or shape")
    if args.groups_property is not None and by != "group":
        raise SettingsError(f"--groups-property {args.groups_property} only applies to --organs-by group; "
                            "add --organs-by group or drop it")
    if by != "group":
        return None
    import mirad
    from mirad.organs import triangle_groups

    scene = mirad.load_scene(args.scene, variant=args.variant)
    triangle_groups(scene, property=args.groups_property)
    return scene


def _probe(args) -> int:
    from mirad.errors import SettingsError
    from mirad.export import read_points, write_probe_table
    from mirad.files import check_output

    check_output(args.output, (".csv",))
    if args.rays < 1:
        raise SettingsError(f"--rays {args.rays} must be >= 1")
    tol = args.probe_tolerance
    if tol is not None and not 0 < tol < 1:
        raise SettingsError(f"--probe-tolerance {tol:g} must be a relative standard error between 0 and 1 "
                            "(exclusive), e.g. 0.01")
    points, normals = read_points(args.points)
    scene, sol = _solution(args)
    irradiance, error = sol.irradiance_at(points, normals, rays=args.rays, tolerance=tol, with_error=True)
    from mirad.bands import channel_names, is_band_result

    write_probe_table(args.output, points, normals, irradiance, error,
                      bands=channel_names(sol) if is_band_result(sol) else None)
    if not args.quiet:
        print(f"wrote {args.output} ({len(points)} points)")
    return 0


# --- sky ---------------------------------------------------------------------------------------

def _add_sky_command(sub) -> None:
    sky = sub.add_parser("sky", help="write a standard sky (uniform, CIE overcast, with a sun) as an EXR and "
                                     "print its XML emitters (docs/skies.md)")
    sky.add_argument("model", choices=("uniform", "overcast"), help="sky radiance model")
    sky.add_argument("--irradiance", required=True,
                     help="horizontal irradiance of the diffuse sky, W/m^2 (or any linear unit): one number or R,G,B")
    sky.add_argument("--ground", type=float, default=None,
                     help="ground albedo whose glow fills the lower hemisphere (0: black; default: black, "
                          "and for 'uniform' Mitsuba's constant emitter, the same radiance all round)")
    sky.add_argument("--up", default="+z", help="the scene's up axis: +z (default), -z, +y, -y, +x or -x")
    sky.add_argument("--rows", type=int, default=None, help="rows of the latitude-longitude bitmap (odd)")
    sun = sky.add_argument_group("sun (all of --azimuth, --elevation and one irradiance add a directional sun)")
    sun.add_argument("--azimuth", type=float, default=None, help="sun azimuth, degrees from north towards east "
                     "(north +y, or -z when the up axis is y)")
    sun.add_argument("--elevation", type=float, default=None, help="sun elevation above the horizon, degrees")
    sun.add_argument("--direct-normal", default=None, help="sun's direct normal irradiance, W/m^2 (or R,G,B)")
    sun.add_argument("--direct-horizontal", default=None,
                     help="or the sun's direct irradiance on a horizontal plane, W/m^2 (or R,G,B)")
    sky.add_argument("-o", "--output", default=None,
                     help="EXR file for the sky's bitmap (needed by envmap skies: overcast, or --ground)")


def _sky(args) -> int:
    from mirad import sky
    from mirad.errors import SettingsError
    from mirad.files import check_output

    def values(text, option):
        numbers = _numbers(text, option, float)
        if numbers is not None and len(numbers) not in (1, 3):
            raise SettingsError(f"{option} {text!r}: give one number or three (R,G,B)")
        return None if numbers is None else (numbers[0] if len(numbers) == 1 else numbers)

    rows = {} if args.rows is None else {"rows": args.rows}
    irradiance = values(args.irradiance, "--irradiance")
    sun_given = [x is not None for x in (args.azimuth, args.elevation, args.direct_normal or args.direct_horizontal)]
    if any(sun_given) and not all(sun_given):
        raise SettingsError("a sun needs --azimuth, --elevation and --direct-normal or --direct-horizontal")
    if args.output:
        check_output(args.output, (".exr",))
    if all(sun_given):
        lights = sky.sun_and_sky(azimuth=args.azimuth, elevation=args.elevation, diffuse_irradiance=irradiance,
                                 direct_normal=values(args.direct_normal, "--direct-normal"),
                                 direct_horizontal=values(args.direct_horizontal, "--direct-horizontal"),
                                 sky=args.model, ground=args.ground, up=args.up, **rows)
    else:
        build = sky.overcast_sky if args.model == "overcast" else sky.uniform_sky
        lights = {"sky": build(irradiance, ground=args.ground, up=args.up, **rows)}
    envmap = any(d["type"] == "envmap" for d in lights.values())
    if envmap and not args.output:
        raise SettingsError(f"the {args.model} sky is an envmap: give -o sky.exr for its bitmap")
    text = sky.write_sky(lights, args.output if envmap else None)
    if envmap:
        name = os.path.basename(args.output)
        text = text.replace(f'value="{args.output}"', f'value="{name}"')
        print(f"<!-- {args.output} written; Mitsuba looks for {name} beside the scene file -->")
    print(text)
    return 0


def _check_variant(variant) -> None:
    """A CUDA variant without a GPU: one line, before Mitsuba tries and fails deep inside."""
    from mirad import _runtime
    from mirad.errors import EnvironmentProblem

    if variant and variant.startswith("cuda") and not _runtime.has_cuda():
        raise EnvironmentProblem(f"--variant {variant} needs an NVIDIA GPU with CUDA, and none was found; "
                                 "use --variant llvm_ad_rgb (CPU) or leave --variant out")


def _interrupted() -> int:
    from mirad.files import WRITTEN

    if WRITTEN:
        print(f"mirad: interrupted after writing {', '.join(map(str, WRITTEN))}; the other outputs were not "
              "written", file=sys.stderr)
    else:
        print("mirad: interrupted; no output was written", file=sys.stderr)
    return 130


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings as one line each, 'mirad: warning: ...' (no source path or code line)."""
    print(f"mirad: warning: {message}", file=sys.stderr if file is None else file)


def command_options(command: str) -> dict:
    """{dest: argparse.Action} of one command's options (``mirad COMMAND --help`` lists the same)."""
    top = parser()
    commands = next(a for a in top._actions if a.dest == "command")     # the subparsers action
    if command not in commands.choices:
        raise ValueError(f"unknown command {command!r}; choose one of {', '.join(commands.choices)}")
    return {a.dest: a for a in commands.choices[command]._actions}


def main(argv=None) -> int:
    import warnings

    try:
        from mirad.files import raise_on_sigterm
    except Exception as exc:  # pragma: no cover - broken installation
        print(f"mirad: error: cannot import mirad ({exc})", file=sys.stderr)
        return 2
    args = parser().parse_args(argv)
    # main() is also called in-process (tests, notebooks): what it changes process-wide for the
    # command's run, it puts back when the command returns
    previous_show = warnings.showwarning
    warnings.showwarning = _show_warning
    previous_sigterm = raise_on_sigterm()
    try:
        return _run_command(args)
    finally:
        warnings.showwarning = previous_show
        if previous_sigterm is not None:
            signal.signal(signal.SIGTERM, previous_sigterm)


def _run_command(args) -> int:
    """Run one parsed command; errors become a message and an exit status, never a traceback."""
    from mirad.errors import MiradError
    from mirad.files import Terminated

    try:
        _check_variant(getattr(args, "variant", None))
        return {"solve": _solve, "info": _info, "validate": _validate, "render": _render,
                "export": _export, "probe": _probe, "sky": _sky}[args.command](args)
    except MiradError as exc:
        print(f"mirad: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return _interrupted()
    except Terminated:
        _interrupted()
        return 143
    except Exception as exc:  # never a traceback for users; MIRAD_DEBUG=1 shows it
        if "KeyboardInterrupt" in str(exc) or isinstance(exc.__cause__ or exc.__context__, KeyboardInterrupt):
            return _interrupted()      # Ctrl-C inside a Dr.Jit kernel arrives wrapped in a RuntimeError
        if os.environ.get("MIRAD_DEBUG"):
            raise
        print(f"mirad: error: {type(exc).__name__}: {exc} (set MIRAD_DEBUG=1 for a traceback)", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
