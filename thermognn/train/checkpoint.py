"""Checkpoints: everything needed to rebuild, evaluate, export or resume a trained model.

A checkpoint is a ``torch.save``d dict of plain types and tensors (loadable with
``weights_only=True``)::

    format        "thermognn-checkpoint/1"
    hparams       TIGNN constructor arguments (see ``model.hyperparameters``)
    dtype         "float32" | "float64"
    state_dict    model weights and normalisation buffers
    stats         normalisation statistics {name: tensor} (training split only)
    state_layout  JSON string, dt [s], effects (list), structure ("generic" | "hamiltonian"), scene
    config        resolved config YAML, versions JSON, dataset (path), fingerprint (dict), split (dict)
    epoch, val_error   (validation rollout error, ``rollout.validation_error``, of the stress it
                  reports: with a stress readout fitted after training, read off by that readout)
    prior         (only with ``model.prior=linear``) {"kind", "sweeps", "positions_only"} and
                  "order" when 2 (``model.prior_order``), "relax" when true
                  (``model.prior_relax``), "corotated" (rotation sweeps, ``model.prior_corotated``),
                  "stress": "material" (``model.prior_stress``), "law" (Newton iterations a step,
                  ``model.prior_law``), "inputs": "correction" (``model.prior_inputs``), "remainders": "zero"
                  (set by ``rollout.remainders``, never trained so): the weights are a
                  ``hybrid.LinearPriorModel``'s; its operators come from the dataset
    (the ``last`` checkpoint adds optimizer, scheduler, rng, history, best_val, stale_rounds)
"""

from __future__ import annotations

import re

from pathlib import Path

import torch

from thermognn.core.errors import DataError
from thermognn.core.io import atomic_path
from thermognn.core.state import law_iterates

FORMAT = "thermognn-checkpoint/1"
REQUIRED = ("hparams", "dtype", "state_dict", "stats", "state_layout", "dt", "structure", "fingerprint")


def last_path(best: str | Path) -> Path:
    """The resumable checkpoint beside the best one: model.ckpt -> model.last.ckpt."""
    best = Path(best)
    return best.with_name(best.stem + ".last" + best.suffix)


def on_cpu(obj):
    """``obj`` with every tensor in it (in dicts, lists and tuples) moved to the CPU."""
    if isinstance(obj, torch.Tensor):
        return obj.detach().cpu() if obj.device.type != "cpu" else obj
    if isinstance(obj, dict):
        out = type(obj)((k, on_cpu(v)) for k, v in obj.items())
        if hasattr(obj, "_metadata"):            # a module state_dict's versions
            out._metadata = obj._metadata
        return out
    if isinstance(obj, tuple) and hasattr(obj, "_fields"):
        return type(obj)(*(on_cpu(v) for v in obj))
    if isinstance(obj, (list, tuple)):
        return type(obj)(on_cpu(v) for v in obj)
    return obj


def save_checkpoint(ckpt: dict, path: str | Path) -> Path:
    """Write atomically (a crash never leaves a half-written checkpoint), with CPU tensors only:
    a model trained on a GPU (``train.device``) loads on a machine without one. The ``_path`` that
    ``load_checkpoint`` adds is not written."""
    path = Path(path)
    with atomic_path(path) as tmp:
        torch.save(on_cpu({k: v for k, v in ckpt.items() if k != "_path"}), tmp)
    return path


