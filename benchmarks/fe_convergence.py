"""FE convergence: cantilever tip deflection error vs number of nodes (P1 and P2 tetrahedra).

Clamped beam L/h = 20, ν = 0, small tip shear (δ/L = 1e-4), reference Euler–Bernoulli
δ = P L³ / (3 E I) (shear deflection adds ~0.15 % at this slenderness, the floor of the P2 column).

    .venv/bin/python benchmarks/fe_convergence.py [--quick]
"""

from __future__ import annotations

import logging
import sys

from thermognn.generate import cases


def main(quick: bool = False) -> None:
    logging.getLogger().setLevel(logging.WARNING)
    meshes = [(10, 1), (20, 2), (40, 4)] if not quick else [(10, 1), (20, 2)]
    print(f"{'elements':>8} {'boxes':>10} {'nodes':>7} {'tip FE [m]':>12} {'rel. error':>10} {'time [s]':>8}")
    for degree in (1, 2):
        for n_len, n_sec in meshes:
            r = cases.cantilever(n_length=n_len, n_section=n_sec, degree=degree)
            print(f"{'P%d tets' % degree:>8} {f'{n_len}x{n_sec}x{n_sec}':>10} {r.n_nodes:>7d} "
                  f"{r.tip_fe:>12.5e} {r.rel_error:>10.2e} {r.seconds:>8.2f}")


if __name__ == "__main__":
    main(quick="--quick" in sys.argv)
