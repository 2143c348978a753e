"""Script the trained model with its mesh, check it against the eager model, save atomically."""

from __future__ import annotations

import json
import math
import statistics
import time
import warnings
from pathlib import Path

import torch
from omegaconf import OmegaConf

from thermognn.core.config import project_path
from thermognn.core.errors import ConfigError, DataError
from thermognn.core.io import atomic_path
from thermognn.core.schema import Dataset
from thermognn.core.state import law_iterates
from thermognn.train.checkpoint import (load_checkpoint, model_from_checkpoint, model_step, served_law_hht,
                                        served_law_settings, torch_dtype, with_rollout)
from thermognn.train.data import check_fingerprint, load_graph
from thermognn.train.hybrid import carried_layout

from .module import ExportedLinearPrior, ExportedTIGNN

FORMAT = "thermognn-model/1"
META_FILE = "thermognn.json"
#: default relative tolerance of the scripted-vs-eager check, per dtype
DEFAULT_RTOL = {torch.float32: 1e-4, torch.float64: 1e-9}


def data_time_record(ds: Dataset) -> dict | None:
    """The exported file's ``data_time_error``: how far the dataset's FE is from twice its sub-steps
    (``generate``'s check: {"substeps", "fine_substeps", "u", "v", "sigma"}), None where unmeasured."""
    tc = ds.time_convergence or {}
    if tc.get("u") is None:
        return None
    return {k: tc[k] for k in ("substeps", "fine_substeps", "u", "v", "sigma") if tc.get(k) is not None}


def metadata(ckpt: dict, internal=(), data_time: dict | None = None) -> str:
    """The ``thermognn.json`` extra file (keys as in docs/stages.md); ``internal``: the column
    groups a linear-prior model carries after a and G (``LinearPriorModel.carried_columns``, for
    ``carried_layout``); ``data_time``: ``data_time_record`` of the export's dataset (absent: None)."""
    return json.dumps({**({"data_time_error": data_time} if data_time else {}),
                       "format": FORMAT, "scene": ckpt.get("scene", ""), "effects": list(ckpt.get("effects", [])),
                       "state_layout": (carried_layout(ckpt["state_layout"], internal) if ckpt.get("prior")
                                        else ckpt["state_layout"]), "dt": float(ckpt["dt"]),
                       "structure": ckpt["structure"], "config": ckpt.get("config", ""),
                       "step": model_step(ckpt),
                       "versions": ckpt.get("versions", "{}")})


def build_exported(ckpt: dict, ds: Dataset) -> ExportedTIGNN | ExportedLinearPrior:
    """Eager ExportedTIGNN (or ExportedLinearPrior, ``model.prior=linear``) from a checkpoint and
    the dataset's mesh (z0: first 'ok' trajectory's initial state, the rest state of the scene)."""
    dtype = torch_dtype(ckpt["dtype"])
    core = model_from_checkpoint(ckpt, ds).eval()
    graph = load_graph(ds, dtype)
    names = ds.ok_names or ds.names
    if not names:
        raise DataError(f"{ds.path}: no trajectories to take the rest state z0 from")
    z0 = torch.as_tensor(ds.read(names[0]).z[0], dtype=dtype)
    if ckpt.get("prior"):
        return ExportedLinearPrior(core, z0, graph.edge_index, graph.node_type, graph.surface_faces, float(ckpt["dt"]))
    return ExportedTIGNN(core, graph.ref_pos, z0, graph.edge_index, graph.node_type, graph.surface_faces,
                         float(ckpt["dt"]))


def script(module: ExportedTIGNN | ExportedLinearPrior) -> torch.jit.ScriptModule:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return torch.jit.script(module)


