"""How closely the learned law's family can hold a dataset's own law, apart from the fit by
equation error (no dynamics, no Prony history).

``model.prior_material=learned`` fits :class:`thermognn.train.learned_law.StrainEnergy` to the
training trajectories through the law prior's remainders, where the energy, the Prony terms and
the trajectories' dynamics are all tangled. This script asks the simpler question first: at the
cells' states C the data passes through (up to ``--trajectories`` training trajectories, evenly
through the training split, ``--cells`` of their cell states at random), how near can the
family's isochoric stress S_iso = 2 ∂Ψ_iso/∂C come to the scene's own (neo-Hookean or Ogden,
with the FE's regularised eigenvalues), fitted by L-BFGS directly to that stress? It prints the relative RMS and
the largest relative error per state for each family (``--families free,convex``), the hidden
units and the iterations. The volumetric part is left out: the scene's U = (J − 1)²/D is the
family's k0 term exactly.

    .venv/bin/python benchmarks/law_capacity.py runs/s80_liver96/dataset.h5 --hidden 32 --iterations 300
    .venv/bin/python benchmarks/law_capacity.py runs/s80_liver96/dataset.h5 --hidden 64 --iterations 1000 --families free

If a family cannot hold the law here, no fit of the trajectories will; if it can, what the
equation-error fit leaves is the optimiser's and the Prony terms'. docs/accuracy.md (session 80)
quotes its figures.
"""

from __future__ import annotations

import argparse
import time

import torch

from thermognn.core.config import load_config
from thermognn.train.data import Dataset, split_names, spread
from thermognn.train.law_prior import neo_hookean_pk2, ogden_isochoric_pk2
from thermognn.train.learned_law import StrainEnergy, convex_roots, invariant_scales


def cell_states(ds: Dataset, trajectories: int, cells: int, seed: int = 0) -> torch.Tensor:
    """Right Cauchy–Green tensors C [cells, 3, 3] of the dataset's cells along up to
    ``trajectories`` of its training trajectories (``train``'s default split and seed; evenly
    through the list, as the learned law's fit picks them), ``cells`` of them at random."""
    cfg = load_config()                                                          # train's default split and seed
    names = spread(split_names(ds, list(cfg.train.split), int(cfg.seed))["train"], trajectories)
    X = torch.as_tensor(ds.mesh.nodes, dtype=torch.float64)                     # [N, 3] m
    tets = torch.as_tensor(ds.mesh.tets, dtype=torch.long)                      # [T, 4]
    Dm_inv = torch.linalg.inv((X[tets[:, 1:]] - X[tets[:, :1]]).transpose(-1, -2))   # [T, 3, 3]
    Cs = []
    for name in names:
        x = torch.as_tensor(ds.read(name).z, dtype=torch.float64)[..., 0:3]     # [S, N, 3] positions
        F = (x[:, tets[:, 1:]] - x[:, tets[:, :1]]).transpose(-1, -2) @ Dm_inv   # [S, T, 3, 3]
        Cs.append((F.transpose(-1, -2) @ F).reshape(-1, 3, 3))
    C = torch.cat(Cs)
    pick = torch.randperm(C.shape[0], generator=torch.Generator().manual_seed(seed))[:cells]
    return C[pick]


def scene_isochoric_stress(ds: Dataset, C: torch.Tensor) -> torch.Tensor:
    """The scene's S_iso [n, 3, 3] Pa at C [n, 3, 3]."""
    mat = ds.material
    if mat.get("law") == "neo_hookean":
        F = torch.linalg.cholesky(C).transpose(-1, -2)                          # any F with FᵀF = C
        return neo_hookean_pk2(F, float(mat["C10"]), float(mat["D1"]))[0]
    if mat.get("law") == "ogden":
        return ogden_isochoric_pk2(C, [float(m) for m in mat["mu"]], [float(a) for a in mat["alpha"]])
    raise SystemExit(f"{ds.path}: scene.material.law = {mat.get('law')!r}, expected neo_hookean or ogden")


def fit(ds: Dataset, C: torch.Tensor, S: torch.Tensor, hidden: int, iterations: int, convex: bool) -> dict:
    """The family's isochoric part fitted to S [n, 3, 3] at C by L-BFGS; its errors and seconds."""
    lam, mu = ds.linear_solid().lame()
    law = StrainEnergy((hidden, 1), mu=mu, kappa=lam + 2.0 * mu / 3.0, scales=invariant_scales(C))
    roots = convex_roots(law, ("iso_out",)) if convex else {}   # as fit_strain_energy's convex family
    for r in roots.values():
        r.requires_grad_()
    fitted = [getattr(law, n).requires_grad_() for n in ("iso_linear", "iso_weight", "iso_bias", "iso_out")
              if n not in roots] + list(roots.values())
    opt = torch.optim.LBFGS(fitted, lr=1.0, max_iter=iterations, history_size=50, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-14, tolerance_change=1e-16)
    mean_square = S.pow(2).mean()

    def stress() -> torch.Tensor:
        for name, r in roots.items():
            setattr(law, name, r * r)
        return law.pk2(C)[0]

    def closure():
        opt.zero_grad()
        loss = (stress() - S).pow(2).mean() / mean_square
        loss.backward()
        return loss

    t0 = time.perf_counter()
    opt.step(closure)
    with torch.no_grad():
        err = stress() - S                                                      # [n, 3, 3] Pa
        per_state = err.flatten(1).norm(dim=1) / S.flatten(1).norm(dim=1).clamp(min=1e-12 * S.abs().max())
        return {"rms": float((err.pow(2).mean() / mean_square).sqrt()), "worst": float(per_state.max()),
                "seconds": time.perf_counter() - t0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset")
    ap.add_argument("--hidden", type=int, default=32, help="isochoric hidden units")
    ap.add_argument("--iterations", type=int, default=300, help="L-BFGS iterations")
    ap.add_argument("--families", default="free,convex", help="comma-separated: free, convex")
    ap.add_argument("--trajectories", type=int, default=40)
    ap.add_argument("--cells", type=int, default=40000)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    ds = Dataset(args.dataset)
    C = cell_states(ds, args.trajectories, args.cells)
    S = scene_isochoric_stress(ds, C)
    s1, s2, s3 = invariant_scales(C)
    print(f"{args.dataset}: {ds.material.get('law')} at {C.shape[0]} cell states of up to {args.trajectories} "
          f"trajectories (largest |Ī1 − 3| {s1:.3g}, |Ī2 − 3| {s2:.3g}, |J − 1| {s3:.3g}); {args.hidden} units, "
          f"{args.iterations} L-BFGS iterations, {args.threads} thread(s)")
    for family in args.families.split(","):
        if family not in ("free", "convex"):
            raise SystemExit(f"--families: {family!r}, expected free or convex")
        r = fit(ds, C, S, args.hidden, args.iterations, family == "convex")
        print(f"  {family}: relative RMS S_iso error {r['rms']:.3e}, worst state {r['worst']:.3e} ({r['seconds']:.0f} s)",
              flush=True)


if __name__ == "__main__":
    main()
