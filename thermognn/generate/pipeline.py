"""``generate(cfg)``: simulate the scene's load cases and write the HDF5 dataset (schema v1)."""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from thermognn.core.config import from_yaml, to_yaml
from thermognn.core.errors import ConfigError
from thermognn.core.io import versions_json
from thermognn.core.schema import NODE_CLAMPED, NODE_SURFACE, DatasetWriter, Trajectory, config_hash
from thermognn.core.state import StateLayout, state_layout, time_error_parts

from .scene import SceneSpec, between_node_points, check_load_cases, dataset_mesh, load_case, loadable_faces, \
    node_types, ramp, scene_from_config, boundary_faces_outward, vertex_normals


@dataclass
class TrajectoryCost:
    seconds: float
    steps: int
    newton_iterations: int
    cuts: int


def build_solid(spec: SceneSpec):
    """The dolfinx solid of a scene with its clamp applied; returns (solid, node_type, normals)."""
    from .meshing import to_dolfinx
    from .solid import Solid

    domain = to_dolfinx(spec.points, spec.tets)
    solid = Solid(domain, spec.material, spec.effects, spec.options)
    cells = solid.cells[:, :4]
    ntype = node_types(solid.nodes, cells, spec.mesh_cfg)
    solid.clamp(np.flatnonzero(ntype == NODE_CLAMPED))
    faces = boundary_faces_outward(solid.nodes, cells)
    # load direction: normals of the loadable surface itself (a top-face edge node points along
    # the top face's normal, not along the bisector with the side face); others: all faces
    normals = vertex_normals(solid.nodes, loadable_faces(solid.nodes, cells, ntype))
    missing = np.linalg.norm(normals, axis=1) == 0
    normals[missing] = vertex_normals(solid.nodes, faces)[missing]
    return solid, ntype, normals


def node_state(solid, layout: StateLayout) -> np.ndarray:
    """The per-node state z (N, D) of the solid's committed state, columns as in ``layout``.

    q = X + u [m], v [m/s] (with inertia), sigma: Cauchy stress [Pa] evaluated at the cell
    centroids and volume-averaged onto the nodes (not L2-projected), Voigt 11 22 33 12 13 23;
    xi_k: Cauchy push-forward of the Prony overstress of term k, averaged the same way.
    """
    z = np.zeros((len(solid.nodes), layout.dim))
    z[:, layout.slice("q")] = solid.nodes + solid.displacement()
    if "v" in layout.names:
        z[:, layout.slice("v")] = solid.velocity()
    z[:, layout.slice("sigma")] = solid.cauchy_stress_nodes()
    xi_names = [n for n in layout.names if n.startswith("xi")]
    if xi_names:
        for name, xi in zip(xi_names, solid.viscous_overstress_nodes()):
            z[:, layout.slice(name)] = xi
    return z


def load_factor(t: float, dt: float, ramp_steps: int, shape: str, substeps: int) -> float:
    """The load factor at time t [s]: the ramp (``scene.ramp``), or with ``substeps`` > 1 the
    ramp's values at the stored steps (multiples of dt) linearly between them, so that the loads
    the dataset stores define the loading within a stored step."""
    if substeps == 1:
        return ramp(t, dt, ramp_steps, shape)
    s = t / dt
    k = int(np.floor(s + 1e-9))
    w = min(1.0, max(0.0, s - k))
    return (1.0 - w) * ramp(k * dt, dt, ramp_steps, shape) + w * ramp((k + 1) * dt, dt, ramp_steps, shape)


