"""Mitsuba BSDF plugin ``leaf``: a thin translucent surface that reflects and transmits diffusely.

.. pluginparameters::

 * - reflectance
   - |spectrum| or |texture|
   - Hemispherical reflectance rho: the fraction of the light arriving on either side that leaves
     from the same side, spread as a Lambertian (cosine) lobe. Required. (|exposed|, |differentiable|)
 * - transmittance
   - |spectrum| or |texture|
   - Hemispherical transmittance tau: the fraction of the light arriving on either side that leaves
     from the other side, spread as a Lambertian lobe. Required; 0 gives a two-sided diffuse
     surface. (|exposed|, |differentiable|)

Both sides reflect with ``reflectance`` and transmit with ``transmittance``; the rest, 1 - rho - tau,
is absorbed. The values must lie in [0, 1] and rho + tau <= 1 in every channel, else the plugin
refuses to load (constant values are checked here, bitmaps by their texel range; mirad's loader
checks every texture point by point). The BSDF value is rho / pi * cos(theta_o) for an outgoing
direction on the incident side and tau / pi * |cos(theta_o)| on the other side; ``sample`` picks the
lobe with probability proportional to the channel means of rho and tau and draws a cosine-weighted
direction in its hemisphere, so every sample weight is rho / P(reflect) or tau / P(transmit).

Different optics on the two sides (the upper and lower faces of a leaf) are two ``leaf`` BSDFs in
Mitsuba's ``twosided`` adapter, which needs ``allow_transmission`` to nest a transmitting BSDF. The
adapter picks the nested BSDF by the side of ``si.wi``, which in Mitsuba's path tracer is the side
the light *leaves* towards the camera, while in light tracing it is the side the light arrives on:
the two agree only when both leaves have the same transmittance (reciprocity), so only the
reflectance may differ per side, and mirad refuses a pair whose transmittances differ (see
docs/leaves.md).

.. tabs::

    .. code-tab:: xml

        <bsdf type="twosided">
            <boolean name="allow_transmission" value="true"/>
            <bsdf type="leaf">   <!-- front (upper, adaxial) side -->
                <rgb name="reflectance" value="0.06, 0.12, 0.05"/>
                <rgb name="transmittance" value="0.04, 0.10, 0.03"/>
            </bsdf>
            <bsdf type="leaf">   <!-- back (lower, abaxial) side -->
                <rgb name="reflectance" value="0.10, 0.16, 0.09"/>
                <rgb name="transmittance" value="0.04, 0.10, 0.03"/>
            </bsdf>
        </bsdf>

    .. code-tab:: python

        'type': 'leaf',
        'reflectance': {'type': 'rgb', 'value': [0.06, 0.12, 0.05]},
        'transmittance': {'type': 'rgb', 'value': [0.04, 0.10, 0.03]}

``import mirad`` registers the plugin in the current Mitsuba variant and in every variant set later
(``install``). The ``mitsuba`` command-line program cannot see it (it is registered from Python).
"""

from __future__ import annotations

import math

import numpy as np

from . import _runtime  # noqa: F401  (LLVM set-up before mitsuba)

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

#: The plugin's parameters; any other property is an error naming it.
PARAMETERS = ("reflectance", "transmittance")
#: Names of the RGB channels in messages.
CHANNELS = ("red", "green", "blue")
#: Slack of the construction checks: float32 storage of values such as 0.7 + 0.3.
SLACK = 1e-5

_DOC = __doc__
_classes: dict = {}


class LeafError(ValueError):
    """A ``leaf`` BSDF was given values it cannot represent (Mitsuba shows the message on load)."""


def constant_value(texture) -> list | None:
    """The per-channel value (list of 3 floats) of a spatially constant texture in an RGB variant,
    else None (spectral variants are not checked here: mirad solves in RGB)."""
    if not mi.is_rgb or texture.is_spatially_varying():
        return None
    value = texture.eval(dr.zeros(mi.SurfaceInteraction3f))
    return [float(v) for v in dr.ravel(value)]


def texel_range(texture) -> tuple[list, list] | None:
    """Per-channel (min, max), lists of 3 floats, over the texels of a floating-point bitmap texture
    in an RGB variant (its lookups interpolate between texels, so they stay within), or None for any
    other texture. 8- and 16-bit bitmaps are stored encoded (sRGB unless ``raw``), always within
    [0, 1]; they and every other texture are checked point by point by mirad's loader."""
    if not mi.is_rgb or not texture.class_name().startswith("Bitmap"):
        return None
    params = mi.traverse(texture)
    if "data" not in params.keys():
        return None
    data = np.asarray(params["data"].numpy())
    if data.size == 0 or data.ndim != 3 or not np.issubdtype(data.dtype, np.floating):
        return None
    lo, hi = data.min(axis=(0, 1)).astype(np.float64), data.max(axis=(0, 1)).astype(np.float64)
    if len(lo) not in (1, 3):
        return None
    return np.broadcast_to(lo, (3,)).tolist(), np.broadcast_to(hi, (3,)).tolist()


