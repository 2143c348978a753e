"""FE cost per step and per trajectory of the generate scenes and of the verification cases.

    .venv/bin/python benchmarks/fe_cost.py [--quick]

Scenes are simulated for one trajectory each (``--quick``: 5 steps) on this machine; the shared
meshes (liver, bunny) are skipped when ../shared is absent.
"""

from __future__ import annotations

import logging
import sys
import time

import numpy as np

from thermognn.core.config import PROJECT_ROOT, load_config
from thermognn.core.state import state_layout


def scene_cost(scene: str, steps: int | None) -> str:
    from thermognn.generate.pipeline import build_solid, simulate
    from thermognn.generate.scene import scene_from_config

    over = [f"scene={scene}"] + ([f"scene.time.steps={steps}"] if steps else [])
    cfg = load_config(over)
    t0 = time.perf_counter()
    spec = scene_from_config(cfg.scene)
    solid, ntype, normals = build_solid(spec)
    setup = time.perf_counter() - t0
    layout = state_layout(spec.effects, len(spec.material.prony), spec.store_internal)
    simulate(solid, spec, layout, 0, ntype, normals)         # warm-up (JIT, caches)
    traj, cost = simulate(solid, spec, layout, 1, ntype, normals)
    return (f"{scene:>6} {spec.material.law:>11} {'+'.join(spec.effects):>28} {len(solid.nodes):>6d} "
            f"{len(solid.cells):>6d} {cost.seconds / max(cost.steps, 1):>8.4f} {cost.seconds:>8.2f} "
            f"{cost.newton_iterations / max(cost.steps, 1):>6.2f} {setup:>7.2f} {traj.status:>6}")


def case_costs(quick: bool) -> list[str]:
    from thermognn.generate import cases
    from thermognn.generate.materials import Material

    rows = []
    t = time.perf_counter()
    e = cases.energy_history(n_steps=200)
    rows.append(f"energy (P1 2x2x4 boxes, 45 nodes, 200 Newmark steps): {time.perf_counter() - t:.2f} s, "
                f"drift {(e.max() - e.min()) / e[0]:.2e}")
    t = time.perf_counter()
    p = cases.snap_through(n_steps=20)
    rows.append(f"snap-through (P2 arch, 20 displacement steps): {time.perf_counter() - t:.2f} s, "
                f"limit load {p.force[:11].max():.3f} N at w = {p.displacement[np.argmax(p.force[:11])] * 1e3:.1f} mm, "
                f"valley {p.force[np.argmax(p.force[:11]):].min():.3f} N")
    t = time.perf_counter()
    q = cases.snap_through_arc_length()
    rows.append(f"snap-through (P2 arch, Riks arc-length, {len(q.force) - 1} increments): "
                f"{time.perf_counter() - t:.2f} s, limit load {q.force[q.displacement < 0.02].max():.4f} N")
    t = time.perf_counter()
    r = cases.uniaxial(Material("ogden", {"mu": [2e3], "alpha": [16.19], "D": [1e-4]}), 0.7, n_steps=6)
    rows.append(f"Ogden 30 % compression (P1 cube, 6 steps): {time.perf_counter() - t:.2f} s, "
                f"rel. error {r.rel_error:.1e}")
    return rows


def main(quick: bool = False) -> None:
    logging.getLogger().setLevel(logging.WARNING)
    steps = 5 if quick else None
    print(f"{'scene':>6} {'law':>11} {'effects':>28} {'nodes':>6} {'tets':>6} {'s/step':>8} {'s/traj':>8} "
          f"{'it/step':>6} {'setup':>7} {'status':>6}")
    for scene in ("block", "shell", "liver", "bunny"):
        if scene in ("liver", "bunny") and not (PROJECT_ROOT.parent / "shared" / "meshes").is_dir():
            print(f"{scene:>6} skipped (../shared/meshes absent)")
            continue
        print(scene_cost(scene, steps), flush=True)
    for row in case_costs(quick):
        print(row)


if __name__ == "__main__":
    main(quick="--quick" in sys.argv)