def simulate(solid, spec: SceneSpec, layout: StateLayout, k: int, ntype: np.ndarray,
             normals: np.ndarray, between: np.ndarray, substeps: int | None = None
             ) -> tuple[Trajectory, TrajectoryCost]:
    """Simulate load case k from rest (``between``: the load points between the nodes, (B, 3) [m]),
    each stored step as ``substeps`` FE steps (default ``spec.substeps``); a failed step ends the
    trajectory as 'failed'."""
    t0 = time.perf_counter()
    case = load_case(k, solid.nodes, ntype, normals, spec.loads, between)
    point, load_nodes, full_force = case.point, case.load_nodes, case.force
    solid.reset()
    dt, ramp_steps, shape = spec.dt, spec.loads.ramp_steps, spec.loads.ramp_shape
    n_sub = spec.substeps if substeps is None else int(substeps)

    def set_loads(t: float) -> None:
        solid.set_nodal_force(load_factor(t, dt, ramp_steps, shape, n_sub) * full_force)

    set_loads(0.0)
    solid.initial_acceleration()
    times, zs, forces = [0.0], [node_state(solid, layout)], [ramp(0.0, dt, ramp_steps, shape) * full_force]
    status, reason, iterations, cuts = "ok", "", 0, 0
    for s in range(1, spec.steps + 1):
        for _ in range(n_sub):              # (one FE step of dt where n_sub is 1, as always)
            report = solid.step(dt / n_sub, set_loads)
            iterations += report.iterations
            cuts += report.cuts
            if not report.ok:
                break
        if not report.ok:
            status, reason = "failed", report.reason
            break
        z = node_state(solid, layout)
        if not np.all(np.isfinite(z)):
            status, reason = "failed", f"non-finite state at step {s}"
            break
        times.append(s * dt)
        zs.append(z)
        forces.append(ramp(s * dt, dt, ramp_steps, shape) * full_force)
    cost = TrajectoryCost(time.perf_counter() - t0, len(times) - 1, iterations, cuts)
    traj = Trajectory(name=f"traj_{k}", time=np.asarray(times), z=np.stack(zs), force=np.stack(forces),
                      load_nodes=load_nodes, load_point=point, status=status, reason=reason,
                      split_group=f"point_{case.point_index}", fe_seconds=cost.seconds,
                      fe_iterations=iterations, fe_cuts=cuts)
    return traj, cost


def _stale_partial(out: Path, nodes: np.ndarray, load_points) -> str:
    """Why a partial file to resume from cannot be resumed ('' if it can): other mesh nodes than
    ``nodes`` (N, 3), or a trajectory whose load point is not this draw's (``load_points(k)``, (3,) [m]:
    a file from an older load draw)."""
    import h5py

    partial = out.with_name(out.name + ".partial")
    if not partial.exists():
        return ""
    try:
        with h5py.File(partial, "r") as f:
            old = f["mesh/nodes"][()]
            if old.shape != nodes.shape or not np.allclose(old, nodes, rtol=0, atol=1e-12):
                return "a different mesh (gmsh version?)"
            for name, g in f.get("trajectories", {}).items():
                k = int(name.split("_")[-1])
                if not np.allclose(g.attrs["load_point"], load_points(k), rtol=0, atol=1e-12):
                    return f"other load points ({name})"
    except (OSError, KeyError, ValueError):
        return ""  # unreadable: DatasetWriter discards it itself
    return ""


def resume_key(scene_cfg) -> str:
    """What decides a dataset's trajectories: the scene config without its number of load cases
    (case k is the same whatever their number). A partial or finished file with the same key
    holds trajectories this run would solve alike; other keys (``train``, ``paths``, ...) do not
    matter to them."""
    from omegaconf import OmegaConf

    scene = OmegaConf.to_container(scene_cfg, resolve=True)
    if isinstance(scene.get("loads"), dict):
        scene["loads"].pop("n_trajectories", None)
    return json.dumps(scene, sort_keys=True)


def _grow_finished(out: Path, key: str, names: list[str], console) -> None:
    """Growing a finished dataset: where ``out`` holds some of ``names`` and nothing else, solved
    for the same scene (``resume_key``; only ``loads.n_trajectories`` raised), copy it to the
    partial file so that only the new cases are solved. ``out`` itself stays as it is until the
    grown file replaces it."""
    import h5py

    partial = out.with_name(out.name + ".partial")
    if partial.exists() or not out.exists():
        return
    try:
        with h5py.File(out, "r") as f:
            same = resume_key(from_yaml(str(f.attrs["config"])).scene) == key
            have = set(f["trajectories"].keys())
    except Exception:   # not a generated dataset (or unreadable): generate afresh, as before
        return
    if not (same and have < set(names)):
        return
    tmp = partial.with_name(partial.name + ".tmp")
    shutil.copyfile(out, tmp)
    with h5py.File(tmp, "r+") as f:
        f.attrs["resume_hash"] = config_hash(key)
    os.replace(tmp, partial)
    console.print(f"growing {out} from {len(have)} to {len(names)} trajectories")