def check_values(name: str, reflectance, transmittance) -> None:
    """Refuse reflectance or transmittance outside [0, 1], or a sum above 1 (constants and bitmaps).

    ``name`` is how messages call the BSDF ("leaf BSDF 'bark'"). Raises LeafError; quiet when the
    textures can only be checked point by point (mirad's loader does that).
    """
    fix_sum = "lower them so that reflectance + transmittance <= 1 in every channel (the rest is absorbed)"
    ranges = {}
    for param, tex in (("reflectance", reflectance), ("transmittance", transmittance)):
        const = constant_value(tex)
        lo_hi = (const, const) if const is not None else texel_range(tex)
        if lo_hi is None:
            continue
        ranges[param] = (const, lo_hi[1])
        if min(lo_hi[0]) < -SLACK:
            raise LeafError(f"{name}: {param} {min(lo_hi[0]):.3g} < 0; give a {param} between 0 and 1")
        if max(lo_hi[1]) > 1 + SLACK:
            raise LeafError(f"{name}: {param} {max(lo_hi[1]):.3g} > 1 breaks energy conservation; "
                            f"give a {param} between 0 and 1")
    if len(ranges) < 2:
        return
    (c_r, max_r), (c_t, max_t) = ranges["reflectance"], ranges["transmittance"]
    if c_r is not None and c_t is not None:
        sums = [r + t for r, t in zip(c_r, c_t)]
        worst = max(range(len(sums)), key=lambda i: sums[i])
        if sums[worst] > 1 + SLACK:
            grey = len(set(c_r)) == 1 and len(set(c_t)) == 1
            where = "" if grey else f" in the {CHANNELS[worst]} channel"
            raise LeafError(f"{name}: reflectance {c_r[worst]:.3g} + transmittance {c_t[worst]:.3g} = "
                            f"{sums[worst]:.3g} > 1{where} breaks energy conservation; {fix_sum}")
    elif c_r is not None or c_t is not None:
        # a constant and a bitmap: per channel, the sum's largest value is the constant plus the
        # largest texel (reached at that texel)
        totals = [r + t for r, t in zip(max_r, max_t)]
        worst = max(range(3), key=lambda i: totals[i])
        if totals[worst] > 1 + SLACK:
            raise LeafError(f"{name}: reflectance + transmittance reaches {totals[worst]:.3g} > 1 in the "
                            f"{CHANNELS[worst]} channel (a texel of the bitmap plus the constant) and breaks "
                            f"energy conservation; {fix_sum}")


def is_leaf(bsdf) -> bool:
    """True when every lobe of ``bsdf`` is diffuse (Lambertian reflection or transmission) and one of
    them transmits: a ``leaf``, a ``twosided`` of leaves, a ``blendbsdf`` of leaves and diffuse BSDFs.

    Such a BSDF is exactly a radiosity surface with a transmittance, which mirad's loader measures per
    side (``Scene.tri_leaf``). Judged by the lobe flags, since a Python plugin's ``class_name()`` is
    just "BSDF"; glass (delta or glossy lobes) and opacity masks (null lobe) are not leaves.

    >>> is_leaf(mi.load_dict({"type": "leaf", "reflectance": 0.1, "transmittance": 0.05}))  # doctest: +SKIP
    True
    >>> is_leaf(mi.load_dict({"type": "thindielectric"}))                                 # doctest: +SKIP
    False
    """
    if bsdf is None:
        return False
    lobes = [int(bsdf.flags(i)) & int(mi.BSDFFlags.All) for i in range(bsdf.component_count())]
    diffuse = int(mi.BSDFFlags.Diffuse)
    return bool(lobes) and all(lobe & ~diffuse == 0 for lobe in lobes) and \
        any(lobe & int(mi.BSDFFlags.DiffuseTransmission) for lobe in lobes)


