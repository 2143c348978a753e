"""The trained models the repository ships (models/): they load safely, keep within the benchmark's
parameter budget (the beam) and, with today's code, still score what models/README.md records for
them: the beam on its reference test split, the learned laws of the paper's scenes on FE cases
solved afresh at load points they never saw."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from thermognn.core.config import load_config
from thermognn.train.checkpoint import load_checkpoint, model_from_checkpoint
from thermognn.train.model import parameter_count, readout_weight_count
from thermognn.train.tignn_import import PUBLISHED

ROOT = Path(__file__).resolve().parents[1]
BEAM_MODEL = ROOT / "models" / "tignn_beam" / "model.ckpt"
BEAM_FIGURES = ROOT / "models" / "tignn_beam" / "figures.json"
BEAM = ROOT.parent / "shared" / "datasets" / "tignn_beam"


def test_shipped_beam_model_loads_safely_within_the_parameter_budget():
    ckpt = load_checkpoint(BEAM_MODEL)               # torch.load(weights_only=True): no code unpickled
    model = model_from_checkpoint(ckpt)
    figures = json.loads(BEAM_FIGURES.read_text())
    assert ckpt["scene"] == "tignn_beam" and ckpt["hparams"]["stress_readout"]["hops"] == 3
    total = parameter_count(model) + readout_weight_count(model)
    assert total == figures["parameters"] <= PUBLISHED["params"]


@pytest.mark.skipif(not BEAM.is_dir(), reason="../shared/datasets/tignn_beam not present")
def test_shipped_beam_model_reproduces_its_figures_and_beats_the_published_one(tmp_path):
    """The reference test split through `evaluate`: the figures recorded when the model was
    shipped come back (to 1 % of each, float32 summation order aside), and each is below the
    published model's."""
    from thermognn.train import evaluate
    from thermognn.train.tignn_import import import_tignn

    dataset = import_tignn(BEAM, tmp_path / "dataset.h5")
    shutil.copy(BEAM_MODEL, tmp_path / "model.ckpt")
    cfg = load_config(["scene=tignn_beam", f"out={tmp_path}", f"paths.dataset={dataset}",
                       "train.eval_max_train=1"])
    res = evaluate(cfg)
    recorded = json.loads(BEAM_FIGURES.read_text())
    for group in ("q", "v", "sigma"):
        published = PUBLISHED[group]
        assert res[group] == pytest.approx(recorded["per_snapshot"][group], rel=1e-2)
        assert res[f"whole_{group}"] == pytest.approx(recorded["whole"][group], rel=1e-2)
        assert res[group] < published


# -- learned laws (model=learned_law, the law alone): the paper's scenes ------------------------------

#: the learned-law models shipped, each a law-alone checkpoint with its figures.json
LAWS = sorted(p.parent.name for p in (ROOT / "models").glob("*_law/model.ckpt"))


def law_errors(ckpt: dict, dataset: Path) -> tuple[dict, dict, dict]:
    """A learned law's checkpoint rolled out over every trajectory of ``dataset`` (of its scene)
    with the checkpoint's own Newton settings, from each first state under its stored loads:
    ({trajectory: whole-rollout relative error per group (evaluate's metric)}, the law prior's
    Newton counts over them all: iterations, steps, unconverged and cut steps, {trajectory: the
    law's energy along the rollout and along the data, ``evaluate``'s ``law_energy_along`` rows})."""
    import torch

    from thermognn.train.data import load_data
    from thermognn.train.evaluation import law_energy_along
    from thermognn.train.rollout import rollout, trajectory_error

    data = load_data(dataset, [0.8, 0.1, 0.1], 0, torch.float64, parts=(), state_dtype=torch.float64)
    model = model_from_checkpoint(ckpt, data.dataset).eval()
    model.prior.newton_taken.zero_()
    errors, energies = {}, {}
    for name in data.dataset.ok_names:
        t = data.read(name)
        pred = rollout(model, data.graph, t.z[0], t.force, data.dt)
        errors[name] = trajectory_error(pred, t.z, data.layout)
        energies[name] = tuple(law_energy_along(model.prior, data.graph.ref_pos, z, t.force) for z in (pred, t.z))
    return errors, dict(zip(("iterations", "steps", "unconverged", "cut"), model.prior.newton_taken.tolist())), energies


