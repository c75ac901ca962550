"""All solver options in one frozen dataclass; the API, the CLI and the plugin build it.

How ``tolerance`` maps onto refinement
--------------------------------------
``tolerance`` is the target relative error of the solution: the area-weighted L1
error of per-triangle radiosity over the area-weighted mean *reflected* radiosity
B - E (emission is exact, so the error is measured against the light the solver
computes; relative to the mean of B itself, the error is smaller still).

Every link p <- q gets an error in watts (see ``solver.link_power_errors``):
``A_p * rho_p * (B_q * std_k(G v) / sqrt(n) + F_pq * spread_q)``, the sampling
error of its form factor plus the error of carrying the source's mean radiosity.
The estimate ``stats["estimated_error"]`` adds them per receiver
(``solver._element_errors``): partly visible links (a shadow edge in their samples)
in quadrature, times sqrt(2/pi); the other links and the source terms summed, times a
calibration constant measured against Mitsuba's path tracer
(``solver.ESTIMATE_CALIBRATION``); all over ``A_total * mean(B - E)``.
Multigridding passes refine every link whose error
exceeds ``link_error_scale * budget / (2 M)`` (M links, budget = the total error
the tolerance allows), splitting the source when its term dominates, and re-solve,
until the estimate is at or below ``tolerance``. Elements never split below
``A_min = max(min_area, (tolerance * min_area_factor)^2) * A_total``.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass

import numpy as np

from .errors import SettingsError

#: Most rays per link: one link's lanes must fit a Dr.Jit launch (arrays.MAX_LANES = 2^22)
#: many times over, so that a wave never holds one link alone.
MAX_SAMPLES_PER_LINK = 1 << 16
SOLVERS = ("gmres", "gauss-seidel", "jacobi")
CORES = ("hierarchical", "legacy")
SWITCHES = ("auto", "on", "off")
ORACLES = ("kernel", "bf", "bound")
#: Options that only the legacy core reads: with core="hierarchical" they are refused unless left
#: at their defaults (the hierarchical core always clusters, never culls shafts, bounds its own
#: errors and caps links, not elements). Shadow textures and the bf/bound oracles instead run the
#: solve on the legacy core, with a warning (solver.uses_hierarchical_core).
LEGACY_ONLY = ("shaft_culling", "clustering", "cluster_threshold", "link_error_scale", "max_elements")


@dataclass(frozen=True)
class Settings:
    """Options of one radiosity solve.

    Attributes
    ----------
    tolerance : float, default 0.03
        Target relative error of the solution (0 < tolerance < 1), see module docstring.
    samples_per_link : int, default 16
        Receiver quadrature points and visibility rays per link (>= 1).
    seed : int, default 0
        Seed of every random number; same seed, same input, same variant -> same output.
    solver : str, default "gmres"
        Linear solver: "gmres" (Krylov, robust for near-white rooms), "gauss-seidel"
        (block Gauss-Seidel over input patches) or "jacobi" (plain, slow when rho -> 1).
    oracle : str, default "kernel"
        Refinement oracle: "kernel" (spread of the sampled kernel over the receiver,
        weighted by rho * B_source), "bf" (rho * B_source * F_hat, Hanrahan et al. 91) or
        "bound" (rho * B_source * (F_max - F_min), with F_min = 0 unless the link is proven
        fully visible; its estimate is a bound, uncalibrated and conservative).
    shaft_culling : str, default "auto"
        Prove links fully visible (shaft against a hierarchy of the scene's triangles) or
        fully blocked (corner rays through one convex occluder) and trace no rays for them
        or their children. "auto": only for the ``bound`` oracle, which needs the proofs
        (in numpy the test costs ~25 us per link, more than 16 shadow rays, so it does not
        pay for itself as a ray saving); "on"/"off" force it. Never in scenes with curved
        shapes (rays hit the true surface, not its tessellation).
    shadow_textures : bool, default False
        Links from emitters that are partly visible and would split may instead carry a
        convolution shadow texture (shadows.py) when its predicted error fits their share of
        the error budget: the receiver stays coarse. Per-triangle outputs use the texture's
        mean transfer; renders and lightmaps do not show the texture's detail yet.
    solver_tolerance : float, default 1e-6
        Relative residual at which the linear solve stops.
    max_iterations : int, default 2000
        Largest number of solver sweeps (or Krylov iterations) per solve.
    min_area : float, default 1e-6
        Smallest element area relative to the total surface area.
    min_area_factor : float, default 0.05
        Elements stop splitting at area (tolerance * min_area_factor)^2 * A_total.
    link_error_scale : float, default 5.0
        How far above its even share of the error budget a link may stay unrefined in a
        pass (see module docstring); smaller refines more per pass.
    max_refine_passes : int, default 12
        Largest number of multigridding passes (refine, then solve).
    max_elements : int, default 2_000_000
        Safety cap on the element count; refinement stops there with a warning.
    max_links : int or None, default None
        Safety cap on the link count (refinement stops before a wave would pass it, with a
        warning naming the estimate reached); None: what 2 GiB (``solver.DEFAULT_LINK_MEMORY``,
        or half the machine's memory if less) holds at ``solver.LINK_PEAK_BYTES`` per link (a
        solve's peak memory per link, wave temporaries included): about 5 M links.
    clustering : str, default "auto"
        "on": every patch starts linked to the root of a bounding-volume hierarchy over the
        patches, opened by refinement (links grow ~linearly); "off": all facing pairs of
        patches start linked (O(P^2)); "auto": on above ``cluster_threshold`` patches.
    cluster_threshold : int, default 256
        Patch count above which "auto" clustering switches on.
    variant : str or None, default None
        Mitsuba variant; None picks cuda_ad_rgb with a GPU, else llvm_ad_rgb.
    quiet : bool, default False
        No progress bars.
    workers : int, default 0
        Run the link waves (either core's) on a Dask ``LocalCluster`` of this many worker
        processes (mirad/distributed.py); 0: in this process. Results are bitwise the same. Needs a
        scene loaded from a file (workers load it themselves).
    scheduler : str or None, default None
        Address of a running Dask scheduler (e.g. "tcp://10.0.0.5:8786") to run the
        link waves on instead of a local cluster; takes precedence over ``workers``.
    core : str, default "hierarchical"
        "hierarchical": links at any level between volume clusters, face clusters and
        triangles, exact unoccluded transfers, rays for visibility only (core.py);
        "legacy": links on receiver leaves with Monte Carlo transfers (solver.py), kept for
        the options and oracles only it has (slower: 30-40 s against 4.2 s on the furnished
        room at tolerance 0.05, 2 cores). Shadow
        textures and the ``bf``/``bound`` oracles run on the legacy core (with a warning when
        "hierarchical" was asked for), and so take the options in ``LEGACY_ONLY``; any other
        hierarchical solve refuses those unless they are left at their defaults.
    periodic : str or None, default None
        A periodic ("infinite") canopy: the lateral pattern box "amin,bmin,amax,bmax" (metres,
        the scene file's frame, along the two horizontal axes of ``periodic_up``: x and y for
        +z) whose sides rays wrap around, so the plot stands for an infinite field
        (mirad/periodic.py, docs/periodic.md); the API also takes four numbers. Every shape must
        lie inside the box; hierarchical core only. None: not periodic.
    periodic_up : str, default "+z"
        The scene's up axis for ``periodic`` (+z, -z, +y, -y, +x or -x); the box spans the
        two other axes.
    error_shapes : str or None, default None
        The shapes the tolerance is measured over: comma-separated shape ids or shell-style
        patterns ("plant-*,stem"; the API also takes a list). The estimate is then relative to
        their light alone (their area times their mean irradiance) and counts the other
        shapes' errors only as far as they can reach them: the share of their reflected light
        that arrives on the named shapes, directly by their links and after interreflection
        (``core.output_weights``). A canopy on a large ground
        asked for ``error_shapes="plant-*"`` gets per-leaf accuracy, where over every shape
        the ground's area dilutes the leaves' error. Every pattern must match a shape;
        hierarchical core only. None: every shape.
    """

    tolerance: float = 0.03
    samples_per_link: int = 16
    seed: int = 0
    solver: str = "gmres"
    oracle: str = "kernel"
    shaft_culling: str = "auto"
    shadow_textures: bool = False
    solver_tolerance: float = 1e-6
    max_iterations: int = 2000
    min_area: float = 1e-6
    min_area_factor: float = 0.05
    link_error_scale: float = 5.0
    max_refine_passes: int = 12
    max_elements: int = 2_000_000
    max_links: int | None = None
    clustering: str = "auto"
    cluster_threshold: int = 256
    variant: str | None = None
    quiet: bool = False
    workers: int = 0
    scheduler: str | None = None
    core: str = "hierarchical"
    periodic: str | None = None
    periodic_up: str = "+z"
    error_shapes: str | None = None

    def __post_init__(self) -> None:
        if isinstance(self.error_shapes, (list, tuple)) and all(isinstance(x, str) for x in self.error_shapes):
            object.__setattr__(self, "error_shapes", ",".join(self.error_shapes))
        self._check_types()
        if not (0.0 < float(self.tolerance) < 1.0):
            raise SettingsError(
                f"tolerance={self.tolerance!r} is outside (0, 1); give the target relative error, e.g. 0.01"
            )
        if int(self.samples_per_link) != self.samples_per_link or self.samples_per_link < 1:
            raise SettingsError(
                f"samples_per_link={self.samples_per_link!r} must be an integer >= 1 (e.g. 16)"
            )
        if self.samples_per_link > MAX_SAMPLES_PER_LINK:
            raise SettingsError(
                f"samples_per_link={self.samples_per_link!r} is more than one link's rays can hold in a Dr.Jit "
                f"launch of bounded memory; give at most {MAX_SAMPLES_PER_LINK} (a lower tolerance refines instead)"
            )
        if self.solver not in SOLVERS:
            raise SettingsError(f"solver={self.solver!r} is unknown; choose one of {', '.join(SOLVERS)}")
        if self.clustering not in SWITCHES:
            raise SettingsError(f"clustering={self.clustering!r} is unknown; choose one of {', '.join(SWITCHES)}")
        if self.shaft_culling not in SWITCHES:
            raise SettingsError(f"shaft_culling={self.shaft_culling!r} is unknown; choose one of {', '.join(SWITCHES)}")
        if self.core not in CORES:
            raise SettingsError(f"core={self.core!r} is unknown; choose one of {', '.join(CORES)}")
        if self.oracle not in ORACLES:
            raise SettingsError(f"oracle={self.oracle!r} is unknown; choose one of {', '.join(ORACLES)}")
        if not (0.0 < self.solver_tolerance < 1.0):
            raise SettingsError(f"solver_tolerance={self.solver_tolerance!r} must be in (0, 1), e.g. 1e-6")
        if self.max_iterations < 1 or self.max_refine_passes < 1 or self.max_elements < 1:
            raise SettingsError("max_iterations, max_refine_passes and max_elements must be >= 1")
        if self.max_links is not None and (isinstance(self.max_links, bool) or int(self.max_links) != self.max_links
                                           or self.max_links < 1):
            raise SettingsError(f"max_links={self.max_links!r} must be an integer >= 1, or None (memory-based)")
        if not (0.0 < self.min_area < 1.0):
            raise SettingsError(f"min_area={self.min_area!r} must be in (0, 1) (relative to total area)")
        if self.link_error_scale <= 0:
            raise SettingsError(f"link_error_scale={self.link_error_scale!r} must be > 0")
        if isinstance(self.workers, bool) or int(self.workers) != self.workers or self.workers < 0:
            raise SettingsError(f"workers={self.workers!r} must be an integer >= 0 (0: no Dask workers)")
        if self.scheduler is not None and (not isinstance(self.scheduler, str) or not self.scheduler.strip()):
            raise SettingsError(f"scheduler={self.scheduler!r} must be a Dask scheduler address such as "
                                "'tcp://10.0.0.5:8786'")
        # (shadow textures and the bf/bound oracles solve on the legacy core, which reads them)
        if self.core == "hierarchical" and self.legacy_feature() is None:
            defaults = {f.name: f.default for f in dataclasses.fields(self)}
            ignored = [f"{name}={getattr(self, name)!r}" for name in LEGACY_ONLY if getattr(self, name) != defaults[name]]
            if ignored:
                raise SettingsError(f"{', '.join(ignored)}: only the legacy core reads {'it' if len(ignored) == 1 else 'them'}, "
                                    "and core='hierarchical' would ignore it; leave it out, or add core='legacy' "
                                    "(CLI: --core legacy)")
        if self.periodic is not None:
            from .periodic import parse_box

            if parse_box(self.periodic, self.periodic_up) is not None and self.core != "hierarchical":
                raise SettingsError(f"periodic={self.periodic!r} runs on the hierarchical core only; add "
                                    "core='hierarchical' (CLI: --core hierarchical)")
        elif not isinstance(self.periodic_up, str) or self.periodic_up.strip().lower() not in (
                "+z", "-z", "+y", "-y", "+x", "-x", "x", "y", "z"):
            raise SettingsError(f"periodic_up={self.periodic_up!r} is not an axis; give one of +z, -z, +y, -y, +x, -x")
        if self.error_shapes is not None:
            if not isinstance(self.error_shapes, str) or not shape_patterns(self.error_shapes):
                raise SettingsError(f"error_shapes={self.error_shapes!r} names no shape; give shape ids or patterns, "
                                    "comma-separated (e.g. 'plant-*,stem'), or leave it out for every shape")
            if self.core != "hierarchical" or self.legacy_feature() is not None:
                feature = self.legacy_feature() or "core='legacy'"
                raise SettingsError(f"error_shapes={self.error_shapes!r} runs on the hierarchical core only, and "
                                    f"{feature} solves on the legacy core; leave one of them out")
        if int(self.seed) != self.seed or self.seed < 0:
            raise SettingsError(f"seed={self.seed!r} must be a non-negative integer")

    def _check_types(self) -> None:
        """Numbers must be real numbers (not strings, booleans, NaN or infinities), integers
        integral, switches booleans: the message names the field and the fix."""
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            kind = annotation_text(f.type)
            if value is None and "None" in kind:
                continue
            if kind.startswith("bool"):
                if not isinstance(value, (bool, np.bool_)):
                    raise SettingsError(f"{f.name}={value!r} must be True or False")
            elif kind.startswith(("int", "float")):
                if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
                    raise SettingsError(f"{f.name}={value!r} must be a number, e.g. {f.name}={f.default!r}")
                if not math.isfinite(float(value)):
                    raise SettingsError(f"{f.name}={value!r} must be finite, e.g. {f.name}={f.default!r}")
                if kind.startswith("int") and float(value) != int(value):
                    raise SettingsError(f"{f.name}={value!r} must be an integer, e.g. {f.name}={f.default!r}")

    def legacy_feature(self) -> str | None:
        """The asked-for feature only the legacy core has ("shadow_textures=True" or
        "oracle='bf'"/"oracle='bound'"), which makes a hierarchical solve run there; None if none."""
        if self.shadow_textures:
            return "shadow_textures=True"
        if self.oracle != "kernel":
            return f"oracle={self.oracle!r}"
        return None

    def replace(self, **changes) -> "Settings":
        """Copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)


def shape_patterns(text: str) -> list[str]:
    """The non-empty shape ids or patterns of a comma-separated ``error_shapes``."""
    return [p.strip() for p in text.split(",") if p.strip()]


def annotation_text(annotation) -> str:
    """A field's annotation as written ("float", "int | None"), whether the interpreter kept it as
    a string (``from __future__ import annotations``) or something evaluated it to the type (on a
    GPU machine's Python 3.12 test run ``str(float)`` read "<class 'float'>" and the type checks
    were skipped)."""
    if isinstance(annotation, str):
        return annotation
    if isinstance(annotation, type):
        return annotation.__name__
    return str(annotation)


def make_settings(**options) -> Settings:
    """Build Settings from keyword options, rejecting unknown names with a clear message."""
    names = {f.name for f in dataclasses.fields(Settings)}
    unknown = sorted(set(options) - names)
    if unknown:
        raise SettingsError(
            f"unknown option(s) {', '.join(unknown)}; valid options are {', '.join(sorted(names))}"
        )
    return Settings(**{k: v for k, v in options.items() if v is not None})
