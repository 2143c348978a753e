"""Export: TorchScript contract (docs/stages.md), parity with the eager model, errors, imports."""

import json
import subprocess
import sys

import pytest
import torch

from thermognn.core.config import load_config
from thermognn.core.errors import DataError
from thermognn.export import export
from thermognn.train import train
from thermognn.train.checkpoint import load_checkpoint, model_from_checkpoint
from thermognn.train.synthetic import write_oscillator_dataset

SMALL = ["train.threads=1", "model.hidden=16", "model.message_passing=2", "train.epochs=2", "train.batch_size=4"]


@pytest.fixture(scope="module", params=["float32", "float64"])
def exported(request, tmp_path_factory):
    out = tmp_path_factory.mktemp(f"export_{request.param}")
    write_oscillator_dataset(out / "dataset.h5", n_trajectories=4, steps=5, viscous=True)
    cfg = load_config([f"out={out}", *SMALL, f"model.dtype={request.param}"])
    train(cfg)
    return out, cfg, export(cfg)


def test_contract_buffers_methods_and_metadata(exported):
    out, cfg, path = exported
    extra = {"thermognn.json": ""}
    m = torch.jit.load(str(path), _extra_files=extra)
    meta = json.loads(extra["thermognn.json"])
    assert set(meta) >= {"format", "scene", "effects", "state_layout", "dt", "structure", "config", "versions"}
    assert meta["format"] == "thermognn-model/1" and meta["structure"] == "generic"
    assert json.loads(meta["state_layout"]) == [["q", 3], ["v", 3], ["sigma", 6]]
    from thermognn.core.state import describe_time_error

    assert "data_time_error" not in meta           # (synthetic data: no FE time step to check; test_pipeline's has)
    assert describe_time_error({"substeps": 4, "fine_substeps": 8, "u": 7.9e-4, "v": 0.0263, "sigma": 3.4e-3}) == (
        "u 0.079 %, v 2.6 %, σ 0.34 % (the data, 4 FE steps a stored step, against the FE at 8; generate's check)")
    assert describe_time_error(None) == ""
    dtype = torch.float32 if cfg.model.dtype == "float32" else torch.float64
    n = 27
    assert m.reference_positions.shape == (n, 3) and m.reference_positions.dtype == dtype
    assert m.z0.shape == (n, 12) and m.z0.dtype == dtype
    assert m.edge_index.dtype == torch.int64 and m.edge_index.shape[0] == 2
    assert m.node_type.shape == (n,) and m.node_type.dtype == torch.int64
    assert m.surface_faces.dtype == torch.int64 and m.surface_faces.shape[1] == 3 and m.surface_faces.shape[0] > 0
    assert m.dt.dim() == 0 and abs(float(m.dt) - meta["dt"]) < 1e-9
    z1 = m(m.z0, torch.zeros(n, 3, dtype=dtype))
    assert z1.shape == (n, 12) and z1.dtype == dtype and torch.isfinite(z1).all()
    clamped = m.node_type == 1
    assert torch.equal(z1[clamped, :3], m.reference_positions[clamped])
    e, s = m.energy_entropy(m.z0)
    assert e.dim() == 0 and s.dim() == 0
    assert torch.equal(m.report(z1), z1)                 # no stress readout: the state as stepped


def test_parity_with_eager_model(exported):
    out, cfg, path = exported
    m = torch.jit.load(str(path))
    core = model_from_checkpoint(load_checkpoint(out / "model.ckpt"))
    dtype = m.z0.dtype
    g = torch.Generator().manual_seed(0)
    z = m.z0.clone()
    f = 0.1 * torch.randn(z.shape[0], 3, generator=g, dtype=dtype)
    for _ in range(3):
        a = m(z, f)
        b = core.step(z, f, m.edge_index, m.node_type, m.reference_positions, m.dt)
        scale = b.abs().amax(0).clamp(min=1e-30)
        assert float(((a - b).abs() / scale).max()) < (1e-4 if dtype == torch.float32 else 1e-10)
        z = a