@pytest.mark.parametrize("law", LAWS)
def test_shipped_learned_law_is_a_law_alone(law):
    """Each shipped learned law loads safely and is what its figures say: the law prior's law
    learned from the data (strain energy, and a viscous scene's Prony terms), stepped alone."""
    ckpt = load_checkpoint(ROOT / "models" / law / "model.ckpt")
    figures = json.loads((ROOT / "models" / law / "figures.json").read_text())
    prior = ckpt["prior"]
    assert ckpt["scene"] == figures["scene"] and law == f"{figures['scene']}_law"
    assert prior["law_material"] == "learned" and prior["remainders"] == "zero"
    assert prior["law_hidden"] == figures["hidden"]
    assert prior.get("law_prony") == figures["prony"]            # the fitted [(g, tau s)] of a viscous scene
    weights = [k for k in ckpt["state_dict"] if k.startswith("prior.learned_law.")]
    assert sum(ckpt["state_dict"][k].numel() for k in weights) == figures["law_weights"]


def _deformation_paths():
    """Deformation gradients [400, 3, 3] along six paths from rest, far beyond any scene's data:
    uniaxial compression to λ = 0.25 and tension to 4, equibiaxial stretch to 3, simple shear to
    γ = 4, and volumetric compression to J = 0.15 and dilation to 3."""
    import torch

    t = torch.linspace(0.0, 1.0, 400, dtype=torch.float64)
    eye = torch.eye(3, dtype=torch.float64)

    def principal(l1, l2, l3):
        return torch.diag_embed(torch.stack([l1, l2, l3], -1))
    lam_c, lam_t, lam_b = 0.25 ** t, 4.0 ** t, 3.0 ** t
    shear = eye.repeat(400, 1, 1)
    shear[:, 0, 1] = 4.0 * t
    J_c, J_d = (1.0 - 0.85 * t) ** (1 / 3), (1.0 + 2.0 * t) ** (1 / 3)
    return {"uniaxial compression": principal(lam_c, lam_c ** -0.5, lam_c ** -0.5),
            "uniaxial tension": principal(lam_t, lam_t ** -0.5, lam_t ** -0.5),
            "equibiaxial stretch": principal(lam_b, lam_b, lam_b ** -2), "simple shear": shear,
            "volumetric compression": principal(J_c, J_c, J_c), "volumetric dilation": principal(J_d, J_d, J_d)}


@pytest.mark.parametrize("law", LAWS)
def test_shipped_learned_law_stiffens_beyond_the_states_it_was_fitted_on(law):
    """Each shipped law's energy (with its guard, derived from its weights on load:
    ``StrainEnergy.settle_guard``) rises along every deformation path once it leaves the box of
    its training states; the liver's free law, unguarded, falls along uniaxial compression and
    equibiaxial stretch beyond about three times its training states' |Ī1 − 3| (where, under the
    sim device's press, a cell collapsed onto such a state and the body ran away: session 90)."""
    import torch

    from thermognn.train.learned_law import StrainEnergy

    ckpt = load_checkpoint(ROOT / "models" / law / "model.ckpt")
    prefix = "prior.learned_law."
    energy = StrainEnergy(ckpt["prior"]["law_hidden"])
    energy.load_state_dict({k[len(prefix):]: v for k, v in ckpt["state_dict"].items() if k.startswith(prefix)})
    guard = energy.guard.clone()
    assert bool((guard > 0).all()), guard

    def falling(g):
        energy.guard.copy_(g)
        out = []
        for name, F in _deformation_paths().items():
            C = F.transpose(-1, -2) @ F
            iso, vol = energy.energy_parts(C)
            I1b, I2b, J, _ = energy.invariants(C)
            s = energy.scales
            beyond = torch.stack([(I1b - 3) / s[0], (I2b - 3) / s[1], (J - 1).abs() / s[2]], -1).amax(-1) > 1.0
            falls = ((iso + vol).diff() < 0) & beyond[1:]
            if bool(falls.any()):
                out.append(name)
        return out
    assert falling(guard) == []
    if law == "liver_law":
        assert falling(torch.zeros_like(guard)) == ["uniaxial compression", "equibiaxial stretch"]