def parity(eager: ExportedTIGNN | ExportedLinearPrior, scripted, ds: Dataset, steps: int = 3,
           modes: tuple[bool, ...] = (True, False)) -> tuple[float, float]:
    """Largest absolute and relative difference between scripted and eager steps on real data:
    one-step predictions from ``steps`` ground-truth states of the first trajectory and from the
    states of the eager model's own ``steps``-step rollout from its initial state (states off the
    data, as in serving), with the TorchScript graph executor's optimisation on and off
    (``torch.jit.optimized_execution``; ``modes``: those of the two to check). Relative: per state
    column, divided by the largest magnitude of that column over all the compared states (a
    linear-prior model's carried remainder G: at least the largest load). Both sides step from
    the same state: comparing two free rollouts would measure how fast the model amplifies
    round-off (an undertrained float32 model: 100x per step), not the export. States are made steppable by the eager ``begin`` (a linear-prior
    model's carried state)."""
    dtype = eager.z0.dtype
    names = ds.ok_names or ds.names
    traj = ds.read(names[0])
    z = torch.as_tensor(traj.z, dtype=dtype)
    f = torch.as_tensor(traj.force, dtype=dtype)
    n = min(steps, z.shape[0] - 1)
    pairs = []                                           # (eager, scripted) states [N, D]
    for optimize in modes:
        with torch.jit.optimized_execution(optimize):
            za = eager.begin(z[0], f[0])
            for s in range(n):
                zs = eager.begin(z[s], f[s])
                pairs += [(eager(zs, f[s + 1]), scripted(zs, f[s + 1])), (zs, scripted.begin(z[s], f[s]))]
                za, zb = eager(za, f[s + 1]), scripted(za, f[s + 1])
                pairs.append((za, zb))
    # [D]: each column's largest magnitude over all compared states (a column may be exactly zero
    # in one of them, e.g. a carried G at rest)
    scale = torch.stack([a.abs().amax(0) for a, _ in pairs]).amax(0)
    if isinstance(eager, ExportedLinearPrior):
        # the carried remainder G [N] is a force: measured against the loads, not its own size (the law
        # prior's learned G is ~1e-10 N, whose float32 round-off is 1e-4 of itself)
        D = int(eager.core.dim)
        scale[D + 3:D + 6] = torch.maximum(scale[D + 3:D + 6], f.abs().max())
    scale = scale.clamp(min=torch.finfo(dtype).tiny)
    max_abs = max(float((a - b).abs().max()) for a, b in pairs)
    max_rel = max(float(((a - b).abs() / scale).max()) for a, b in pairs)
    return max_abs, max_rel


#: steps timed each way by ``step_times`` (after as many warm-up steps)
TIMED_STEPS = 7


def step_times(path, ds: Dataset, optimized=None, modes: tuple[bool, ...] = (False, True)) -> tuple[float, float]:
    """Median wall time (ms) of one step of the exported file ``path`` along a rollout of the
    first trajectory, each step from the last one's state under the trajectory's next load (as
    serve steps it: a step from the state just timed would time what a model keeps of its last
    start, as the law prior keeps its tangent's factors, not a step), with the TorchScript graph
    executor's optimisation off and on (``torch.jit.optimized_execution``), each on a copy
    loaded from ``path`` as a user loads it (the executor keeps the plan it made first); with
    optimisation on, ``optimized`` where given: such a copy that has already made its optimised
    plan (``export``'s parity check), which the executor keeps (making it took the law prior's
    step of the tiny block 25 s of the export's 60, session 87); ``modes``: which of the two
    to time (NaN for the other: ``train.export_optimized=false``). Off is how serve steps the model:
    on, the profiling executor re-optimises the autograd graph the step differentiates, and the
    TIGNN beam's step took about 2x as long (docs/stages.md). A rollout that stops (the law prior
    refuses a non-finite state) starts again from the first state."""
    traj = ds.read((ds.ok_names or ds.names)[0])
    S = traj.force.shape[0]
    times = []
    for optimize in (False, True):
        if optimize not in modes:
            times.append(math.nan)
            continue
        module = optimized if optimize and optimized is not None else torch.jit.load(str(path), map_location="cpu")
        dtype = module.z0.dtype
        forces = [torch.as_tensor(traj.force[k % S], dtype=dtype) for k in range(2 * TIMED_STEPS + 1)]
        with torch.jit.optimized_execution(optimize):
            start = module.begin(torch.as_tensor(traj.z[0], dtype=dtype), forces[0])
            z, ts = start, []
            for k in range(1, 2 * TIMED_STEPS + 1):     # the first half warms up (the executor specialises)
                t0 = time.perf_counter()
                try:
                    z = module(z, forces[k])
                except RuntimeError:
                    z = start
                    continue
                if k > TIMED_STEPS:
                    ts.append(time.perf_counter() - t0)
        times.append(1e3 * statistics.median(ts or [math.nan]))
    return times[0], times[1]