def _linearised(solid, spec: SceneSpec, layout: StateLayout, writer: DatasetWriter, console) -> None:
    """Store the solid linearised at rest (``/linear``: the physics baseline ``evaluate`` reports,
    ``modes.linear_solid``), then print and store (root attribute ``time_resolution``) how well dt
    resolves its modes over the ok trajectories (``modes.diagnose``). A diagnostic: a failure here
    only prints a warning."""
    try:
        from .modes import describe, diagnose, linear_solid

        linear = linear_solid(solid)
        writer.set_linear(linear)
        report = diagnose(solid, writer.ok_trajectories, layout, spec.dt, linear=linear)
        if "skipped" not in report and not report["trajectories"]:
            return
        for line in describe(report, spec.name):
            console.print(line, soft_wrap=True)
        writer.set_time_resolution(report)
    except Exception as exc:  # a diagnostic: never fails generate
        msg = str(exc).splitlines()[0] if str(exc) else ""
        console.print(f"[yellow]warning[/]: time-resolution diagnostic failed ({type(exc).__name__}: {msg})",
                      soft_wrap=True)


#: ``time_convergence``: above this whole RRMSE (u or v) against twice the substeps, generate hints
#: at ``scene.time.substeps`` (the learned models' goal is 2 % against the data)
TIME_HINT = 0.05


def time_convergence(solid, spec: SceneSpec, layout: StateLayout, trajectories, ntype: np.ndarray,
                     normals: np.ndarray, between: np.ndarray) -> dict:
    """How far the data are from the same FE at twice the substeps (``scene.time.convergence_check``
    cases, the first ok ones): per case and on their mean, the whole-rollout relative L2 error
    ‖z_data − z_fine‖ / ‖z_fine‖ of u = q − X [m], v [m/s] and σ [Pa] over all stored steps and
    nodes, with both solves' FE seconds. The data's own error against the converged motion is of
    that order: 4/3 of it where the trapezoid converges at its second order, about equal where
    stiff damped modes it does not damp make it first order (the block). A JSON-ready dict, or
    {"skipped": why}."""
    if spec.convergence_check == 0:
        return {"skipped": "scene.time.convergence_check = 0"}
    if "inertia" not in spec.effects and "viscous" not in spec.effects:
        return {"skipped": "quasi-static and elastic: the data do not depend on the time step"}
    t0 = time.perf_counter()
    fine_substeps = 2 * spec.substeps
    X = solid.nodes
    groups = {"u": layout.slice("q"), **({"v": layout.slice("v")} if "v" in layout.names else {}),
              "sigma": layout.slice("sigma")}
    cases = []
    for traj in trajectories():
        if len(cases) == spec.convergence_check:
            break
        k = int(traj.name.split("_")[-1])
        fine, cost = simulate(solid, spec, layout, k, ntype, normals, between, substeps=fine_substeps)
        case: dict = {"name": traj.name, "seconds": round(float(traj.fe_seconds), 3),
                      "fine_seconds": round(cost.seconds, 3)}
        if fine.status != "ok" or fine.z.shape != traj.z.shape:
            case["failed"] = fine.reason or "the finer solve stopped early"
        else:
            for g, sl in groups.items():
                data, ref = traj.z[..., sl], fine.z[..., sl]                     # [S, N, c]
                if g == "u":
                    data, ref = data - X, ref - X
                norm = float(np.linalg.norm(ref))
                case[g] = float(np.linalg.norm(data - ref) / norm) if norm > 0 else 0.0
        cases.append(case)
    done = [c for c in cases if "failed" not in c]
    out: dict = {"dt": float(spec.dt), "substeps": spec.substeps, "fine_substeps": fine_substeps, "cases": cases}
    for g in groups:
        out[g] = float(np.mean([c[g] for c in done])) if done else None
    out["seconds"] = round(time.perf_counter() - t0, 3)
    return out


def describe_convergence(report: dict, scene: str = "") -> list[str]:
    """One or two console lines (rich markup) that summarise :func:`time_convergence`."""
    where = f" ({scene})" if scene else ""
    if "skipped" in report:
        return [f"time convergence{where}: not checked, {report['skipped']}"]
    if not report["cases"]:
        return [f"time convergence{where}: not checked, no ok trajectory"]
    if report["u"] is None:
        return [f"time convergence{where}: the FE at {report['fine_substeps']} sub-steps a step failed: "
                + "; ".join(f"{c['name']}: {c['failed']}" for c in report["cases"])]
    parts = time_error_parts(report)
    cost = sum(c["seconds"] for c in report["cases"]), sum(c["fine_seconds"] for c in report["cases"])
    names = ", ".join(c["name"] for c in report["cases"])
    k = report["substeps"]
    lines = [f"time convergence{where}: the data (dt {report['dt']:g} s, {k} FE step{'s' if k > 1 else ''} a step) are "
             f"{parts} from the FE at {report['fine_substeps']} sub-steps a step ({names}: FE {cost[0]:.1f} s "
             f"against {cost[1]:.1f} s)"]
    if max(report["u"], report.get("v") or 0.0) > TIME_HINT:
        lines.append(f"[yellow]hint[/]: the data's own time error is above {100 * TIME_HINT:.0f} %, and every error "
                     f"against them includes it: solve finer with scene.time.substeps={2 * report['substeps']} "
                     f"(the error falls with the sub-step, as its square where the motion is resolved; "
                     f"docs/accuracy.md, session 92)")
    return lines