@pytest.mark.parametrize("law", LAWS)
def test_shipped_learned_law_is_strongly_elliptic_within_twice_its_states(law):
    """Each shipped law, with its scene's moduli at rest, keeps every acoustic value positive over
    deformations within twice the box of its training states (``ellipticity``, up to where its guard
    starts): a wave travels in every direction and the strain cannot localise. Not the liver's
    (session 86's free fit; session 94): it loses ellipticity over about a fifth of its own box,
    where the data's Ogden law keeps it. A fit with ``train.law_fit_elliptic`` is elliptic at the
    same accuracy, not shipped (under 30 s of the sim press at 20 ms it rang up and collapsed as
    the free fit does; HHT 0.05 holds it); replacing the liver's law flips this test's branch."""
    from omegaconf import OmegaConf

    from thermognn.generate.materials import material_from_config
    from thermognn.train.learned_law import GUARD_MARGIN, StrainEnergy, ellipticity

    ckpt = load_checkpoint(ROOT / "models" / law / "model.ckpt")
    material = material_from_config(OmegaConf.create(ckpt["config"]).scene.material)    # its moduli at rest
    prefix = "prior.learned_law."
    energy = StrainEnergy(ckpt["prior"]["law_hidden"], mu=material.shear_modulus, kappa=material.bulk_modulus)
    energy.load_state_dict({k[len(prefix):]: v for k, v in ckpt["state_dict"].items() if k.startswith(prefix)})
    assert ellipticity(energy, 1e-6, 64)["min"] == pytest.approx(1.0, rel=0.05)    # μ_s at rest: the moduli fit
    if law == "liver_law":
        box = ellipticity(energy, 1.0)
        assert ellipticity(energy, 0.5)["fraction"] == 0.0 and box["fraction"] > 0.1 and box["min"] < -1.0, box
        return
    wide = ellipticity(energy, GUARD_MARGIN)
    assert wide["fraction"] == 0.0 and wide["min"] > 0.0, wide