def test_export_times_the_scripted_step_with_the_optimisation_off_and_on(exported, capsys):
    """``export`` prints a scripted step's time both ways (serve steps it with the graph
    executor's optimisation off), each a positive median in ms, along a rollout."""
    import re

    out, cfg, path = exported
    export(cfg)
    lines = [ln for ln in capsys.readouterr().out.splitlines() if "a step of the exported model takes" in ln]
    assert len(lines) == 1 and "optimized_execution(False), as serve steps it" in lines[0]
    assert "stepping a rollout" in lines[0]         # each step from the last one's state, as serve steps
    off, on = (float(x) for x in re.findall(r"takes ([0-9.]+) ms .* ([0-9.]+) ms with it on", lines[0])[0])
    assert off > 0 and on > 0
    # train.export_optimized=false: checked and timed with the optimisation off only (as serve
    # steps it), and says so; anything but a boolean is refused in one line
    from omegaconf import OmegaConf

    from thermognn.core.errors import ConfigError

    off_only = OmegaConf.merge(cfg, {"train": {"export_optimized": False}})
    assert torch.jit.load(str(export(off_only))).z0.shape == (27, 12)
    said = capsys.readouterr().out
    assert "the graph executor's optimisation off only (train.export_optimized=false)" in said
    line = [ln for ln in said.splitlines() if "a step of the exported model takes" in ln][0]
    assert "not timed with it on (train.export_optimized=false;" in line and "nan" not in line
    assert float(re.findall(r"takes ([0-9.]+) ms", line)[0]) > 0
    with pytest.raises(ConfigError, match=r"^train.export_optimized = 'no', expected true \| false") as err:
        export(OmegaConf.merge(cfg, {"train": {"export_optimized": "no"}}))
    assert "\n" not in str(err.value)