def served_rollout(cfg, ckpt: dict, ds: Dataset | None = None):
    """``cfg`` with ``rollout.prior_hht`` set to the scene's ``served_hht`` where a law model would
    otherwise be exported at its data's undamped rule (``served_law_hht``; ``rollout.prior_hht`` and
    ``rollout.prior_rule`` null), and a line saying so ("" where nothing changed, a note where the
    scene's rule does not apply). ``rollout.prior_hht=0`` keeps the data's rule."""
    if (OmegaConf.select(cfg, "rollout.prior_hht", default=None) is not None
            or OmegaConf.select(cfg, "rollout.prior_rule", default=None) is not None):
        return cfg, ""
    h, note = served_law_hht(ckpt, OmegaConf.select(cfg, "scene", default=None), ds)
    if h is None:
        return cfg, (f"{note}: exported at its data's rule" if note else "")
    served = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    OmegaConf.update(served, "rollout.prior_hht", h, force_add=True)
    return served, (f"scene '{ckpt.get('scene')}' serves its law with HHT's dissipation α = -{h:g} "
                    f"(scene.time.served_hht: under minutes of pressing the data's undamped rule rang the body up; "
                    f"rollout.prior_hht=0 exports the data's rule)")


def served_step(cfg, ckpt: dict):
    """``cfg`` with the ``rollout.prior_*`` keys of ``served_law_settings`` set (a law model iterated
    to a tolerance: its tangent kept, its chord updates Anderson-mixed, its updates line-searched, a
    looser tolerance tightened to 1e-7), and a line saying so ("" where nothing changed) with the overrides that export the step
    as trained."""
    want = served_law_settings(ckpt, cfg)
    if not want:
        return cfg, ""
    served = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    for key, value in want.items():
        OmegaConf.update(served, f"rollout.{key}", value, force_add=True)
    law = ckpt["prior"]
    trained = {"prior_tangent": law.get("law_tangent") or "fresh", "prior_line_search": law.get("law_search") or 0,
               "prior_newton_rtol": law.get("law_rtol"), "prior_newton_max": law.get("law_max"),
               "prior_anderson": law.get("law_anderson") or 0}

    def overrides(values: dict) -> str:                 # as typed on the command line
        return " ".join(f"rollout.{k}={v:g}" if isinstance(v, float) else f"rollout.{k}={v}" for k, v in values.items())

    said, undo = overrides(want), overrides({k: trained[k] for k in want})
    return served, (f"a law iterated to a tolerance is served with {said} (its steps converged as before, faster, "
                    f"and uncut after a sudden release: docs/stages.md; {undo} exports the step as trained)")