def generate(cfg) -> Path:
    """Build ``cfg.scene``, solve its load cases, write ``cfg.paths.dataset``; return the path.

    Resumable: trajectories already in the partial file (same scene, ``resume_key``) are skipped.
    Growable: re-run with a larger ``scene.loads.n_trajectories`` and the same ``out``, and only
    the new cases are solved (``_grow_finished``).
    """
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    for name in ("UFL", "ffcx"):
        logging.getLogger(name).setLevel(logging.WARNING)
    try:
        out = Path(str(cfg.paths.dataset))
        sc = cfg.scene
    except Exception:
        raise ConfigError("config: expected keys 'scene' and 'paths.dataset'") from None
    spec = scene_from_config(sc)
    layout = state_layout(spec.effects, len(spec.material.prony), spec.store_internal)
    console = Console(stderr=True)
    solid, ntype, normals = build_solid(spec)
    mesh = dataset_mesh(solid.nodes, solid.cells, ntype)
    costs: list[TrajectoryCost] = []
    failed = 0
    names = [f"traj_{k}" for k in range(spec.loads.n_trajectories)]
    check_load_cases(spec.loads, int((ntype == NODE_SURFACE).sum()))
    between = between_node_points(solid.nodes, ntype, loadable_faces(solid.nodes, solid.cells[:, :4], ntype)
                                  if spec.loads.between_nodes else None, spec.loads)     # drawn once
    key = resume_key(sc)
    _grow_finished(out, key, names, console)
    stale = _stale_partial(out, mesh.nodes,
                           lambda k: load_case(k, solid.nodes, ntype, normals, spec.loads, between).point)
    if stale:
        console.print(f"partial dataset has {stale}: starting afresh")
        out.with_name(out.name + ".partial").unlink()
    with DatasetWriter(out, mesh, layout, spec.dt, to_yaml(cfg), versions_json(), spec.name, spec.effects,
                       resume_key=key) as w:
        todo = [k for k, n in enumerate(names) if not w.has(n)]
        if len(todo) < len(names):
            console.print(f"resuming: {len(names) - len(todo)} of {len(names)} trajectories already done")
        with Progress(TextColumn("[bold]generate[/] {task.description}"), BarColumn(), MofNCompleteColumn(),
                      TimeRemainingColumn(), console=console, transient=False) as progress:
            task = progress.add_task(spec.name, total=len(todo))
            for k in todo:
                traj, cost = simulate(solid, spec, layout, k, ntype, normals, between)
                w.write(traj)
                costs.append(cost)
                failed += traj.status != "ok"
                if traj.status != "ok":
                    console.print(f"[yellow]{traj.name} failed[/]: {traj.reason}")
                progress.advance(task)
        _linearised(solid, spec, layout, w, console)
        if spec.substeps > 1:
            w.set_substeps(spec.substeps)
        try:                                   # a diagnostic: never fails generate
            report = time_convergence(solid, spec, layout, w.ok_trajectories, ntype, normals, between)
            if "skipped" not in report:
                w.set_time_convergence(report)
            for line in describe_convergence(report, spec.name):
                console.print(line, soft_wrap=True)
        except Exception as exc:
            msg = str(exc).splitlines()[0] if str(exc) else ""
            console.print(f"[yellow]warning[/]: time-convergence check failed ({type(exc).__name__}: {msg})",
                          soft_wrap=True)
    if costs:
        total_steps = sum(c.steps for c in costs)
        secs = sum(c.seconds for c in costs)
        console.print(
            f"FE cost ({spec.name}): {len(solid.nodes)} nodes, {len(solid.cells)} tets, "
            f"{secs / max(total_steps, 1):.4f} s/step, {secs / len(costs):.3f} s/trajectory, "
            f"{sum(c.newton_iterations for c in costs) / max(total_steps, 1):.2f} Newton it/step, "
            f"{sum(c.cuts for c in costs)} step cuts, {failed} failed of {len(costs)}", soft_wrap=True)
    return out
