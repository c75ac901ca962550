"""Refinement oracles: decide per link whether to keep it or split one of its ends.

The per-link errors (watts, compared against a share of the error budget) are computed
by ``solver.link_power_errors``:

* ``kernel`` (default): A_p * rho_p * B_q * std_k[G(x_k) v_k] / sqrt(n), the sampling
  error of the link's form factor from its n receiver points, plus the source term
  A_p * rho_p * F_pq * spread_q (the link carries the source's mean radiosity);
* ``bf`` (Hanrahan-Salzman-Aupperle 91, power form): A_p * rho_p * B_q * F_hat_pq, with
  F_hat the largest unoccluded point-to-source form factor over the receiver samples,
  plus the same source term.

Here: which end of a link over the threshold to split.
"""

from __future__ import annotations

import numpy as np


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