def export(cfg) -> Path:
    """Load ``cfg.paths.checkpoint``, script it with the dataset's mesh, verify it against the
    eager model and write ``cfg.paths.exported`` atomically."""
    torch.set_num_threads(int(OmegaConf.select(cfg, "train.threads", default=2)))
    ckpt_path = project_path(cfg.paths.checkpoint)
    ckpt = load_checkpoint(ckpt_path)
    ds = Dataset(project_path(cfg.paths.dataset))
    check_fingerprint(ckpt["fingerprint"], ds, ckpt_path)
    cfg, served = served_rollout(cfg, ckpt, ds)
    if served:
        print(f"export: {served}")
    cfg, step = served_step(cfg, ckpt)
    if step:
        print(f"export: {step}")
    ckpt, stepped = with_rollout(ckpt, cfg)
    if stepped:
        print(f"export: stepping the trained model with {stepped}")
    law = ckpt.get("prior") or {}
    if law_iterates(law) and not law.get("law_cuts"):
        print(f"export: note: a law step whose {int(law['law_max'])} Newton iterations run out before it converges "
              f"is taken as it stands (serve warns when one is); rollout.prior_step_cuts=4 halves it as the FE "
              f"does, which held the liver under the sim's default press (docs/accuracy.md, session 78)")
    eager = build_exported(ckpt, ds)
    scripted = script(eager)
    dtype = torch_dtype(ckpt["dtype"])
    rtol = OmegaConf.select(cfg, "train.export_rtol", default=None)
    rtol = DEFAULT_RTOL[dtype] if rtol is None else float(rtol)
    optimized = OmegaConf.select(cfg, "train.export_optimized", default=True)
    if not isinstance(optimized, bool):
        raise ConfigError(f"train.export_optimized = {optimized!r}, expected true | false (whether export also checks "
                          f"and times the step with TorchScript's graph-executor optimisation on)")
    out = project_path(cfg.paths.exported)
    internal = eager.core.carried_columns() if isinstance(eager, ExportedLinearPrior) else []
    forget = getattr(scripted.core.prior, "forget", None) if isinstance(eager, ExportedLinearPrior) else None
    if forget is not None:              # the law prior's kept step start (its factors): not for the file
        forget()
    with atomic_path(out) as tmp:       # written to a temporary file; ``out`` only once all checks pass
        torch.jit.save(scripted, str(tmp), _extra_files={META_FILE: metadata(ckpt, internal, data_time_record(ds))})
        verify(tmp)
        # the file as a user loads it against the eager model; with its optimised plan made here,
        # once, and kept for the timing below (the law prior's: 25 s of the tiny block's export)
        loaded = torch.jit.load(str(tmp), map_location="cpu")
        modes = (True, False) if optimized else (False,)
        max_abs, max_rel = parity(eager, loaded, ds, modes=modes)
        print(f"export: scripted vs eager on {ds.path.name}: max abs diff {max_abs:.3e}, "
              f"max rel diff {max_rel:.3e} (tolerance {rtol:.1e})"
              + ("" if optimized else ", the graph executor's optimisation off only (train.export_optimized=false)"))
        if not max_rel <= rtol:
            raise DataError(f"{ckpt_path}: TorchScript export differs from the eager model by {max_rel:.3e} "
                            f"(relative), above train.export_rtol = {rtol:.1e}")
        off, on = step_times(tmp, ds, optimized=loaded, modes=modes)
    print(f"export: a step of the exported model takes {off:.1f} ms with the graph executor's optimisation "
          f"off (torch.jit.optimized_execution(False), as serve steps it), "
          + (f"{on:.1f} ms with it on (each" if optimized else "not timed with it on (train.export_optimized=false;")
          + f" on a copy loaded from the file, stepping a rollout; median of {TIMED_STEPS}, "
            f"{torch.get_num_threads()} threads)")
    print(f"export: wrote {out} ({ckpt['structure']}, {ckpt['dtype']}, {eager.z0.shape[0]} nodes)")
    return out


def verify(path) -> dict:
    """Load an exported file with plain torch.jit.load and check the contract; returns the metadata."""
    extra = {META_FILE: ""}
    try:
        m = torch.jit.load(str(path), map_location="cpu", _extra_files=extra)
    except Exception as exc:  # noqa: BLE001
        raise DataError(f"{path}: not a loadable TorchScript file ({type(exc).__name__})") from None
    meta = json.loads(extra[META_FILE] or "{}")
    if meta.get("format") != FORMAT:
        raise DataError(f"{path}: metadata format {meta.get('format')!r}, expected {FORMAT!r}")
    for name in ("reference_positions", "z0", "edge_index", "node_type", "surface_faces", "dt"):
        if not hasattr(m, name):
            raise DataError(f"{path}: exported module lacks buffer '{name}'")
    for name in ("energy_entropy", "begin"):
        if not hasattr(m, name):
            raise DataError(f"{path}: exported module lacks method '{name}'")
    return meta