def _make_class():
    """The ``leaf`` BSDF class of the current Mitsuba variant (mi.BSDF is variant-specific)."""

    class Leaf(mi.BSDF):
        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            label = f"leaf BSDF '{props.id()}'" if props.id() else "leaf BSDF"
            unknown = [k for k in props.keys() if k not in PARAMETERS]
            if unknown:
                raise LeafError(f"{label}: unknown parameter '{unknown[0]}'; a leaf takes "
                                f"{' and '.join(PARAMETERS)}")
            for param in PARAMETERS:
                if not props.has_property(param):
                    example = "0.1" if param == "reflectance" else "0.05"
                    note = "" if param == "reflectance" else " (0 for an opaque leaf)"
                    raise LeafError(f"{label}: parameter '{param}' is missing; give it, e.g. "
                                    f"<rgb name=\"{param}\" value=\"{example}\"/>{note}")
            self.reflectance = props.get_texture("reflectance")
            self.transmittance = props.get_texture("transmittance")
            check_values(label, self.reflectance, self.transmittance)
            reflect = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide
            transmit = mi.BSDFFlags.DiffuseTransmission | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide
            self.m_components = [reflect, transmit]
            self.m_flags = reflect | transmit

        # --- helpers ---------------------------------------------------------------------
        def _albedos(self, ctx, si, active):
            """(rho, tau) unpolarized spectra at si, zero for a lobe the context disables."""
            rho = self.reflectance.eval(si, active)
            tau = self.transmittance.eval(si, active)
            if not ctx.is_enabled(mi.BSDFFlags.DiffuseReflection, 0):
                rho = dr.zeros(type(rho), dr.width(rho))
            if not ctx.is_enabled(mi.BSDFFlags.DiffuseTransmission, 1):
                tau = dr.zeros(type(tau), dr.width(tau))
            return rho, tau

        @staticmethod
        def _reflect_probability(rho, tau):
            """Float in [0, 1]: the chance of sampling reflection, by the channel means."""
            mr, mt = dr.mean(rho), dr.mean(tau)
            total = mr + mt
            return dr.select(total > 0, mr / dr.maximum(total, 1e-30), 0.0), total > 0

        @staticmethod
        def _spectrum(value):
            return mi.depolarizer(value) if mi.is_polarized else value

        # --- BSDF interface ------------------------------------------------------------------
        def sample(self, ctx, si, sample1, sample2, active=True):
            cos_i = mi.Frame3f.cos_theta(si.wi)
            active = mi.Bool(active) & (cos_i != 0)
            rho, tau = self._albedos(ctx, si, active)
            p_r, any_lobe = self._reflect_probability(rho, tau)
            active &= any_lobe
            reflect = sample1 < p_r
            local = mi.warp.square_to_cosine_hemisphere(sample2)
            # reflection: wo on the side of wi; transmission: on the other side
            z = dr.select(reflect, dr.mulsign(local.z, cos_i), -dr.mulsign(local.z, cos_i))
            bs = dr.zeros(mi.BSDFSample3f)
            bs.wo = mi.Vector3f(local.x, local.y, z)
            prob = dr.select(reflect, p_r, 1.0 - p_r)
            bs.pdf = prob * mi.warp.square_to_cosine_hemisphere_pdf(local)
            bs.eta = 1.0
            bs.sampled_type = dr.select(reflect, mi.UInt32(+mi.BSDFFlags.DiffuseReflection),
                                        mi.UInt32(+mi.BSDFFlags.DiffuseTransmission))
            bs.sampled_component = dr.select(reflect, mi.UInt32(0), mi.UInt32(1))
            active &= bs.pdf > 0
            weight = dr.select(reflect, rho, tau) / dr.maximum(prob, 1e-30)
            return bs, self._spectrum(dr.select(active, weight, 0.0))

        def eval(self, ctx, si, wo, active=True):
            value, _ = self.eval_pdf(ctx, si, wo, active)
            return value

        def pdf(self, ctx, si, wo, active=True):
            _, pdf = self.eval_pdf(ctx, si, wo, active)
            return pdf

        def eval_pdf(self, ctx, si, wo, active=True):
            cos_i, cos_o = mi.Frame3f.cos_theta(si.wi), mi.Frame3f.cos_theta(wo)
            active = mi.Bool(active) & (cos_i != 0) & (cos_o != 0)
            rho, tau = self._albedos(ctx, si, active)
            p_r, _ = self._reflect_probability(rho, tau)
            same = cos_i * cos_o > 0
            cos_abs = dr.abs(cos_o)
            value = dr.select(same, rho, tau) * (cos_abs / math.pi)
            pdf = dr.select(same, p_r, 1.0 - p_r) * (cos_abs / math.pi)
            return self._spectrum(dr.select(active, value, 0.0)), dr.select(active, pdf, 0.0)

        def eval_diffuse_reflectance(self, si, active=True):
            return self.reflectance.eval(si, active)

        def traverse(self, callback):
            callback.put("reflectance", self.reflectance, mi.ParamFlags.Differentiable)
            callback.put("transmittance", self.transmittance, mi.ParamFlags.Differentiable)

        def parameters_changed(self, keys=None):
            pass  # textures are evaluated at every call: nothing is cached

        def to_string(self):
            return (f"Leaf[\n  reflectance = {self.reflectance},\n"
                    f"  transmittance = {self.transmittance}\n]")

    Leaf.__doc__ = _DOC
    return Leaf


def leaf_class():
    """The ``leaf`` BSDF class of the current Mitsuba variant."""
    variant = mi.variant()
    if variant not in _classes:
        _classes[variant] = _make_class()
    return _classes[variant]


def register() -> None:
    """Register ``leaf`` with Mitsuba for the current variant (no-op without a variant)."""
    if mi.variant() is None:
        return
    cls = leaf_class()
    mi.register_bsdf("leaf", lambda props: cls(props))


def _on_variant_change(old, new) -> None:
    if new is not None:
        register()


def install() -> None:
    """Register now and again whenever the Mitsuba variant changes."""
    register()
    if not getattr(install, "_done", False):
        mi.detail.add_variant_callback(_on_variant_change)
        install._done = True
