"""Refinement oracles: decide per link whether to keep it or split one of its ends.

Kernel oracle (default; Bekaert-Willems 96 style, THEORY O4): refine link p <- q while

    rho_p * B_q * std_k[G(x_k) v_k] > eps,

where G(x_k) v_k are the sampled point-to-source form factors (visibility
included) at the link's receiver points. The spread of the kernel over the
receiver is what a constant-per-element link gets wrong: it sees 1/r^2 variation
near contact, shadow boundaries, and the far-field/near-field mismatch that makes
coarse links over-light elements next to a corner.

BF oracle (Hanrahan-Salzman-Aupperle 91): refine link p <- q while

    rho_p * B_q * F_hat_pq > eps,

with F_hat the largest unoccluded point-to-source form factor over the link's
receiver samples (a bounded estimate: <= 1 even for touching elements). The end
with the larger area is split (it subtends the larger solid angle), unless it is
already at the minimum element area.
"""

from __future__ import annotations

import numpy as np


def bf_error(ff_max: np.ndarray, rho_recv: np.ndarray, b_src: np.ndarray) -> np.ndarray:
    """(M,) BF link error, W/m^2: max over channels of rho_p * B_q, times F_hat."""
    return ff_max.astype(np.float64) * np.max(rho_recv * b_src, axis=1)


ORACLES = ("kernel", "bf")


def link_error(oracle: str, links, rho_recv: np.ndarray, b_src: np.ndarray) -> np.ndarray:
    """(M,) error of each link under the named oracle, W/m^2."""
    if oracle == "bf":
        return bf_error(links.ff_max, rho_recv, b_src)
    if oracle == "kernel":
        return kernel_error(np.maximum(links.ff_std, 0.5 * links.ff_range * links.vis), rho_recv, b_src)
    raise ValueError(f"unknown oracle {oracle!r}; choose one of {', '.join(ORACLES)}")


def kernel_error(ff_std: np.ndarray, rho_recv: np.ndarray, b_src: np.ndarray) -> np.ndarray:
    """(M,) kernel-variation link error, W/m^2: max over channels of rho_p * B_q, times std_k(G v)."""
    return ff_std.astype(np.float64) * np.max(rho_recv * b_src, axis=1)


def link_uncertainty(ff_std: np.ndarray, rho_recv: np.ndarray, b_src: np.ndarray) -> np.ndarray:
    """(M,) practical error of a link's transfer, W/m^2: rho_p * B_q * std of the sampled kernel.

    The kernel's spread over the receiver measures both the representation error
    (irradiance varies over the element but is stored as one value) and the
    quadrature/visibility sampling error.
    """
    return ff_std.astype(np.float64) * np.mean(rho_recv * b_src, axis=1)


def choose_splits(error: np.ndarray, eps: float, area_recv: np.ndarray, area_src: np.ndarray,
                  can_split_recv: np.ndarray, can_split_src: np.ndarray,
                  prefer_source: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Boolean masks (split source, split receiver) for the links whose error exceeds eps.

    The larger end is split, or the source where ``prefer_source`` says the error comes
    from the source's own radiosity variation; an end at the minimum area is never split.
    """
    want = error > eps
    pick_src = area_src >= area_recv
    if prefer_source is not None:
        pick_src = pick_src | prefer_source
    split_src = want & can_split_src & (pick_src | ~can_split_recv)
    split_recv = want & can_split_recv & ~split_src
    return split_src, split_recv