def load_checkpoint(path: str | Path) -> dict:
    """Load and validate; DataError (one line) when missing, unreadable or incomplete."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: checkpoint not found (run `thermognn train` first)")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means a corrupt file
        raise DataError(f"{path}: not a readable thermognn checkpoint ({type(exc).__name__})") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise DataError(f"{path}: not a thermognn checkpoint (expected format '{FORMAT}')")
    missing = [k for k in REQUIRED if k not in ckpt]
    if missing:
        raise DataError(f"{path}: checkpoint lacks {missing}")
    ckpt["_path"] = str(path)  # for error messages; not saved
    return ckpt


def torch_dtype(name: str) -> torch.dtype:
    if name not in ("float32", "float64"):
        raise DataError(f"model.dtype = {name!r}, expected float32 or float64")
    return torch.float32 if name == "float32" else torch.float64


def model_from_checkpoint(ckpt: dict, dataset=None):
    """Rebuild the eager model (weights and normalisation loaded): the TIGNN, or for a checkpoint
    with a ``prior`` (``model.prior=linear``) the LinearPriorModel around it, whose linearised FE
    operators come from ``dataset`` (a ``Dataset``; default: the checkpoint's own dataset path),
    anchored (its remainders at the unloaded reference state subtracted, ``LinearPriorModel.anchor``)."""
    from .model import build_model

    model = build_model(dict(ckpt["hparams"]), torch_dtype(ckpt["dtype"]))
    if ckpt.get("prior"):
        from thermognn.core.schema import Dataset

        from .hybrid import prior_model

        if dataset is None:
            dataset = Dataset(ckpt.get("dataset", ""))
        model = prior_model(model, dict(ckpt["prior"]), dataset, float(ckpt["dt"]))
    try:
        model.load_state_dict(ckpt["state_dict"])
    except (RuntimeError, KeyError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DataError(f"{ckpt.get('_path', 'checkpoint')}: weights do not fit the model they describe "
                        f"(written by another thermognn version?): {first}") from None
    if ckpt.get("prior"):                 # remainders zero at the unloaded reference state
        from .data import load_graph

        graph = load_graph(dataset, torch_dtype(ckpt["dtype"]))
        model.anchor(graph.edge_index, graph.node_type, graph.ref_pos)
    return model


#: how a trained model is stepped, overridable at evaluate and export time (``rollout.<key>``)
ROLLOUT_KEYS = ("integrator", "implicit_iterations", "kinematics")
#: ... and how a law-prior model's law is stepped (``rollout.<key>``, as ``model.<key>``)
LAW_ROLLOUT_KEYS = ("prior_newton", "prior_newton_max", "prior_newton_rtol", "prior_step_cuts", "prior_tangent",
                    "prior_line_search", "prior_cut_loads", "prior_rule", "prior_hht", "prior_substeps",
                    "prior_anderson")


def law_phrase(prior: dict) -> str:
    """How a law prior's settings step its law, in a few words: "1 to 16 Newton iterations to
    1e-07, cut down to Δt/16, its tangent kept"."""
    k, most = int(prior["law"]), int(prior.get("law_max", prior["law"]))
    text = (f"{k} to {most} Newton iterations to {float(prior['law_rtol']):g}" if most > k
            else f"{k} Newton iteration{'s' if k > 1 else ''}")
    if int(prior.get("law_substeps", 1)) > 1:
        text = f"{int(prior['law_substeps'])} sub-steps a step (loaded between its loads), each {text}"
    if prior.get("law_cuts"):
        text += f", cut down to Δt/{2 ** int(prior['law_cuts']) * int(prior.get('law_substeps', 1))}"
        text += (", its sub-steps loaded between the step's loads" if prior.get("law_cut_loads") == "linear"
                 and int(prior.get("law_substeps", 1)) == 1 else "")
    text += ", its tangent kept" if prior.get("law_tangent") == "kept" else ""
    text += (f", its chord updates Anderson-mixed with up to {int(prior['law_anderson'])} earlier ones"
             if prior.get("law_anderson") else "")
    text += f", its updates line-searched ({int(prior['law_search'])} halvings)" if prior.get("law_search") else ""
    text += ", the energy rule in time" if prior.get("law_rule") == "energy" else ""
    return text + (f", HHT's dissipation α = -{float(prior['law_hht']):g}" if prior.get("law_hht") else "")


def with_law_rollout(ckpt: dict, want: dict) -> tuple[dict, str]:
    """The law-prior checkpoint with ``rollout.prior_*`` (``want``: LAW_ROLLOUT_KEYS, None: as
    trained) applied to its law's step, validated as ``model.prior_*`` are (``prior_settings``):
    the same network and remainders, the law stepped another way (where the network was fitted to
    the converged law, as by default, any step near convergence keeps its meaning; a network fitted
    to what a fixed budget leaves, ``train.fit_target=budget``, is refused)."""
    from omegaconf import OmegaConf

    from thermognn.core.errors import ConfigError

    from .hybrid import prior_settings

    prior = dict(ckpt["prior"])
    set_keys = ", ".join(f"rollout.{k}" for k, v in want.items() if v is not None)
    if not prior.get("law"):
        raise ConfigError(f"{set_keys}: the checkpoint's prior is not the data's law (model=law_prior); "
                          f"leave them null")
    trained = OmegaConf.create(ckpt.get("config") or "{}")
    if str(OmegaConf.select(trained, "train.fit_target", default="exact")) == "budget":
        raise ConfigError(f"{set_keys}: this model's network was fitted to what its {prior['law']}-iteration "
                          f"budget leaves (train.fit_target=budget), which another step does not leave; "
                          f"leave them null")
    law = {"prior": "linear", "prior_law": True, "prior_newton": prior["law"],
           "prior_newton_max": prior.get("law_max"), "prior_newton_rtol": prior.get("law_rtol"),
           "prior_step_cuts": prior.get("law_cuts", 0), "prior_tangent": prior.get("law_tangent", "fresh"),
           "prior_line_search": prior.get("law_search", 0), "prior_cut_loads": prior.get("law_cut_loads", "end"),
           "prior_rule": prior.get("law_rule", "newmark"), "prior_hht": prior.get("law_hht", 0.0),
           "prior_substeps": prior.get("law_substeps", 1), "prior_anderson": prior.get("law_anderson", 0)}
    law.update({k: v for k, v in want.items() if v is not None})
    try:
        stepped = prior_settings(OmegaConf.create(law))
    except ConfigError as exc:                  # named as they were set
        raise ConfigError(re.sub(r"model\.(" + "|".join(LAW_ROLLOUT_KEYS) + r")\b", r"rollout.\1", str(exc))) from None
    keys = ("law", "law_max", "law_rtol", "law_cuts", "law_tangent", "law_search", "law_cut_loads", "law_rule",
            "law_hht", "law_substeps", "law_anderson")
    new = {**{k: v for k, v in prior.items() if k not in keys}, **{k: stepped[k] for k in keys if k in stepped}}
    if law_phrase(new) == law_phrase(prior):
        return ckpt, ""
    return {**ckpt, "prior": new}, f"the law prior's step {law_phrase(new)} (trained: {law_phrase(prior)})"


def served_law_hht(ckpt: dict, scene=None, ds=None) -> tuple[float | None, str]:
    """The HHT dissipation h (α = −h) a law model is served with where its scene declares one
    (``scene.time.served_hht``, ``thermognn.core.config.scene_served_hht``; ``scene``: a composed
    scene config, used where it is the checkpoint's) and the model is stepped at its data's
    undamped Newmark rule: (h, ""). (None, "") where that does not arise (not a law model, a law
    already damped or on the energy rule, a scene declaring none), and (None, why) where the scene
    declares h but the model cannot take it: data ``ds`` whose rule HHT does not modify
    (stiffness-proportional damping, as the block's), or a network fitted to what its Newton
    budget leaves (``train.fit_target=budget``), which another rule does not leave."""
    from omegaconf import OmegaConf

    from thermognn.core.config import scene_served_hht

    from .law_prior import hht_applies

    law = ckpt.get("prior") or {}
    if not law.get("law") or float(law.get("law_hht", 0.0) or 0.0) or law.get("law_rule", "newmark") != "newmark":
        return None, ""
    h = scene_served_hht(str(ckpt.get("scene", "")), scene)
    if h is None:
        return None, ""
    declared = f"note: scene '{ckpt.get('scene')}' serves its law with HHT's dissipation α = -{h:g} (scene.time.served_hht)"
    linear = ds.linear_solid() if ds is not None else None
    if linear is not None and not hht_applies(float(linear.beta), float(linear.gamma), float(linear.rayleigh[1])):
        return None, (f"{declared}, but its data's rule (β {linear.beta:g}, γ {linear.gamma:g}, βK "
                      f"{linear.rayleigh[1]:g} s) is not the undamped average-acceleration rule HHT modifies")
    trained = OmegaConf.create(ckpt.get("config") or "{}")
    if str(OmegaConf.select(trained, "train.fit_target", default="exact")) == "budget":
        return None, (f"{declared}, but this model's network was fitted to what its Newton budget leaves "
                      f"(train.fit_target=budget), which another rule does not leave")
    return h, ""


#: how ``export`` steps a law model whose law iterates to a tolerance where neither its checkpoint
#: nor the command line (``rollout.prior_*``) sets these: its tangent kept between chord updates, its
#: Newton updates line-searched, and a looser tolerance tightened to 1e-7 with 16 updates at most, as
#: a chord stops further from the solution than Newton's method at the same tolerance (the shell's
#: 1e-4 kept: q 1.6e-4 from its fresh FE cases against 1.2e-6; at 1e-7, 1.2e-6 and 1.6x faster; the
#: float32 states an exported model carries round at about 6e-8, so a tighter one buys serve
#: nothing). ``served_law_step``; docs/accuracy.md, session 97: under the sim press the bunny's fresh,
#: unsearched step took 2.1 s a step and cut steps for up to 16 s after the tool's release, kept and
#: searched 0.39 s and none; and its chord updates Anderson-mixed with the last 2 (session 102: the
#: liver's body under the press 1.29x faster by the median step, 1.43x by the mean; the bunny's
#: 1.17x by the mean; the shell's as fast)
SERVED_LAW_STEP = {"prior_tangent": "kept", "prior_line_search": 6, "prior_newton_rtol": 1e-7, "prior_newton_max": 16,
                   "prior_anderson": 2}


def served_law_step(ckpt: dict) -> dict:
    """The ``rollout.prior_*`` settings (SERVED_LAW_STEP's) a law model is served with beyond its
    checkpoint's: {} where none apply (not a law model, a fixed Newton budget, which the step's
    settings would change, a network fitted to its budget's misses, or a checkpoint that already
    keeps its tangent to 1e-7, mixes its chord updates and searches). A converged step stays where it was (within the
    tolerance); what they change is how fast, and whether a step after a sudden release converges
    at all."""
    from omegaconf import OmegaConf

    law = ckpt.get("prior") or {}
    if not law_iterates(law):
        return {}
    trained = OmegaConf.create(ckpt.get("config") or "{}")
    if str(OmegaConf.select(trained, "train.fit_target", default="exact")) == "budget":
        return {}
    want = {}
    if (law.get("law_tangent") or "fresh") == "fresh":
        want["prior_tangent"] = SERVED_LAW_STEP["prior_tangent"]
    if not law.get("law_anderson"):
        want["prior_anderson"] = SERVED_LAW_STEP["prior_anderson"]
    if not law.get("law_search"):
        want["prior_line_search"] = SERVED_LAW_STEP["prior_line_search"]
    if float(law.get("law_rtol") or 0.0) > SERVED_LAW_STEP["prior_newton_rtol"]:
        want["prior_newton_rtol"] = SERVED_LAW_STEP["prior_newton_rtol"]
        want["prior_newton_max"] = max(int(law["law_max"]), SERVED_LAW_STEP["prior_newton_max"])
    return want


def served_law_settings(ckpt: dict, cfg) -> dict:
    """The ``served_law_step`` settings for a checkpoint as trained (``ckpt``) stepped as ``cfg``'s
    ``rollout.*`` says: the keys the command line leaves null, where the step so is still a law
    iterated to a tolerance (a fixed budget the command line made iterate keeps its step); the
    tolerance tightened only where the served tangent is kept and the command line sets neither
    ``rollout.prior_newton_rtol`` nor ``rollout.prior_newton_max``. What ``export`` serves and
    ``evaluate`` rolls out as served."""
    from omegaconf import OmegaConf

    offered = served_law_step(ckpt)
    if not offered:
        return {}

    def given(key: str) -> bool:
        return OmegaConf.select(cfg, f"rollout.{key}", default=None) is not None

    # the step as the command line makes it, but for the mixing it asks for, which needs the
    # kept tangent this may give it (rollout.prior_anderson=3 alone on a law trained fresh)
    unmixed = cfg
    if given("prior_anderson"):
        unmixed = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
        OmegaConf.update(unmixed, "rollout.prior_anderson", None, force_add=True)
    stepped, _ = with_rollout(ckpt, unmixed)
    still = served_law_step(stepped)

    want = {k: offered[k] for k in ("prior_tangent", "prior_line_search") if k in offered and k in still and not given(k)}
    kept = (want.get("prior_tangent") or stepped["prior"].get("law_tangent")) == "kept"
    if kept and "prior_anderson" in offered and "prior_anderson" in still and not given("prior_anderson"):
        want["prior_anderson"] = offered["prior_anderson"]
    if (kept and "prior_newton_rtol" in offered and "prior_newton_rtol" in still and not given("prior_newton_rtol")
            and not given("prior_newton_max")):
        want["prior_newton_rtol"], want["prior_newton_max"] = offered["prior_newton_rtol"], offered["prior_newton_max"]
    return want


#: ``rollout.remainders`` values: the network's remainders (as trained) | zero (G = H = 0, the prior alone)
REMAINDERS = ("learned", "zero")


def with_remainders(ckpt: dict, want) -> tuple[dict, str]:
    """The prior checkpoint with ``rollout.remainders`` (``want``: "learned" | "zero", None: as
    trained) applied: "zero" steps the prior alone, the network's remainders G = H = 0 and the
    network not evaluated (a law prior: the data's law at its Newton budget, the FE model
    itself), so that a rollout beside the model as trained shows what its network adds."""
    from thermognn.core.errors import ConfigError

    if want is None:
        return ckpt, ""
    want = str(want)
    if want not in REMAINDERS:
        raise ConfigError(f"rollout.remainders = '{want}', expected " + " | ".join(REMAINDERS))
    if not ckpt.get("prior"):
        raise ConfigError(f"rollout.remainders = {want}: only a model.prior=linear model (linear_prior, "
                          f"law_prior) has remainders; leave it null")
    if want == "learned":                        # as every model is trained
        if ckpt["prior"].get("remainders") == "zero":
            raise ConfigError(f"rollout.remainders = learned: {ckpt.get('_path', 'the checkpoint')} is the prior "
                              f"alone (train.prior_alone_candidate: no epoch beat it, or none ran); its network "
                              f"was not trained (the last epoch's, if any, is in model.last.ckpt)")
        return ckpt, ""
    return {**ckpt, "prior": {**ckpt["prior"], "remainders": "zero"}}, \
        "its remainders zero, the prior alone (trained: learned)"


def with_rollout(ckpt: dict, cfg) -> tuple[dict, str]:
    """The checkpoint with the ``rollout`` config group applied to its time step: the integrator,
    its sweeps and the kinematics of the same learned dz/dt, or a law-prior model's law step
    (``rollout.prior_*``, ``with_law_rollout``; null: as trained). Returns the changed copy and a
    note for reports, e.g. "integrator midpoint (trained: euler)", or "" when nothing changed."""
    from omegaconf import OmegaConf

    from .model import step_settings, stepping

    ckpt, zero_note = with_remainders(ckpt, OmegaConf.select(cfg, "rollout.remainders", default=None))
    law = {k: OmegaConf.select(cfg, f"rollout.{k}", default=None) for k in LAW_ROLLOUT_KEYS}
    if any(v is not None for v in law.values()):
        if not ckpt.get("prior"):
            from thermognn.core.errors import ConfigError

            set_keys = ", ".join(f"rollout.{k}" for k, v in law.items() if v is not None)
            raise ConfigError(f"{set_keys}: only a model=law_prior model steps the data's law; leave them null")
        ckpt, law_note = with_law_rollout(ckpt, law)
    else:
        law_note = ""
    law_note = ", ".join(n for n in (law_note, zero_note) if n)
    want = {k: OmegaConf.select(cfg, f"rollout.{k}", default=None) for k in ROLLOUT_KEYS}
    if all(v is None for v in want.values()):
        return ckpt, law_note
    if ckpt.get("prior"):
        from thermognn.core.errors import ConfigError

        set_keys = ", ".join(f"rollout.{k}" for k, v in want.items() if v is not None)
        raise ConfigError(f"{set_keys}: a model.prior=linear model steps with the data's own Newmark rule "
                          f"(model.prior_sweeps sets its network calls); leave rollout.* null")
    hparams = stepping(ckpt["hparams"], **want)
    old, new = step_settings(ckpt["hparams"]), step_settings(hparams)
    changes = []
    if new["integrator"] != old["integrator"]:
        changes.append(f"integrator {new['integrator']} (trained: {old['integrator']})")
    if new["integrator"] == "midpoint" and new["implicit_iterations"] != old["implicit_iterations"]:
        changes.append(f"{new['implicit_iterations']} midpoint sweeps (trained: {old['implicit_iterations']})")
    if new["kinematics"] != old["kinematics"]:
        changes.append(f"{new['kinematics']} kinematics (trained: {old['kinematics']})")
    return {**ckpt, "hparams": hparams}, ", ".join(changes)


def model_step(ckpt: dict) -> dict:
    """How the checkpoint's model steps (``step`` metadata of exported files, ``describe_step``):
    the TIGNN's ``step_settings``, or for a linear-prior model {"integrator": "newmark",
    "prior": "linear", "sweeps": network calls per step, "kinematics": "exact"} (and "order": 2
    for second-order remainders, "corotated": the rotation sweeps of a corotated prior, "stress":
    "material" where its stress is the material's law, "law": the Newton iterations a step of the
    law prior, "law_max": the most it takes where a step has not converged, "law_rtol": to what,
    "law_cuts": how many times a step that still has not is halved, "law_tangent": "kept" where its
    tangent is kept between iterations and steps, "law_anderson": how many earlier chord updates a
    kept tangent's update is mixed with, "law_search": the halvings of its line search,
    "law_cut_loads": "linear" where a cut step's sub-steps are loaded between the step's loads,
    "law_substeps": how many sub-steps every step is taken as (``rollout.prior_substeps``),
    "law_rule": "energy" where the trapezoid is corrected by its step potential's discrete gradient,
    "law_hht": h where the step is HHT's with α = −h (``rollout.prior_hht``, ``scene.time.served_hht``),
    "law_material": "learned" where the law is a strain energy learned from the data, "remainders": "zero" where the prior steps alone,
    ``rollout.remainders`` or ``train.prior_alone_candidate``)."""
    from .model import step_settings

    prior = ckpt.get("prior")
    if prior:
        return {"integrator": "newmark", "prior": str(prior.get("kind", "linear")),
                "sweeps": int(prior.get("sweeps", 1)), "kinematics": "exact",
                **({"order": 2} if int(prior.get("order", 1)) == 2 else {}),
                **({"corotated": int(prior["corotated"])} if prior.get("corotated") else {}),
                **({"stress": "material"} if prior.get("stress") == "material" else {}),
                **({"law": int(prior["law"])} if prior.get("law") else {}),
                **({"law_material": "learned"} if prior.get("law_material") == "learned" else {}),
                **({"law_max": int(prior["law_max"])} if prior.get("law_max") else {}),
                **({"law_rtol": float(prior["law_rtol"])} if prior.get("law_rtol") else {}),
                **({"law_cuts": int(prior["law_cuts"])} if prior.get("law_cuts") else {}),
                **({"law_tangent": str(prior["law_tangent"])} if prior.get("law_tangent") else {}),
                **({"law_anderson": int(prior["law_anderson"])} if prior.get("law_anderson") else {}),
                **({"law_search": int(prior["law_search"])} if prior.get("law_search") else {}),
                **({"law_cut_loads": "linear"} if prior.get("law_cut_loads") == "linear" else {}),
                **({"law_substeps": int(prior["law_substeps"])} if int(prior.get("law_substeps", 1)) > 1 else {}),
                **({"law_rule": "energy"} if prior.get("law_rule") == "energy" else {}),
                **({"law_hht": float(prior["law_hht"])} if float(prior.get("law_hht", 0.0) or 0.0) else {}),
                **({"remainders": "zero"} if prior.get("remainders") == "zero" else {})}
    return step_settings(ckpt.get("hparams", {}))