def test_loads_with_torch_only(exported):
    out, cfg, path = exported
    code = ("import sys, torch\n"
            f"m = torch.jit.load({str(path)!r})\n"
            "z = m(m.z0, torch.zeros(m.z0.shape[0], 3, dtype=m.z0.dtype))\n"
            "assert not any(k.startswith('thermognn') for k in sys.modules), 'thermognn imported'\n"
            "print(tuple(z.shape))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd="/")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "(27, 12)" in r.stdout


def test_export_rejects_mismatched_dataset(exported, tmp_path):
    out, cfg, path = exported
    write_oscillator_dataset(tmp_path / "other.h5", n_trajectories=2, steps=3, shape=(3, 3, 4), viscous=True)
    cfg2 = load_config([f"out={tmp_path}", f"paths.checkpoint={out / 'model.ckpt'}",
                        f"paths.dataset={tmp_path / 'other.h5'}"])
    with pytest.raises(DataError) as err:
        export(cfg2)
    assert "\n" not in str(err.value) and "other.h5" in str(err.value)
    assert not (tmp_path / "model.pt").exists()


def test_export_missing_checkpoint(tmp_path):
    cfg = load_config([f"out={tmp_path}"])
    with pytest.raises(DataError, match="not found"):
        export(cfg)




def test_export_graph_only_dataset_has_empty_surface(tmp_path):
    """Imported datasets (e.g. the TIGNN beam) have graph edges but no tets: no surface faces."""
    write_oscillator_dataset(tmp_path / "dataset.h5", n_trajectories=3, steps=3, with_tets=False)
    cfg = load_config([f"out={tmp_path}", *SMALL, "train.epochs=1"])
    train(cfg)
    m = torch.jit.load(str(export(cfg)))
    assert m.surface_faces.shape == (0, 3) and m.surface_faces.dtype == torch.int64
    assert m.edge_index.shape[1] > 0


def test_export_with_another_time_step(exported, tmp_path):
    """``rollout.*`` at export: the file steps by the midpoint rule with exact kinematics, says so
    in its metadata, and matches the eager model stepped the same way."""
    from thermognn.train.model import stepping

    out, cfg, _ = exported
    path = export(load_config([f"out={out}", *SMALL, f"model.dtype={cfg.model.dtype}", f"paths.exported={tmp_path / 'm.pt'}",
                               "rollout.integrator=midpoint", "rollout.implicit_iterations=2", "rollout.kinematics=exact"]))
    extra = {"thermognn.json": ""}
    m = torch.jit.load(str(path), _extra_files=extra)
    assert json.loads(extra["thermognn.json"])["step"] == {"integrator": "midpoint", "implicit_iterations": 2,
                                                           "kinematics": "exact"}
    ckpt = load_checkpoint(out / "model.ckpt")
    plain = {"thermognn.json": ""}
    torch.jit.load(str(out / "model.pt"), _extra_files=plain)           # exported as trained
    assert json.loads(plain["thermognn.json"])["step"]["integrator"] == ckpt["hparams"]["integrator"] == "euler"
    core = model_from_checkpoint({**ckpt, "hparams": stepping(ckpt["hparams"], "midpoint", 2, "exact")})
    f = 0.1 * torch.ones(m.z0.shape[0], 3, dtype=m.z0.dtype)
    a, b = m(m.z0, f), core.step(m.z0, f, m.edge_index, m.node_type, m.reference_positions, m.dt)
    scale = b.abs().amax(0).clamp(min=1e-30)
    assert float(((a - b).abs() / scale).max()) < (1e-4 if m.z0.dtype == torch.float32 else 1e-10)
    free = m.node_type != 1                     # exact kinematics: q_1 = q_0 + dt (v_0 + v_1) / 2
    assert torch.allclose(a[free, :3], m.z0[free, :3] + 0.5 * m.dt * (m.z0[free, 3:6] + a[free, 3:6]),
                          rtol=0, atol=1e-6 if m.z0.dtype == torch.float32 else 1e-12)


def test_a_law_iterated_to_a_tolerance_is_served_with_its_tangent_kept_and_its_updates_searched():
    """``served_law_settings``: export steps a law model whose law iterates to a tolerance with its
    tangent kept, its chord updates Anderson-mixed with the last 2 (session 102), its Newton updates
    line-searched and a looser tolerance tightened to 1e-7 (a chord stops further from the solution
    at the same tolerance) unless the command line says otherwise
    (``rollout.prior_*``, each key on its own) or the checkpoint already does (under the sim press
    the bunny's fresh, unsearched step cut steps for up to 16 s after the tool's release;
    docs/accuracy.md, session 97). A fixed budget keeps its step (the settings would change what it
    leaves), and so does a network fitted to that."""
    from omegaconf import OmegaConf

    from thermognn.export.exporter import served_step
    from thermognn.train.checkpoint import SERVED_LAW_STEP, served_law_settings, served_law_step

    law = {"scene": "bunny", "prior": {"law": 1, "law_max": 16, "law_rtol": 1e-7, "law_cuts": 4}, "config": ""}
    assert served_law_step(law) == {"prior_tangent": "kept", "prior_anderson": 2, "prior_line_search": 6}
    assert SERVED_LAW_STEP["prior_newton_rtol"] == 1e-7 and SERVED_LAW_STEP["prior_newton_max"] == 16
    cfg = load_config([])
    served, note = served_step(cfg, law)
    assert OmegaConf.select(served, "rollout.prior_tangent") == "kept" and cfg.rollout.prior_tangent is None
    assert OmegaConf.select(served, "rollout.prior_line_search") == 6
    assert OmegaConf.select(served, "rollout.prior_anderson") == 2
    assert note.startswith("a law iterated to a tolerance is served with rollout.prior_tangent=kept "
                           "rollout.prior_line_search=6 rollout.prior_anderson=2 (")
    assert ("rollout.prior_tangent=fresh rollout.prior_line_search=0 rollout.prior_anderson=0 exports the step as "
            "trained") in note
    # the command line's choice stands, each key on its own
    fresh = load_config(["rollout.prior_tangent=fresh"])
    served, note = served_step(fresh, law)
    assert served.rollout.prior_tangent == "fresh" and served.rollout.prior_line_search == 6
    assert served.rollout.prior_anderson is None                     # (mixing needs the kept tangent)
    assert "rollout.prior_tangent=kept" not in note and "rollout.prior_line_search=0 exports" in note
    unmixed = load_config(["rollout.prior_anderson=0"])
    assert served_law_settings(law, unmixed) == {"prior_tangent": "kept", "prior_line_search": 6}
    # more mixing asked of a law trained fresh: on the kept tangent export gives it
    from thermognn.train.checkpoint import with_rollout

    more = load_config(["rollout.prior_anderson=3"])
    assert served_law_settings(law, more) == {"prior_tangent": "kept", "prior_line_search": 6}
    assert with_rollout(law, served_step(more, law)[0])[0]["prior"]["law_anderson"] == 3
    chosen = load_config(["rollout.prior_tangent=fresh", "rollout.prior_line_search=0"])
    assert served_step(chosen, law) == (chosen, "")
    # a checkpoint that searches already (the liver's) is given the kept tangent only
    searched = {**law, "prior": {**law["prior"], "law_search": 6}}
    assert served_law_settings(searched, cfg) == {"prior_tangent": "kept", "prior_anderson": 2}
    kept = {**law, "prior": {**law["prior"], "law_search": 6, "law_tangent": "kept"}}
    assert served_law_settings(kept, cfg) == {"prior_anderson": 2}
    assert served_law_settings({**kept, "prior": {**kept["prior"], "law_anderson": 3}}, cfg) == {}
    # a looser tolerance (the shell's 1e-4, 12 at most) is tightened where the tangent is kept, and
    # only where the command line sets neither the tolerance nor the most updates
    loose = {**law, "prior": {**law["prior"], "law_max": 12, "law_rtol": 1e-4}}
    assert served_law_settings(loose, cfg) == {"prior_tangent": "kept", "prior_line_search": 6, "prior_anderson": 2,
                                               "prior_newton_rtol": 1e-7, "prior_newton_max": 16}
    assert "rollout.prior_newton_rtol=0.0001 rollout.prior_newton_max=12 exports" in served_step(cfg, loose)[1]
    assert served_law_settings(loose, fresh) == {"prior_line_search": 6}
    assert served_law_settings(loose, load_config(["rollout.prior_newton_rtol=1e-5"])) == {
        "prior_tangent": "kept", "prior_line_search": 6, "prior_anderson": 2}
    # a fixed budget (trained, or the one the command line iterates), a budget fit and a graph
    # network keep their step
    budget = {**law, "prior": {"law": 2, "law_max": 2}}
    for other in (budget, {**law, "prior": {"law": 1}}, {**law, "prior": None},
                  {**law, "config": "train:\n  fit_target: budget\n"}):
        assert served_law_step(other) == {} and served_step(cfg, other) == (cfg, "")
    iterated = load_config(["rollout.prior_newton_max=8", "rollout.prior_newton_rtol=1e-9"])
    assert served_step(iterated, {**law, "prior": {"law": 1}}) == (iterated, "")


def test_a_scene_declares_the_time_rule_its_law_is_served_with():
    """``scene.time.served_hht``: export steps a law model of a scene that declares it with HHT's
    dissipation unless ``rollout.prior_hht`` or ``rollout.prior_rule`` says otherwise (the liver
    declares one: at its data's undamped rule the served body rang up and collapsed, sessions 94–96).
    The scene is the checkpoint's: read from the command line's scene where it names it, else from
    conf/scene. A graph network, a law already damped or given another rule, and a network fitted
    to its Newton budget's misses keep their rule; a bad value is one line naming the key."""
    from omegaconf import OmegaConf

    from thermognn.core.errors import ConfigError
    from thermognn.export.exporter import served_rollout

    from thermognn.core.config import scene_served_hht

    liver = scene_served_hht("liver")                         # conf/scene/liver.yaml's
    assert liver is not None and 0.0 < liver <= 0.05 and scene_served_hht("shell") is None
    law = {"scene": "liver", "prior": {"law": 1, "law_max": 16, "law_rtol": 1e-7}, "config": ""}
    cfg = load_config([])                                     # scene=block: the liver's read from conf/scene
    served, note = served_rollout(cfg, law)
    assert OmegaConf.select(served, "rollout.prior_hht") == liver and cfg.rollout.prior_hht is None
    assert f"scene 'liver' serves its law with HHT's dissipation α = -{liver:g} (scene.time.served_hht" in note
    for kept in (load_config(["rollout.prior_hht=0"]), load_config(["rollout.prior_rule=energy"]),
                 load_config(["scene=liver", "scene.time.served_hht=null"])):
        assert served_rollout(kept, law) == (kept, "")
    for other in ({**law, "prior": None}, {**law, "prior": {**law["prior"], "law_hht": 0.05}},
                  {**law, "prior": {**law["prior"], "law_rule": "energy"}}, {**law, "scene": "shell"},
                  {**law, "scene": "my_own_scene"}):
        assert served_rollout(cfg, other) == (cfg, "")
    budget = {**law, "config": "train:\n  fit_target: budget\n"}
    same, note = served_rollout(cfg, budget)
    assert same is cfg and "train.fit_target=budget" in note and "exported at its data's rule" in note
    block = load_config(["scene.time.served_hht=0.05"])        # the command line's scene, where it is the model's
    assert OmegaConf.select(served_rollout(block, {**law, "scene": "block"})[0], "rollout.prior_hht") == 0.05
    # data whose rule HHT does not modify (the block's stiffness-proportional damping) keep it
    from types import SimpleNamespace

    from thermognn.core.state import describe_step

    damped = SimpleNamespace(linear_solid=lambda: SimpleNamespace(rayleigh=(0.0, 0.002), beta=0.25, gamma=0.5))
    same, note = served_rollout(cfg, law, damped)
    assert same is cfg and "its data's rule (β 0.25, γ 0.5, βK 0.002 s) is not the undamped" in note
    plain = SimpleNamespace(linear_solid=lambda: SimpleNamespace(rayleigh=(0.0, 0.0), beta=0.25, gamma=0.5))
    assert OmegaConf.select(served_rollout(cfg, law, plain)[0], "rollout.prior_hht") == liver
    # the exported file's step says so (its metadata, read by serve)
    assert describe_step({"prior": "linear", "law": 1, "law_hht": 0.02}).startswith("HHT's step (α = -0.02, ")
    for bad in ("2", "true", "abc"):
        with pytest.raises(ConfigError, match=r"^scene.time.served_hht = .* \(scene 'block'\): expected null or a number 0 to 1/3"):
            served_rollout(load_config([f"scene.time.served_hht={bad}"]), {**law, "scene": "block"})