@pytest.mark.slow
@pytest.mark.parametrize("law", LAWS)
def test_shipped_learned_law_follows_fresh_fe_cases_within_2_percent(tmp_path, law):
    """The scene's FE (dolfinx) solved afresh at load points of another seed and at another
    magnitude than the training data's (so no case is one of its trajectories), and the shipped law
    rolled over them: every case within issue 4's 2 % in q, v and σ over the whole rollout, no step
    left unconverged, and the figures recorded when it was shipped come back (to 1 % of each)."""
    from omegaconf import OmegaConf

    ckpt = load_checkpoint(ROOT / "models" / law / "model.ckpt")
    mesh = OmegaConf.create(ckpt["config"]).scene.mesh.get("file")
    if mesh and not (ROOT / str(mesh)).is_file():
        pytest.skip(f"{mesh} not present (../shared)")
    fresh = json.loads((ROOT / "models" / law / "figures.json").read_text())["fresh"]
    trained = OmegaConf.create(ckpt["config"]).scene.loads
    loads = OmegaConf.from_dotlist([o for o in fresh["generate"] if o.startswith("scene.loads.")]).scene.loads
    assert loads.seed != trained.seed and loads.magnitude != trained.magnitude, (loads, trained)
    res = subprocess.run([sys.executable, "-m", "thermognn.cli", "generate", f"out={tmp_path}", *fresh["generate"],
                          "scene.time.convergence_check=0"],                     # (not needed here)
                         capture_output=True, text=True, timeout=1800)
    assert res.returncode == 0, res.stderr[-3000:]
    errors, newton, energies = law_errors(ckpt, tmp_path / "dataset.h5")
    assert newton["unconverged"] == 0, newton
    assert sorted(errors) == sorted(fresh["whole"])
    for name, err in errors.items():
        for group in ("q", "v", "sigma"):
            assert 0 < err[group] <= 0.02, (name, group, err)
            assert err[group] == pytest.approx(fresh["whole"][name][group], rel=1e-2, abs=1e-8), (name, group, err)
    # the law's own energy along each case (evaluate's, session 89): within 2 % of the data's under
    # the same law; a viscous scene's law passive at every step (it never gives back more than the
    # loads put in), the elastic shell's holding the loads' work up to the trapezoidal drift its
    # data has too (on its test split at most 4.4 % of the work)
    import numpy as np

    from thermognn.train.evaluation import PASSIVE_TOL
    viscous = bool(OmegaConf.create(ckpt["config"]).scene.material.prony)
    for name, (pred, data) in energies.items():
        work = float(np.abs(pred[:, 4]).max())
        assert work > 0 and np.abs(pred[:, 0] - data[:, 0]).max() <= 0.02 * np.abs(data[:, 0]).max(), name
        if viscous:
            assert pred[1:, 5].min() >= -PASSIVE_TOL * work and pred[-1, 5] > 0, (name, pred[:, 5] / work)
        else:
            assert np.abs(pred[:, 5]).max() <= 0.1 * work, (name, pred[:, 5] / work)
            assert np.abs(pred[:, 5] - data[:, 5]).max() <= 0.02 * work, name
    # as served: a scene that declares a served time rule (scene.time.served_hht; the liver's HHT
    # 0.02, which held its law under 60 s of the sim press where the data's undamped rule collapsed,
    # session 95) has its law exported so, and every law iterated to a tolerance is served with its
    # tangent kept and its updates line-searched (served_law_step, session 97), its chord updates
    # Anderson-mixed (session 102); the law stepped so
    # is still within 2 % of every fresh case, every step converged
    from thermognn.core.config import scene_served_hht
    from thermognn.export.exporter import verify
    from thermognn.train.checkpoint import served_law_step

    hht = scene_served_hht(ckpt["scene"])
    assert served_law_step(ckpt).get("prior_tangent") == "kept"       # every shipped law iterates to a tolerance
    import torch

    from thermognn.train.data import load_data
    from thermognn.train.evaluation import served_errors, served_sentence

    data = load_data(tmp_path / "dataset.h5", [0.8, 0.1, 0.1], 0, torch.float64, parts=(),
                     state_dtype=torch.float64)
    served = served_errors(ckpt, load_config([]), data, [data.read(n) for n in data.dataset.ok_names])
    print(f"{law}: {served_sentence(served, ['q', 'v', 'sigma'])}")
    assert served["hht"] == (hht or 0.0) and served["unconverged"] == 0, served
    assert ("its tangent kept, its chord updates Anderson-mixed with up to 2 earlier ones, its updates line-searched"
            in served["step"]), served
    for group in ("q", "v", "sigma"):
        mean = sum(err[group] for err in errors.values()) / len(errors)
        assert 0 < served["worst"][group] <= 0.02, (group, served)
        if hht:                                   # another rule: other errors; else the converged law's
            assert served["whole"][group] != pytest.approx(mean), (group, served)
        else:   # within 1e-4 of it: the kept tangent's chords stop at the tolerance on the update, short
            # of the root (the shell's v 1.8e-5 -> 5.6e-5 once a law alone steps once a model step, session 99)
            assert served["whole"][group] <= 1.05 * mean + 1e-4, (group, served, mean)

    def export_as_served() -> tuple[Path, str]:
        """The shipped law exported by the CLI as export serves it (tmp_path/served/model.pt); its stdout."""
        out = tmp_path / "served"
        out.mkdir()
        shutil.copy(ROOT / "models" / law / "model.ckpt", out / "model.ckpt")
        res = subprocess.run([sys.executable, "-m", "thermognn.cli", "export", f"out={out}",
                              f"paths.dataset={tmp_path / 'dataset.h5'}", "train.threads=1",
                              "train.export_optimized=false"], capture_output=True, text=True, timeout=1800)
        assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
        return out / "model.pt", res.stdout

    if hht:                                           # exported so by the CLI (the liver's)
        exported, stdout = export_as_served()
        assert f"scene '{ckpt['scene']}' serves its law with HHT's dissipation α = -{hht:g}" in stdout
        step = verify(exported)["step"]
        assert step["law_hht"] == hht and step["law_tangent"] == "kept" and step["law_search"] == 6, step
    if not viscous:                                   # the undamped shell under serve's tool (session 98)
        # exported as served and pressed by the sim device's default press for one period (400
        # steps of 5 ms), serve's passivity and health on: with the contact load found at the end
        # of each step (serve's implicit coupling) the shell stays within its law's states, its
        # passivity never acts, every law step converges and the force is smooth; found before
        # each step (explicit) it chattered between 0 and 2.4 N and was crushed (session 97)
        from thermognn.serve.lockstep import force_envelope, press_rollout

        pressed = press_rollout(export_as_served()[0], 400, load_radius=0.008)
        assert pressed.finite and pressed.healthy and pressed.resets == 0, pressed.health
        assert pressed.first_step("cells_beyond_states") is None and pressed.unsettled == 0
        assert pressed.passivity["passivity_steps"] == 0 and pressed.law_counts[2] == 0, pressed.passivity
        force = np.linalg.norm(pressed.force, axis=1)                  # [400] N
        assert 0.3 < force.max() < 1.0 and 1.0 < pressed.trials.mean() < 2.5, (force.max(), pressed.trials.mean())
        envelope = force_envelope(pressed.force, 21)                    # over 100 ms
        assert np.linalg.norm(pressed.force - envelope) < 0.1 * np.linalg.norm(envelope)
        assert np.abs(np.diff(force)).max() < 0.1                      # [N] a step
