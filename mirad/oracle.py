"""Refinement oracles: decide per link whether to keep it or split one of its ends.

The per-link errors (watts, compared against a share of the error budget) are computed
by ``solver.link_power_errors``:

* ``kernel`` (default): A_p * rho_p * B_q * std_k[G(x_k) v_k] / sqrt(n), the sampling
  error of the link's form factor from its n receiver points, plus the source term
  A_p * rho_p * F_pq * spread_q (the link carries the source's mean radiosity);
* ``bf`` (Hanrahan-Salzman-Aupperle 91, power form): A_p * rho_p * B_q * F_hat_pq, with
  F_hat the largest unoccluded point-to-source form factor over the receiver samples,
  plus the same source term;
* ``bound`` (lower/upper bounds, LTG93-style): A_p * rho_p * B_q * (F_max - F_min), see
  ``transfer_bounds``, plus the same source term.

Here: the transfer bounds, and which end of a link over the threshold to split.
"""

from __future__ import annotations

import numpy as np


def transfer_bounds(links, cluster: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F_min, F_max), each (M,): bounds of each link's form factor with visibility.

    F_max is the largest unoccluded point-to-source form factor over the receiver's sample
    points and (inset) corners, F_min the smallest when the link is proven fully visible
    (shaft.py) and 0 otherwise; both 0 when it is proven fully blocked. The visibility
    classes are proofs; the kernel's extremes are taken over the sample points, so for a
    kernel peaked between them (a receiver touching its source) they are estimates.
    The sampled form factor always lies in [F_min, F_max]. Cluster sources get (0, 0)
    here: the solver bounds them with their bounding sphere.
    """
    f_lo = links.ff_lo.astype(np.float64)
    f_hi = f_lo + links.ff_range
    visible, blocked = links.vclass == 1, links.vclass == 2
    f_lo = np.where(visible & ~cluster, f_lo, 0.0)
    f_hi = np.where(blocked | cluster, 0.0, f_hi)
    return f_lo, f_hi


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
