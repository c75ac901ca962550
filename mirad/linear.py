"""Linear solvers for the hierarchical system on the leaves.

With L leaves and N elements, the operator of one gather + push-pull is

    K = P @ F @ R,    P (L, N): push (leaf <- ancestors), F (N, N): links,
                      R (N, L): pull (area-weighted mean of the leaves below),

and the radiosity of the leaves solves  B = E + rho * (K @ B)  per channel.
K is never formed (it can fill in); each product is three sparse mat-vecs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


@dataclass
class LeafSystem:
    """B = emission + rho * H + tau * (opposite @ H) with H = push @ links @ pull @ B, arrays
    over leaves (L, C).

    ``tau`` (L, C) and ``opposite`` (L, L), both or neither: the transmittance of a
    translucent leaf's other side and the area-weighted mean over that side's leaves (the
    light a leaf transmits leaves diffusely from its other side)."""

    push: sp.csr_matrix
    links: sp.csr_matrix
    pull: sp.csr_matrix
    rho: np.ndarray
    emission: np.ndarray
    tau: np.ndarray | None = None
    opposite: sp.csr_matrix | None = None
    _trimmed: tuple | None = field(default=None, init=False, repr=False, compare=False)

    def gather(self, b: np.ndarray) -> np.ndarray:
        """Irradiance (L, C) gathered over all links for leaf radiosity b (L, C)."""
        push, links, pull = self.trimmed()
        return push @ (links @ (pull @ b))

    def trimmed(self) -> tuple[sp.csr_matrix, sp.csr_matrix, sp.csr_matrix]:
        """(push, links, pull) over the nodes that receive a link (push's columns, the links'
        rows) and the nodes that send one (the links' columns, pull's rows) only: the same
        products (the nodes left out only add zeros) at a fraction of the work. A pass's
        system links a few hundred of tens of thousands of nodes, yet push and pull hold every
        node's leaves: its products were 6x the trimmed ones on the fine Cornell box."""
        # (kept with the matrices it was made from: a field set anew is trimmed again)
        made_of = (self.push, self.links, self.pull)
        if self._trimmed is None or any(a is not b for a, b in zip(self._trimmed[0], made_of)):
            links = self.links.tocsr()
            receivers = np.flatnonzero(np.diff(links.indptr) > 0)
            senders = np.unique(links.indices)
            self._trimmed = (made_of, (self.push[:, receivers].tocsr(), links[receivers][:, senders].tocsr(),
                                       self.pull[senders].tocsr()))
        return self._trimmed[1]

    def scatter(self, h: np.ndarray, channel: int | None = None) -> np.ndarray:
        """Radiosity that irradiance h (L, C), or (L,) of one channel, sends back out:
        reflected, and transmitted from the other side."""
        rho = self.rho if channel is None else self.rho[:, channel]
        out = rho * h
        if self.tau is not None:
            tau = self.tau if channel is None else self.tau[:, channel]
            out = out + tau * (self.opposite @ h)
        return out

    def residual(self, b: np.ndarray) -> float:
        r = b - self.emission - self.scatter(self.gather(b))
        scale = max(np.abs(self.emission).sum(), np.abs(b).sum(), 1e-300)
        return float(np.abs(r).sum() / scale)


def solve_system(system: LeafSystem, x0: np.ndarray, *, method: str, tol: float,
                 max_iterations: int) -> tuple[np.ndarray, int, float]:
    """Solve the leaf system; returns (B (L, C), iterations, relative residual)."""
    if method == "gmres":
        return _gmres(system, x0, tol, max_iterations)
    if method == "jacobi":
        return _jacobi(system, x0, tol, max_iterations)
    if method == "gauss-seidel":
        if system.tau is not None:      # (transmission couples leaves across the blocks)
            return _gmres(system, x0, tol, max_iterations)
        return _block_gauss_seidel(system, x0, tol, max_iterations)
    raise ValueError(f"unknown solver {method!r}")


def _jacobi(system: LeafSystem, x: np.ndarray, tol: float, max_iterations: int):
    for it in range(1, max_iterations + 1):
        new = system.emission + system.scatter(system.gather(x))
        change = np.abs(new - x).sum() / max(np.abs(new).sum(), 1e-300)
        x = new
        if change < tol:
            return x, it, system.residual(x)
    return x, max_iterations, system.residual(x)


def _gmres(system: LeafSystem, x0: np.ndarray, tol: float, max_iterations: int):
    n, channels = x0.shape
    out = np.empty_like(x0)
    total = 0
    for c in range(channels):
        emission = system.emission[:, c]
        if not np.any(emission) and not np.any(x0[:, c]):
            out[:, c] = 0.0
            continue

        def matvec(v, c=c):
            v = np.ravel(v)
            return v - system.scatter(system.gather(v), c)

        # solved for the reflected part R = B - E, (I - rho K) R = rho K E: its tolerance is
        # then relative to the first bounce, not to the emission (a light a millionth of the
        # room's area, a million times brighter, once made the warm start "converged" with
        # no reflected light at all)
        first = system.scatter(system.gather(emission), c)
        if not np.any(first):
            out[:, c] = emission
            continue
        op = spla.LinearOperator((n, n), matvec=matvec, dtype=np.float64)
        count = [0]

        def callback(_, count=count):
            count[0] += 1

        sol, info = spla.gmres(op, first, x0=x0[:, c] - emission, rtol=tol, atol=0.0, restart=min(60, n),
                               maxiter=max(1, max_iterations // 60 + 1), callback=callback,
                               callback_type="pr_norm")
        out[:, c] = emission + sol
        total += count[0]
    return out, total, system.residual(out)


def _block_gauss_seidel(system: LeafSystem, x: np.ndarray, tol: float, max_iterations: int,
                        blocks: int = 16):
    """Gauss-Seidel over blocks of leaves: each block gathers with the latest values."""
    x = x.copy()
    n = len(x)
    bounds = np.linspace(0, n, min(blocks, n) + 1).astype(int)
    y = system.pull @ x                       # element radiosity, kept current
    parts = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        push_b = system.push[a:b]
        needed = np.unique(push_b.indices)
        parts.append((a, b, push_b[:, needed], system.links[needed], system.pull[:, a:b].tocsc()))
    for it in range(1, max_iterations + 1):
        change = 0.0
        for a, b, push_b, links_b, pull_b in parts:
            new = system.emission[a:b] + system.rho[a:b] * (push_b @ (links_b @ y))
            delta = new - x[a:b]
            change += np.abs(delta).sum()
            y += pull_b @ delta
            x[a:b] = new
        if change / max(np.abs(x).sum(), 1e-300) < tol:
            return x, it, system.residual(x)
    return x, max_iterations, system.residual(x)
