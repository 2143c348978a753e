"""Training on a tiny analytic dataset: loss decreases, stable rollouts, checkpoints, resume, errors."""

import csv
import math

import numpy as np
import pytest
import torch

from thermognn.core.config import load_config
from thermognn.core.errors import ConfigError, DataError
from thermognn.train import train
from thermognn.train.checkpoint import last_path, load_checkpoint, model_from_checkpoint
from thermognn.train.data import load_data
from thermognn.train.rollout import rollout, validation_error
from thermognn.train.synthetic import write_oscillator_dataset

SMALL = ["train.threads=1", "model.hidden=24", "model.message_passing=2", "train.batch_size=4", "train.val_every=2", "train.lr=3e-3"]


def _cfg(out, *extra):
    return load_config([f"out={out}", *SMALL, *extra])


def _rows(out):
    with open(out / "metrics.csv") as fh:
        return list(csv.DictReader(fh))


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    write_oscillator_dataset(out / "dataset.h5", n_trajectories=6, steps=10)
    cfg = _cfg(out, "train.epochs=12")
    ckpt = train(cfg)
    return out, cfg, ckpt


def test_split_keeps_each_load_point_in_one_part():
    """Cases pressing one point at several magnitudes share a part, fractions count points, and
    trajectories without groups split as a permutation of themselves (the split before groups)."""
    from types import SimpleNamespace

    import numpy as np

    from thermognn.train.data import split_names

    names = [f"traj_{k}" for k in range(40)]
    plain = SimpleNamespace(ok_names=names[:20], split=None, split_groups={})
    parts = split_names(plain, [0.8, 0.1, 0.1], 0)
    perm = [names[i] for i in np.random.default_rng(0).permutation(20)]
    assert parts == {"train": sorted(perm[:16], key=names.index), "val": sorted(perm[16:18], key=names.index),
                     "test": sorted(perm[18:], key=names.index)}
    grouped = SimpleNamespace(ok_names=names, split=None, split_groups={n: f"point_{k % 20}" for k, n in enumerate(names)})
    both = split_names(grouped, [0.8, 0.1, 0.1], 0)
    assert {k: len(v) for k, v in both.items()} == {"train": 32, "val": 4, "test": 4}
    for part, members in both.items():      # the same points as without the second round, both rounds
        assert members == sorted(parts[part] + [f"traj_{names.index(n) + 20}" for n in parts[part]], key=names.index)


def test_split_keeps_a_fine_tunes_init_split():
    """keep (train.init's split): the trajectories it names, and the rest of their split groups,
    stay in their parts whatever the seeded draw; only the new groups are split, among themselves,
    by the fractions (no minimum of one per part); a keep naming no training case here is ignored."""
    from types import SimpleNamespace

    import numpy as np

    from thermognn.train.data import split_names

    names = [f"traj_{k}" for k in range(96)]
    old = split_names(SimpleNamespace(ok_names=names[:48], split=None, split_groups={}), [0.8, 0.1, 0.1], 0)
    grown = SimpleNamespace(ok_names=names, split=None, split_groups={})
    assert split_names(grown, [0.8, 0.1, 0.1], 0)["test"] != old["test"]     # a fresh draw would mix them
    kept = split_names(grown, [0.8, 0.1, 0.1], 0, keep=old)
    perm = [names[48 + i] for i in np.random.default_rng(0).permutation(48)]
    for part, (a, b) in {"train": (0, 38), "val": (38, 43), "test": (43, 48)}.items():
        assert kept[part] == sorted(old[part] + perm[a:b], key=names.index)
    # a group pressed again (traj_k and traj_{k+48} share point k) follows its kept case
    grouped = SimpleNamespace(ok_names=names, split=None, split_groups={n: f"point_{k % 48}" for k, n in enumerate(names)})
    again = split_names(grouped, [0.8, 0.1, 0.1], 5, keep=old)
    for part in ("train", "val", "test"):
        assert again[part] == sorted(old[part] + [f"traj_{names.index(n) + 48}" for n in old[part]], key=names.index)
    # three new cases: rounded shares, all to training
    few = split_names(SimpleNamespace(ok_names=names[:51], split=None, split_groups={}), [0.8, 0.1, 0.1], 0, keep=old)
    assert few["train"] == sorted(old["train"] + names[48:51], key=names.index) and few["test"] == old["test"]
    foreign = {"train": ["other_1"], "val": ["other_2"], "test": ["other_3"]}
    assert split_names(grown, [0.8, 0.1, 0.1], 0, keep=foreign) == split_names(grown, [0.8, 0.1, 0.1], 0)


def test_fine_tune_on_a_grown_dataset_keeps_the_held_out_cases(trained, tmp_path):
    """train.init on a dataset with more trajectories (same mesh): the init's validation and test
    cases are still held out, and the new ones are split too (the checkpoint records it)."""
    out, _, ckpt = trained
    write_oscillator_dataset(tmp_path / "dataset.h5", n_trajectories=16, steps=10)
    old = load_checkpoint(ckpt)["split"]
    train(_cfg(tmp_path, "train.epochs=1", f"train.init={ckpt}", "train.lr=1e-5"))
    split = load_checkpoint(tmp_path / "model.ckpt")["split"]
    for part in ("val", "test"):
        assert set(old[part]) <= set(split[part])
        assert not set(old[part]) & set(split["train"])
    assert set(old["train"]) <= set(split["train"])
    assert {len(split[k]) for k in ("val", "test")} == {len(old["val"]) + 1}       # 10 new: 8 / 1 / 1


def test_training_lowers_loss_and_writes_outputs(trained):
    out, cfg, ckpt = trained
    assert ckpt.exists() and last_path(ckpt).exists()
    rows = _rows(out)
    assert [int(r["epoch"]) for r in rows] == list(range(1, 13))
    losses = [float(r["loss"]) for r in rows]
    assert losses[-1] < 0.5 * losses[0]
    assert any(r["val_error"] for r in rows)


def test_checkpoint_contents_and_round_trip(trained):
    out, cfg, ckpt_path = trained
    ckpt = load_checkpoint(ckpt_path)
    for key in ("hparams", "state_dict", "stats", "state_layout", "dt", "effects", "structure", "config",
                "versions", "fingerprint", "split"):
        assert key in ckpt, key
    assert ckpt["structure"] == "hamiltonian"  # elastic + inertia: reversible
    assert ckpt["fingerprint"]["n_nodes"] == 27
    model = model_from_checkpoint(ckpt)
    sd = model.state_dict()
    assert all(torch.equal(sd[k], v) for k, v in ckpt["state_dict"].items())
    assert torch.equal(model.z_std, ckpt["stats"]["z_std"].float())
    # stats come from the training split only
    data = load_data(out / "dataset.h5", cfg.train.split, cfg.seed)
    assert set(ckpt["split"]["train"]).isdisjoint(ckpt["split"]["test"])
    z = torch.cat([t.z for t in data.of("train")]).reshape(-1, 12).double()
    assert torch.allclose(ckpt["stats"]["z_mean"], z.mean(0), rtol=1e-5, atol=1e-9)


def test_rollout_stays_finite_long_horizon_and_large_loads(trained):
    out, cfg, ckpt_path = trained
    model = model_from_checkpoint(load_checkpoint(ckpt_path))
    data = load_data(out / "dataset.h5", cfg.train.split, cfg.seed)
    t = data.of("test")[0]
    steps = 10 * (t.z.shape[0] - 1)
    pred = rollout(model, data.graph, t.z[0], 10.0 * t.force, data.dt, steps=steps)
    assert pred.shape[0] == steps + 1
    assert torch.isfinite(pred).all()


def test_resume_after_interruption_matches_uninterrupted(tmp_path, monkeypatch):
    import thermognn.train.loop as loop

    write_oscillator_dataset(tmp_path / "a" / "dataset.h5", n_trajectories=4, steps=6)
    write_oscillator_dataset(tmp_path / "b" / "dataset.h5", n_trajectories=4, steps=6)
    extra = ("train.epochs=4", "train.noise=0.01", "train.rollout_pairs=2", "train.rest_rollout=4",
             "train.rest_stability=10", "train.symmetry_augment=true")
    ref = train(_cfg(tmp_path / "a", *extra))

    real_write = loop._write_metrics
    calls = {"n": 0}

    def interrupt_after_two(path, history):
        real_write(path, history)
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(loop, "_write_metrics", interrupt_after_two)
    with pytest.raises(KeyboardInterrupt):
        train(_cfg(tmp_path / "b", *extra))
    assert load_checkpoint(last_path(tmp_path / "b" / "model.ckpt"))["epoch"] == 2
    monkeypatch.setattr(loop, "_write_metrics", real_write)
    resumed = train(_cfg(tmp_path / "b", *extra))
    assert [int(r["epoch"]) for r in _rows(tmp_path / "b")] == [1, 2, 3, 4]
    a = load_checkpoint(last_path(ref))["state_dict"]
    b = load_checkpoint(last_path(resumed))["state_dict"]
    for k in a:
        assert torch.allclose(a[k], b[k], rtol=1e-5, atol=1e-7), k


def test_resume_within_an_epoch_goes_on_at_its_next_batch(tmp_path, monkeypatch, capsys):
    """train.checkpoint_minutes in the general loop: model.last.ckpt is also written within an
    epoch, and a run interrupted there (once in the first epoch, once in the third, whose drifted
    states come from the weights its epoch began with) goes on at the next batch with the same
    order, noise, probe directions and rate: the weights and every metrics column but the seconds
    are the uninterrupted run's."""
    import thermognn.train.loop as loop

    for run in ("a", "b"):
        write_oscillator_dataset(tmp_path / run / "dataset.h5", n_trajectories=4, steps=6)
    extra = ("train.epochs=3", "train.noise=0.01", "train.rollout_pairs=2", "train.rest_rollout=4",
             "train.rest_stability=10", "train.batch_size=2", "train.val_every=1")
    ref = load_checkpoint(last_path(train(_cfg(tmp_path / "a", *extra))))
    assert "mid_epoch" not in ref

    real_save = loop.save_checkpoint
    seen = []

    def interrupt(state, path):                 # KeyboardInterrupt right after chosen mid-epoch writes
        real_save(state, path)
        if "mid_epoch" in state:
            seen.append((len(state["history"]), state["mid_epoch"]["batch"]))
            if seen[-1] in ((0, 3), (2, 2)):
                raise KeyboardInterrupt

    monkeypatch.setattr(loop, "save_checkpoint", interrupt)
    cfg = _cfg(tmp_path / "b", *extra, "train.checkpoint_minutes=1e-9")     # after every batch
    with pytest.raises(KeyboardInterrupt):
        train(cfg)                              # in epoch 1, after its 3rd batch
    with pytest.raises(KeyboardInterrupt):
        train(cfg)                              # resumed there; then in epoch 3, after its 2nd
    assert "within epoch 1, at batch 4 of" in capsys.readouterr().out
    assert seen[:2] == [(0, 1), (0, 2)] and (0, 4) in seen and (1, 1) in seen
    monkeypatch.setattr(loop, "save_checkpoint", real_save)
    got = load_checkpoint(last_path(train(cfg)))
    assert "within epoch 3, at batch 3 of" in capsys.readouterr().out
    assert "mid_epoch" not in got and [r["epoch"] for r in got["history"]] == [1, 2, 3]
    for a, b in zip(ref["history"], got["history"]):
        assert {k: v for k, v in a.items() if k != "seconds"} == {k: v for k, v in b.items() if k != "seconds"}
    for k, v in ref["state_dict"].items():
        assert torch.equal(v, got["state_dict"][k]), k


def test_symmetry_augment_shows_training_pairs_in_the_meshs_mirrors(tmp_path, capsys):
    """``train.symmetry_augment``: the square box clamped at its base has one mirror besides the
    identity, the x <-> y swap; the image of an oscillator trajectory is the same oscillator driven
    sideways (u_y = b Z / H, σ23 = G b / H, the load along y), twice the image is the original, the
    batches see it, training with it runs, and bad settings are refused in one line."""
    from thermognn.train.data import make_batch, state_images

    write_oscillator_dataset(tmp_path / "dataset.h5", n_trajectories=4, steps=6)
    data = load_data(tmp_path / "dataset.h5", [0.5, 0.25, 0.25], 0, torch.float64)
    images = state_images(data.graph, data.layout)
    assert len(images) == 2 and torch.equal(images[0].matrix, torch.eye(12, dtype=torch.float64))
    assert len(state_images(data.graph, data.layout, gravity=[0.0, 0.0, -9.81])) == 2   # the swap keeps g along z
    assert len(state_images(data.graph, data.layout, gravity=[0.0, -9.81, 0.0])) == 1   # not along y
    swap = images[1]
    t = data.read(data.split["train"][0])
    z, f, X = swap.states(t.z), swap.loads(t.force), data.graph.ref_pos.double()
    H, b = float(X[:, 2].max()), (t.z[:, :, 0] - X[:, 0]) / (X[:, 2] / float(X[:, 2].max())).clamp(min=1e-12)
    top = X[:, 2] == H
    assert torch.allclose(z[:, :, 0], X[:, 0].expand_as(z[:, :, 0]), atol=1e-15)            # no motion along x now
    assert torch.allclose(z[:, top, 1] - X[top, 1], b[:, top], atol=1e-15)                # the shear along y
    assert torch.allclose(z[:, :, 4], t.z[:, :, 3], atol=1e-15)                            # v_y = the former v_x
    assert torch.allclose(z[:, :, 6 + 5], t.z[:, :, 6 + 4]) and not z[:, :, 6 + 4].any()  # σ23 = the former σ13
    assert torch.equal(f[:, :, 1], t.force[:, :, 0]) and not f[:, :, 0].any()
    assert torch.allclose(swap.states(z), t.z, atol=1e-15) and torch.equal(swap.loads(f), t.force)
    batch = make_batch([t], [(0, 2), (0, 2)], data.graph, frames=[images[0], swap])
    n = data.graph.n_nodes
    assert torch.equal(batch.z[:n], t.z[2]) and torch.allclose(batch.z[n:], z[2]) and torch.equal(batch.f[n:], f[3])
    capsys.readouterr()
    ckpt = load_checkpoint(train(_cfg(tmp_path, "train.epochs=2", "train.symmetry_augment=true")))
    assert "each pair seen in one of the mesh's 2 mirror frames at random" in capsys.readouterr().out
    assert all(math.isfinite(float(r["loss"])) for r in _rows(tmp_path)) and ckpt["epoch"] == 2
    with pytest.raises(ConfigError, match=r"train.symmetry_augment = 'yes', expected true .* or false"):
        train(_cfg(tmp_path / "bad", "train.symmetry_augment=yes", f"paths.dataset={tmp_path / 'dataset.h5'}"))
    with pytest.raises(ConfigError, match=r"train.symmetry_augment = true: .* model.prior=linear"):
        train(_cfg(tmp_path / "lp", "model=linear_prior", "train.symmetry_augment=true",
                   f"paths.dataset={tmp_path / 'dataset.h5'}"))


def test_mirror_average_steps_the_mean_over_the_meshs_mirror_frames(tmp_path, capsys):
    """``model.mirror_average``: each step is the mean over the mesh's mirror frames g of
    g⁻¹ step(g z, g f) (the box: the identity and the x <-> y swap, its own inverse), so the model
    is exactly equivariant where the plain network is not; set on a trained network with
    train.epochs=0 from its checkpoint (weights kept), trained with from scratch, dropped again by a
    fine-tune; export keeps it; bad settings are refused in one line."""
    from thermognn.export import export
    from thermognn.train.data import state_images

    write_oscillator_dataset(tmp_path / "dataset.h5", n_trajectories=4, steps=6)
    on_data = f"paths.dataset={tmp_path / 'dataset.h5'}"
    plain_path = train(_cfg(tmp_path / "a", "train.epochs=2", on_data))
    capsys.readouterr()
    cfg = _cfg(tmp_path / "m", "train.epochs=0", f"train.init={plain_path}", "model.mirror_average=true", on_data)
    ckpt = load_checkpoint(train(cfg))
    assert "kept as it is, stepped in the mesh's 2 mirror frames" in capsys.readouterr().out
    assert ckpt["hparams"]["mirror_frames"] == {"frames": 2, "nodes": 27} and ckpt["epoch"] == 0
    src = load_checkpoint(plain_path)
    assert all(torch.equal(v, ckpt["state_dict"][k]) for k, v in src["state_dict"].items())   # weights kept
    plain, mirrored = model_from_checkpoint(src), model_from_checkpoint(ckpt)
    data = load_data(tmp_path / "dataset.h5", [0.5, 0.25, 0.25], 0, torch.float32)
    swap = state_images(data.graph, data.layout)[1]
    t = data.read(data.split["train"][0])
    z, f = t.z[2], t.force[3]
    args = (data.graph.edge_index, data.graph.node_type, data.graph.ref_pos, torch.tensor(data.dt))
    step = mirrored.step(z, f, *args)
    scale = step.abs().amax(0).clamp(min=1e-12)
    mean = 0.5 * (plain.step(z, f, *args) + swap.states(plain.step(swap.states(z), swap.loads(f), *args)))
    assert float(((step - mean).abs() / scale).max()) < 1e-5
    image = mirrored.step(swap.states(z), swap.loads(f), *args)          # the image steps to the step's image
    assert float(((image - swap.states(step)).abs() / scale).max()) < 1e-5
    ei, nt, X, dt = args                                                  # a batch of two states steps as each alone
    two = mirrored.step(torch.cat([z, swap.states(z)]), torch.cat([f, swap.loads(f)]), torch.cat([ei, ei + 27], 1),
                        nt.repeat(2), X.repeat(2, 1), dt)
    assert float(((two - torch.cat([step, image])).abs() / scale).max()) < 1e-5
    lone = plain.step(swap.states(z), swap.loads(f), *args) - swap.states(plain.step(z, f, *args))
    assert float((lone.abs() / scale).max()) > 1e-3                       # the plain network is not equivariant
    scripted = torch.jit.load(str(export(cfg)))
    assert float(((scripted(z, f) - step).abs() / scale).max()) < 1e-5
    from thermognn.train import evaluate
    evaluate(cfg)                                                        # says how it steps
    assert "each step the mean over 2 mirror frames" in (tmp_path / "m" / "eval" / "summary.md").read_text()
    trained = load_checkpoint(train(_cfg(tmp_path / "t", "train.epochs=1", "model.mirror_average=true", on_data)))
    assert trained["hparams"]["mirror_frames"]["frames"] == 2
    dropped = load_checkpoint(train(_cfg(tmp_path / "d", "train.epochs=1", f"train.init={tmp_path / 'm' / 'model.ckpt'}",
                                         on_data)))
    assert "mirror_frames" not in dropped["hparams"] and not any(k.startswith("frame_") for k in dropped["state_dict"])
    assert "the mirror frames of" in capsys.readouterr().out
    # training windows roll out as the model steps: the window loss's error is that of its averaged steps
    from thermognn.train.data import make_window_batch
    from thermognn.train.loop import window_loss
    window = make_window_batch(data.of("train"), [(0, 1), (1, 2)], data.graph, 3)
    wei, wnt, wX = window.edge_index, window.node_type, window.pos
    rolled, errors = window.z[0], []
    free = mirrored.free_entries(wnt, rolled)                             # [2 N, D]
    for k in range(1, 4):
        rolled = mirrored.step(rolled, window.f[k], wei, wnt, wX, dt)
        e = (rolled - window.z[k]) / (data.dt * mirrored.dzdt_std)
        errors.append((e.pow(2) * free).sum() / free.sum())
    ones = torch.ones(data.layout.dim)
    _, by_loss, _ = window_loss(mirrored, window, data.dt, ones, ones, 1.0, 0.0)
    assert math.isclose(by_loss, float(sum(errors) / 3), rel_tol=1e-4)
    _, by_plain, _ = window_loss(plain, window, data.dt, ones, ones, 1.0, 0.0)
    assert not math.isclose(by_plain, by_loss, rel_tol=1e-3)
    capsys.readouterr()
    train(_cfg(tmp_path / "tw", "train.epochs=1", "model.mirror_average=true", "train.window_steps=2", on_data))
    assert "mirror frames (model.mirror_average), the training windows' steps too" in capsys.readouterr().out
    listed = load_checkpoint(train(_cfg(tmp_path / "g", "train.epochs=0", f"train.init={plain_path}",
                                        "model.mirror_average=[0,1]", on_data)))
    assert "(x, y, z), 1 (y, x, z); averaging over 0, 1" in capsys.readouterr().out
    assert all(torch.equal(v, ckpt["state_dict"][k]) for k, v in listed["state_dict"].items())
    with pytest.raises(ConfigError, match=r"model.mirror_average = 'yes', expected true .*, false, or a list of frame"):
        train(_cfg(tmp_path / "bad", "model.mirror_average=yes", on_data))
    with pytest.raises(ConfigError, match=r"model.mirror_average = \[1\]: not a group, frame 1 then 1 is frame 0, "
                                          r"not listed .* 0 \(x, y, z\), 1 \(y, x, z\)"):
        train(_cfg(tmp_path / "ng", "model.mirror_average=[1]", on_data))
    with pytest.raises(ConfigError, match=r"model.mirror_average = \[0, 2\]: expected distinct frame indices from 0 to 1"):
        train(_cfg(tmp_path / "nr", "model.mirror_average=[0,2]", on_data))
    with pytest.raises(ConfigError, match=r"model.mirror_average = true: .* model.prior=linear"):
        train(_cfg(tmp_path / "lp", "model=linear_prior", "model.mirror_average=true", on_data))
    with pytest.raises(ConfigError, match=r"train.epochs = 0, expected >= 1 .* model.mirror_average"):
        train(_cfg(tmp_path / "e0", "train.epochs=0", on_data))


def test_generic_structure_trains(tmp_path):
    write_oscillator_dataset(tmp_path / "dataset.h5", n_trajectories=4, steps=6, viscous=True)
    ckpt = train(_cfg(tmp_path, "train.epochs=2"))
    assert load_checkpoint(ckpt)["structure"] == "generic"
    rows = _rows(tmp_path)
    assert all(math.isfinite(float(r["loss"])) for r in rows)
    assert float(rows[0]["degeneracy_loss"]) > 0.0


def test_mismatched_dataset_is_one_line_error(trained, tmp_path):
    from thermognn.train import evaluate

    out, cfg, ckpt_path = trained
    write_oscillator_dataset(tmp_path / "other.h5", n_trajectories=3, steps=4, shape=(4, 3, 3))
    cfg2 = load_config([f"out={tmp_path}", f"paths.checkpoint={ckpt_path}", f"paths.dataset={tmp_path / 'other.h5'}"])
    with pytest.raises(DataError) as err:
        evaluate(cfg2)
    msg = str(err.value)
    assert "\n" not in msg and str(ckpt_path) in msg and "other.h5" in msg and "n_nodes" in msg


def test_missing_and_corrupt_checkpoint(tmp_path):
    with pytest.raises(DataError, match="not found"):
        load_checkpoint(tmp_path / "none.ckpt")
    bad = tmp_path / "bad.ckpt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(DataError) as err:
        load_checkpoint(bad)
    assert "\n" not in str(err.value) and "bad.ckpt" in str(err.value)


def test_evaluate_writes_figures_tables_and_vtu(trained):
    from thermognn.train import evaluate

    out, cfg, _ = trained
    res = evaluate(cfg)
    assert set(res) == {"q", "v", "sigma", "ms_per_step", "energy_balance", "rest_drift", "rest_growth",
                        "one_step_q", "one_step_v", "one_step_sigma", "whole_q", "whole_v", "whole_sigma"}
    assert all(math.isfinite(v) for v in res.values())
    ev = out / "eval"
    summary = (ev / "summary.md").read_text()
    from thermognn.train.evaluation import _fmt

    # the whole-rollout errors of summary.md's second table, at full precision in rrmse.json
    assert "| test | " + " | ".join(_fmt(res[f"whole_{g}"]) for g in ("q", "v", "sigma")) + " |" in summary
    assert "One step from every true state" in summary and f"| test | {res['one_step_q']:.3g}" in summary
    assert "Linearised FE baseline: not computed, the dataset holds no linearised FE operators" in summary
    with open(ev / "one_step_vs_time.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert int(rows[0]["step"]) == 1 and len(rows) == sum(1 for _ in open(ev / "rrmse_vs_time.csv")) - 2
    assert res["rest_growth"] > 0 and "- rest stability: one step multiplies" in summary
    assert f"{res['rest_growth']:.4f} at " in summary and "at 30 typical steps' size" in summary   # the largest of 3
    for name in ("rrmse_vs_time.csv", "rrmse_vs_time.png", "rrmse_per_trajectory.csv", "rrmse_per_trajectory.png",
                 "energy_entropy.csv", "energy_entropy.png", "rest_drift.csv", "summary.md"):
        assert (ev / name).stat().st_size > 0, name
    vtu = list(ev.glob("snapshot_*.vtu"))
    assert len(vtu) == 1
    import meshio

    mesh = meshio.read(vtu[0])
    assert {"u_pred", "u_true", "sigma_pred", "sigma_true"} <= set(mesh.point_data)
    with open(ev / "rrmse_per_trajectory.csv") as fh:
        splits = {r["split"] for r in csv.DictReader(fh)}
    assert splits == {"train", "test"}


def test_evaluate_tabulates_the_test_errors_by_peak_load(tmp_path):
    """Test trajectories pressed at two load magnitudes (the oscillator's loads rescaled to peak
    loads of 1 N and 1.3 N): rrmse_per_trajectory.csv gives each trajectory's peak load and errors,
    rrmse.json and summary.md their means at each load; one load, or many, give no table. The csv
    also gives each load point, summary.md the test trajectories with the largest errors."""
    import h5py

    from thermognn.core.schema import Dataset
    from thermognn.train import evaluate
    from thermognn.train.data import split_names
    from thermognn.train.evaluation import MAX_LOAD_GROUPS, _fmt, by_peak_load, hardest, peak_load

    path = write_oscillator_dataset(tmp_path / "dataset.h5", n_trajectories=20, steps=6)
    cfg = _cfg(tmp_path, "train.epochs=1")
    test = split_names(Dataset(path), cfg.train.split, int(cfg.seed))["test"]
    assert len(test) == 2
    with h5py.File(path, "r+") as f:
        for k, name in enumerate(f["trajectories"]):
            force = f["trajectories"][name]["force"]
            target = 1.0 if name == test[0] else 1.3 if name in test else (1.0, 1.3)[k % 2]      # [N]
            force[...] = force[()] * (target / peak_load(torch.as_tensor(force[()])))
    train(cfg)
    res = evaluate(cfg)
    with open(tmp_path / "eval" / "rrmse_per_trajectory.csv") as fh:
        rows = {r["trajectory"]: r for r in csv.DictReader(fh) if r["split"] == "test"}
    assert set(rows) == set(test) and float(rows[test[1]]["peak_load_N"]) == pytest.approx(1.3)
    for name, load in ((test[0], "1"), (test[1], "1.3")):
        for g in ("q", "v", "sigma"):
            assert res[f"{g}@{load}N"] == pytest.approx(float(rows[name][g]), rel=1e-12), (name, g)
            assert res[f"whole_{g}@{load}N"] == pytest.approx(float(rows[name][f"whole_{g}"]), rel=1e-12)
    assert res["whole_sigma"] == pytest.approx((res["whole_sigma@1N"] + res["whole_sigma@1.3N"]) / 2, rel=1e-12)
    points = Dataset(path).load_points                                      # [m], the file's own
    assert [float(rows[test[1]][f"load_point_{c}_m"]) for c in "xyz"] == pytest.approx(points[test[1]], rel=1e-12)
    summary = (tmp_path / "eval" / "summary.md").read_text()
    # the test trajectories ranked by whole-rollout error, relative to each group's test mean
    score = {n: np.mean([float(rows[n][f"whole_{g}"]) / res[f"whole_{g}"] for g in ("q", "v", "sigma")])
             for n in test}
    first = max(test, key=score.get)
    assert "| trajectory | peak load, load point | whole q | whole v | whole sigma |" in summary
    assert (f"| {first} | {float(rows[first]['peak_load_N']):.3g} N at ("
            + ", ".join(f"{x:.4g}" for x in points[first]) + ") m | "
            + _fmt(float(rows[first]["whole_q"]))) in summary
    nan = float("nan")
    assert hardest([{"q": 1.0, "v": 0.01}, {"q": 1.0, "v": 0.03}, {"q": nan, "v": nan}],
                   {"q": 1.0, "v": 0.02}, ["q", "v"]) == [1, 0, 2]
    assert hardest([{"q": 9.0, "v": 0.01}, {"q": 1.0, "v": 0.03}], {"q": nan, "v": 0.02}, ["q", "v"]) == [1, 0]
    assert "| peak load [N] | test trajectories | q | v | sigma | whole q | whole v | whole sigma |" in summary
    assert (f"| 1.3 | 1 | {_fmt(res['q@1.3N'])} | {_fmt(res['v@1.3N'])} | {_fmt(res['sigma@1.3N'])} | "
            f"{_fmt(res['whole_q@1.3N'])} |") in summary
    # loads within 1 % are one group, labelled to 3 significant figures (also across a rounding
    # boundary); one load or more than MAX_LOAD_GROUPS: nothing to tabulate
    errs = [{"q": 1.0}, {"q": 3.0}, {"q": 5.0}]
    grouped = by_peak_load([1.0002, 0.9998, 1.3], errs, errs, ["q"])
    assert list(grouped) == [1.0, 1.3] and grouped[1.0] == {"trajectories": 2.0, "q": 2.0, "whole_q": 2.0}
    across = by_peak_load([0.99949, 1.3, 0.99951], errs, errs, ["q"])
    assert len(across) == 2 and list(across.values())[0]["trajectories"] == 2.0
    close = [1.0, 1.0099, 1.0099, 1.0099, 1.0101]          # means 1.007425 and 1.0101: both 1.01 to 3 figures
    assert list(by_peak_load(close, [errs[0]] * 5, [errs[0]] * 5, ["q"])) == [1.00743, 1.0101]
    assert by_peak_load([1.0, 1.0], errs[:2], errs[:2], ["q"]) == {}
    many = [float(k) for k in range(1, MAX_LOAD_GROUPS + 2)]
    assert by_peak_load(many, [errs[0]] * len(many), [errs[0]] * len(many), ["q"]) == {}


def test_share_of_the_linear_error_left_and_the_training_sample():
    """error_left: the mean over trajectories of the model's error over the linear model's, per
    group, skipping groups the linear model does not predict (nan) or gets exactly (0); spread:
    an evenly spaced sample of the training trajectories with both ends (every load level)."""
    from thermognn.train.data import spread
    from thermognn.train.evaluation import error_left

    nan = float("nan")
    model = [{"q": 1.0, "v": 0.02, "s": 0.5}, {"q": 3.0, "v": 0.01, "s": 0.5}]
    linear = [{"q": 2.0, "v": 0.04, "s": nan}, {"q": 4.0, "v": 0.0, "s": nan}]
    left = error_left(model, linear, ["q", "v", "s"])
    assert left["q"] == pytest.approx((0.5 + 0.75) / 2) and left["v"] == pytest.approx(0.5) and math.isnan(left["s"])
    names = [f"traj_{k}" for k in range(92)]            # 46 points at 1 N, then the same at 1.3 N
    sample = spread(names, 10)
    assert len(sample) == 10 and sample[0] == "traj_0" and sample[-1] == "traj_91" and sample == sorted(sample, key=names.index)
    assert sum(int(n.split("_")[1]) >= 46 for n in sample) == 5
    assert spread(names[:3], 10) == names[:3] and spread(names, 0) == [] and spread(names, 1) == ["traj_0"]


def test_one_step_errors_vanish_on_the_models_own_rollout(trained):
    """Stepping each state of the model's own rollout once reproduces the next state: the batched
    one-step pass (mesh copies, chunked) agrees with the sequential rollout to round-off."""
    from thermognn.train import rollout as ro
    from thermognn.train.data import TrajectoryTensors

    _, cfg, ckpt = trained
    model = model_from_checkpoint(load_checkpoint(ckpt)).double().eval()
    data = load_data(cfg.paths.dataset, cfg.train.split, int(cfg.seed), torch.float64, parts=("test",))
    t = data.of("test")[0]
    own = TrajectoryTensors("own", ro.rollout(model, data.graph, t.z[0], t.force, data.dt), t.force, t.time)
    chunk, nodes = ro.ONE_STEP_CHUNK, ro.ONE_STEP_NODES
    try:
        ro.ONE_STEP_CHUNK = 3                                   # several chunks, the last one short
        whole, per_step = ro.one_step_errors(model, data.graph, [own], data.layout, data.dt)
        real, _ = ro.one_step_errors(model, data.graph, [t], data.layout, data.dt)
        ro.ONE_STEP_NODES = data.graph.n_nodes                  # the node budget: one snapshot a pass
        alone, _ = ro.one_step_errors(model, data.graph, [t], data.layout, data.dt)
    finally:
        ro.ONE_STEP_CHUNK, ro.ONE_STEP_NODES = chunk, nodes
    assert all(len(v) == t.z.shape[0] - 1 for v in per_step.values())
    assert all(v < 1e-9 for v in whole.values() if math.isfinite(v)) and math.isfinite(whole["q"])
    # against the data, the same model's one-step error is a real, finite number, however chunked
    assert real["q"] > 1e-6
    assert all(math.isclose(real[g], alone[g], rel_tol=1e-9) for g in real if math.isfinite(real[g]))


def test_early_stopping(tmp_path):
    write_oscillator_dataset(tmp_path / "dataset.h5", n_trajectories=3, steps=4)
    # lr = 0: the validation error never improves, so patience 1 stops after the second round
    train(_cfg(tmp_path, "train.epochs=6", "train.lr=0.0", "train.val_every=1", "train.patience=1"))
    assert [int(r["epoch"]) for r in _rows(tmp_path)] == [1, 2]


def test_resume_refuses_checkpoint_of_another_dataset(trained, tmp_path):
    import shutil

    out, _, ckpt = trained
    write_oscillator_dataset(tmp_path / "dataset.h5", n_trajectories=3, steps=4, shape=(3, 4, 3))
    shutil.copy(last_path(ckpt), last_path(tmp_path / "model.ckpt"))
    with pytest.raises(DataError, match="train.resume=false"):
        train(_cfg(tmp_path, "train.epochs=1"))
    train(_cfg(tmp_path, "train.epochs=1", "train.resume=false"))
    assert load_checkpoint(tmp_path / "model.ckpt")["fingerprint"]["n_nodes"] == 36


def test_make_batch_matches_pyg_batching(trained):
    from torch_geometric.data import Batch, Data

    from thermognn.train.data import make_batch

    out, cfg, _ = trained
    data = load_data(out / "dataset.h5", cfg.train.split, cfg.seed)
    trajs, g = data.of("train"), data.graph
    items = [(0, 1), (2, 5), (1, 0)]
    got = make_batch(trajs, items, g)
    ref = Batch.from_data_list([Data(z=trajs[i].z[s], z_next=trajs[i].z[s + 1], f=trajs[i].force[s + 1], pos=g.ref_pos,
                                     node_type=g.node_type, edge_index=g.edge_index, num_nodes=g.n_nodes)
                                for i, s in items])
    for key in ("z", "z_next", "f", "pos", "node_type", "edge_index", "batch"):
        assert torch.equal(getattr(got, key), getattr(ref, key)), key


def test_data_parallel_with_torchrun(tmp_path):
    """Two processes (gloo, gradients averaged by all_reduce) train and write one checkpoint."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    write_oscillator_dataset(tmp_path / "dataset.h5", n_trajectories=3, steps=4)
    script = tmp_path / "run.py"
    script.write_text("import sys\nfrom thermognn.core.config import load_config\nfrom thermognn.train import train\n"
                      f"train(load_config(['out={tmp_path}', 'train.epochs=2', 'train.val_every=1', "
                      f"'model.hidden=8', 'model.message_passing=1', 'train.threads=1']))\n")
    torchrun = Path(sys.executable).with_name("torchrun")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    r = subprocess.run([str(torchrun), "--standalone", "--nproc_per_node=2", str(script)], capture_output=True,
                       text=True, timeout=120, env=env)
    assert r.returncode == 0, r.stdout[-1500:] + r.stderr[-1500:]
    assert load_checkpoint(tmp_path / "model.ckpt")["epoch"] in (1, 2)
    assert [int(row["epoch"]) for row in _rows(tmp_path)] == [1, 2]


def test_data_parallel_resumes_within_an_epoch(tmp_path, torchrun_train):
    """Under torchrun too, model.last.ckpt is written within an epoch (rank 0's clock decides for
    both processes) with the whole sample order and each process's running sums; rank 0 dying
    after such a write loses nothing: the resumed two-process run ends with the uninterrupted
    one's weights and metrics. Resuming with another number of processes is refused by name."""
    run = ["train.epochs=2", "train.val_every=1", "model.hidden=8", "model.message_passing=1", "train.threads=1",
           "train.batch_size=2", "train.noise=0.01", "train.rest_rollout=3"]
    for name in ("a", "b"):
        write_oscillator_dataset(tmp_path / name / "dataset.h5", n_trajectories=4, steps=6)
    r = torchrun_train(tmp_path / "a", 0, run)
    assert r.returncode == 0, r.stdout[-1500:] + r.stderr[-1500:]
    assert "epoch 2: batch 2 of" in r.stdout                      # mid-epoch writes under torchrun
    assert torchrun_train(tmp_path / "b", 2, run).returncode != 0  # rank 0 dies in epoch 2, after batch 2
    mid = load_checkpoint(last_path(tmp_path / "b" / "model.ckpt"))["mid_epoch"]
    assert mid["batch"] == 2 and mid["world"] == 2 and len(mid["rank_totals"]) == 2
    r = torchrun_train(tmp_path / "b", 0, run, processes=1)
    assert r.returncode != 0 and "written within epoch 2 by 2 process(es), resumed by 1" in r.stderr
    r = torchrun_train(tmp_path / "b", 0, run)
    assert r.returncode == 0, r.stdout[-1500:] + r.stderr[-1500:]
    assert "within epoch 2, at batch 3 of" in r.stdout
    ref, got = (load_checkpoint(last_path(tmp_path / name / "model.ckpt")) for name in ("a", "b"))
    for a, b in zip(ref["history"], got["history"], strict=True):
        assert {k: v for k, v in a.items() if k != "seconds"} == {k: v for k, v in b.items() if k != "seconds"}
    for k, v in ref["state_dict"].items():
        assert torch.equal(v, got["state_dict"][k]), k


def test_changed_configuration_trains_from_scratch(tmp_path, capsys):
    write_oscillator_dataset(tmp_path / "dataset.h5", n_trajectories=3, steps=4)
    train(_cfg(tmp_path, "train.epochs=2"))
    train(_cfg(tmp_path, "train.epochs=3"))  # more epochs: resumes
    assert "resuming from" in capsys.readouterr().out
    assert [int(r["epoch"]) for r in _rows(tmp_path)] == [1, 2, 3]
    train(_cfg(tmp_path, "train.epochs=2", "train.lr=1e-4"))  # another learning rate: from scratch
    assert "configuration changed (lr)" in capsys.readouterr().out
    assert [int(r["epoch"]) for r in _rows(tmp_path)] == [1, 2]
    # the later rest terms join the identity only when on: a run from before them resumes
    last = last_path(tmp_path / "model.ckpt")
    state = load_checkpoint(last)
    assert not {"rest_stability", "rest_rollout", "rest_stability_probe", "rest_stability_every"} & set(state["identity"])
    train(_cfg(tmp_path, "train.epochs=3", "train.lr=1e-4", "train.rest_stability=0", "train.rest_rollout=0"))
    assert "resuming from" in capsys.readouterr().out
    train(_cfg(tmp_path, "train.epochs=2", "train.lr=1e-4", "train.rest_stability=10"))
    assert "configuration changed (rest_stability, rest_stability_probe)" in capsys.readouterr().out
    train(_cfg(tmp_path, "train.epochs=2", "train.lr=1e-4"))   # a key only the stored run had is named too
    assert "configuration changed (rest_stability, rest_stability_probe)" in capsys.readouterr().out
    from thermognn.train.checkpoint import save_checkpoint      # stored as off: the same as absent
    state = load_checkpoint(last)
    save_checkpoint({**state, "identity": {**state["identity"], "rest_rollout": 0, "rest_stability": 0.0,
                                           "rest_stability_probe": 0.3, "rest_stability_every": 1}}, last)
    train(_cfg(tmp_path, "train.epochs=3", "train.lr=1e-4"))
    assert "resuming from" in capsys.readouterr().out
    from thermognn.train.loop import _without_off_terms    # the penalty's settings count only while it is on
    assert _without_off_terms({"rest_stability": 0, "rest_stability_probe": [0.3, 30], "rest_stability_every": 2}) == {}
    assert _without_off_terms({"rest_stability": 10, "rest_stability_probe": 0.3}) == {"rest_stability": 10}


def test_a_fine_tune_resumes_only_from_the_same_init_file(tmp_path, capsys):
    """train.init counts by its contents, not only its path: the next fine-tune of a chain that
    rewrites the init at one path starts afresh; the same file resumes; so do a run stored before
    the digest existed and a run whose init is its own checkpoint (which it rewrites itself)."""
    import shutil

    from thermognn.train.checkpoint import save_checkpoint
    for name in ("a", "b"):
        write_oscillator_dataset(tmp_path / name / "dataset.h5", n_trajectories=3, steps=4)
    train(_cfg(tmp_path / "a", "train.epochs=2"))
    init = tmp_path / "init.ckpt"
    shutil.copy(tmp_path / "a" / "model.ckpt", init)
    tune = (f"train.init={init}", "train.lr=1e-4")
    train(_cfg(tmp_path / "b", "train.epochs=1", *tune))
    train(_cfg(tmp_path / "b", "train.epochs=2", *tune))           # the same init, more epochs: resumes
    assert "resuming from" in capsys.readouterr().out
    shutil.copy(tmp_path / "b" / "model.ckpt", init)                # the chain's next init, at the same path
    train(_cfg(tmp_path / "b", "train.epochs=2", *tune))
    assert "configuration changed (init_digest)" in capsys.readouterr().out
    assert [int(r["epoch"]) for r in _rows(tmp_path / "b")] == [1, 2]
    last = last_path(tmp_path / "b" / "model.ckpt")
    state = load_checkpoint(last)
    save_checkpoint({**state, "identity": {k: v for k, v in state["identity"].items() if k != "init_digest"}}, last)
    train(_cfg(tmp_path / "b", "train.epochs=3", *tune))           # stored before the digest: resumes
    assert "resuming from" in capsys.readouterr().out
    own = (f"train.init={tmp_path / 'a' / 'model.ckpt'}", "train.lr=1e-4")
    train(_cfg(tmp_path / "a", "train.epochs=1", *own))           # a new init path: from scratch, rewrites it
    assert "configuration changed (init, lr)" in capsys.readouterr().out
    train(_cfg(tmp_path / "a", "train.epochs=2", *own))
    assert "resuming from" in capsys.readouterr().out


def test_structure_auto_follows_effects_and_damping():
    from thermognn.train.loop import resolve_structure

    undamped = "scene:\n  time:\n    integrator: newmark\n    rayleigh: [0.0, 0.0]\n"
    damped = "scene:\n  time:\n    integrator: newmark\n    rayleigh: [0.5, 0.0]\n"
    assert resolve_structure("auto", ["elastic", "inertia"], undamped) == "hamiltonian"
    assert resolve_structure("auto", ["elastic", "inertia"], damped) == "generic"
    assert resolve_structure("auto", ["elastic", "inertia"], undamped.replace("newmark", "quasi_static")) == "generic"
    assert resolve_structure("auto", ["elastic", "viscous", "inertia"], undamped) == "generic"
    assert resolve_structure("auto", ["elastic"]) == "generic"  # quasi-static scene: no inertia
    assert resolve_structure("hamiltonian", ["elastic", "viscous", "inertia"]) == "hamiltonian"


def test_checkpoint_with_foreign_weights_is_one_line_error(trained, tmp_path):
    from thermognn.train.checkpoint import save_checkpoint

    out, cfg, ckpt_path = trained
    ckpt = load_checkpoint(ckpt_path)
    ckpt["state_dict"] = {k: v for k, v in ckpt["state_dict"].items() if "decoder" not in k}
    save_checkpoint(ckpt, tmp_path / "foreign.ckpt")
    with pytest.raises(DataError) as err:
        model_from_checkpoint(load_checkpoint(tmp_path / "foreign.ckpt"))
    assert "\n" not in str(err.value) and "foreign.ckpt" in str(err.value)


def test_energy_drift_report_midpoint_against_euler(trained):
    """The evaluation's energy error (learned E's change the port's work does not explain) along a
    rollout of the trained Hamiltonian model: the midpoint rule leaves far less of it than Euler."""
    from thermognn.train.evaluation import energy_balance, energy_entropy_along

    out, cfg, ckpt = trained
    model = model_from_checkpoint(load_checkpoint(ckpt))
    assert model.hamiltonian and model.balanced
    data = load_data(out / "dataset.h5", cfg.train.split, 0, parts=("test",))
    t = data.of("test")[0]
    balance = {}
    for integrator in ("euler", "midpoint"):
        model.integrator, model.implicit_iterations = integrator, 6
        pred = rollout(model, data.graph, t.z[0], t.force, data.dt)
        balance[integrator] = energy_balance([energy_entropy_along(model, data.graph, pred, t.force, data.dt)])
    assert balance["midpoint"] < 0.2 * balance["euler"], balance


def test_metrics_also_logged_for_tensorboard(trained):
    """train.tensorboard=auto with tensorboard installed (make setup installs it): the event file
    holds the same per-epoch losses as metrics.csv."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out, _, _ = trained
    acc = EventAccumulator(str(out / "tensorboard"))
    acc.Reload()
    logged = [(e.step, e.value) for e in acc.Scalars("train/loss")]
    rows = _rows(out)
    assert [s for s, _ in logged] == [int(r["epoch"]) for r in rows]
    assert [v for _, v in logged] == pytest.approx([float(r["loss"]) for r in rows], rel=1e-6)


def test_tensorboard_required_but_missing_is_one_line_error(tmp_path, monkeypatch):
    import sys

    from thermognn.core.errors import ConfigError
    from thermognn.train.loop import _tensorboard

    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)   # as if not installed
    assert _tensorboard("auto", tmp_path) is None and _tensorboard(False, tmp_path) is None
    with pytest.raises(ConfigError, match="train.tensorboard = true") as err:
        _tensorboard(True, tmp_path)
    assert "\n" not in str(err.value)


def test_validation_error_stays_finite_where_a_group_comes_to_rest():
    """A velocity that comes to rest: the per-snapshot metric explodes at the last step, the
    whole-trajectory error used for model selection stays at the size of the deviation."""
    from thermognn.core.state import state_layout
    from thermognn.train.rollout import rrmse_per_step, trajectory_error

    layout = state_layout(["elastic", "inertia"])
    truth = torch.zeros(3, 4, layout.dim, dtype=torch.float64)
    truth[1:] = 1.0
    truth[2, :, layout.slice("v")] = 1e-9                      # at rest at the last step
    pred = truth.clone()
    pred[1:, :, layout.slice("v")] += 1e-3
    assert rrmse_per_step(pred, truth, layout)["v"][2] > 1e5
    err = trajectory_error(pred, truth, layout)
    assert err["v"] == pytest.approx(1e-3 * math.sqrt(2), rel=1e-6) and err["q"] == 0.0


def test_rollout_pairs_start_from_the_models_own_bounded_drift(trained):
    """drifted_states: the model's rollout, its deviation from the truth clipped per column;
    make_batch takes (i, s, 1) items from it and still aims at the true next state."""
    from thermognn.train.data import make_batch
    from thermognn.train.loop import ROLLOUT_CLIP, drifted_states

    out, cfg, ckpt = trained
    model = model_from_checkpoint(load_checkpoint(ckpt))
    data = load_data(out / "dataset.h5", cfg.train.split, 0)
    trajs = data.of("train")[:2]
    rolled = drifted_states(model, data.graph, trajs, data.dt)
    bound = ROLLOUT_CLIP * data.dt * model.dzdt_std
    for t, r in zip(trajs, rolled):
        assert r.shape == t.z.shape and torch.isfinite(r).all()
        assert ((r - t.z).abs() <= bound * (1 + 1e-6)).all()
        assert (r[1:] != t.z[1:]).any()                              # it did drift somewhere
    batch = make_batch(trajs, [(1, 3, 1), (0, 2)], data.graph, rolled)
    n = data.graph.n_nodes
    assert torch.equal(batch.z[:n], rolled[1][3]) and torch.equal(batch.z[n:], trajs[0].z[2])
    assert torch.equal(batch.z_next[:n], trajs[1].z[4])


def test_warm_start_from_a_checkpoint(trained, tmp_path):
    """train.init: the run starts from the checkpoint's weights and statistics (its first epoch
    starts where that model ended, far below a fresh start); another model is a one-line error."""
    import shutil

    from thermognn.core.errors import ConfigError

    out, _, ckpt = trained
    shutil.copy(out / "dataset.h5", tmp_path / "dataset.h5")
    fresh = _rows(out)[0]
    train(_cfg(tmp_path, "train.epochs=1", f"train.init={ckpt}", "train.lr=1e-5"))
    warm = _rows(tmp_path)[0]
    assert float(warm["data_loss"]) < 0.5 * float(fresh["data_loss"])
    started = load_checkpoint(tmp_path / "model.ckpt")
    assert torch.equal(started["stats"]["dzdt_std"], load_checkpoint(ckpt)["stats"]["dzdt_std"])
    # the time step alone may change: fine-tuning under another integrator and kinematics
    train(_cfg(tmp_path / "c", "train.epochs=1", f"train.init={ckpt}", "model.integrator=midpoint",
               "model.kinematics=learned", f"paths.dataset={tmp_path / 'dataset.h5'}"))
    assert load_checkpoint(tmp_path / "c" / "model.ckpt")["hparams"]["integrator"] == "midpoint"
    with pytest.raises(ConfigError, match=r"train.init = .*hidden \(24 there, 32 here\)") as err:
        train(_cfg(tmp_path / "b", "train.epochs=1", f"train.init={ckpt}", "model.hidden=32",
                   f"paths.dataset={tmp_path / 'dataset.h5'}"))
    assert "\n" not in str(err.value)


def test_start_repeats_adds_each_trajectorys_first_transition(trained):
    """train.start_repeats k: every transition once, each trajectory's first k times in all;
    below 1 is a one-line configuration error."""
    from thermognn.core.errors import ConfigError
    from thermognn.train.data import samples

    out, cfg, _ = trained
    trajs = load_data(out / "dataset.h5", cfg.train.split, 0).of("train")
    once, thrice = samples(trajs), samples(trajs, 3)
    assert len(once) == sum(t.z.shape[0] - 1 for t in trajs)
    assert sorted(thrice) == sorted(once + [(i, 0) for i in range(len(trajs))] * 2)
    with pytest.raises(ConfigError, match="train.start_repeats = 0, expected an integer >= 1"):
        samples(trajs, 0)
    with pytest.raises(ConfigError, match="train.start_repeats = 'many'"):
        samples(trajs, "many")


def test_rest_samples_hold_the_unloaded_reference_state(trained, tmp_path):
    """train.rest_samples: z0 -> z0 under zero force, taken from the data's common rest start;
    refused (one line) for trajectories that start moving or loaded, and for scenes with gravity."""
    from dataclasses import replace

    from thermognn.core.errors import ConfigError
    from thermognn.train.data import make_batch, rest_trajectory, velocity_columns

    out, cfg, _ = trained
    data = load_data(out / "dataset.h5", cfg.train.split, 0)
    trajs, vel = data.of("train"), velocity_columns(data.layout)
    rest = rest_trajectory(trajs, data.dataset.effects, vel)
    assert rest.z.shape == (2, *trajs[0].z.shape[1:]) and torch.equal(rest.z[0], trajs[0].z[0])
    assert torch.equal(rest.z[1], rest.z[0]) and not rest.force.any()
    batch = make_batch(trajs + [rest], [(len(trajs), 0)], data.graph)
    assert torch.equal(batch.z, batch.z_next) and not batch.f.any()

    moving = replace(trajs[1], z=trajs[1].z.clone())
    moving.z[0, :, vel[0]] = 1e-3
    with pytest.raises(ConfigError, match=f"trajectory {moving.name} does not start at rest"):
        rest_trajectory([trajs[0], moving], data.dataset.effects, vel)
    with pytest.raises(ConfigError, match="gravity"):
        rest_trajectory(trajs, ["elastic", "inertia", "gravity"], vel)

    from thermognn.train.data import rest_samples

    assert rest_samples("auto", trajs, data.dataset.effects, vel)[0] == len(trajs)
    assert rest_samples("auto", [trajs[0], moving], data.dataset.effects, vel) == (0, None)
    assert rest_samples(0, trajs, data.dataset.effects, vel) == (0, None)
    n, held = rest_samples(2, trajs, data.dataset.effects, vel)
    assert n == 2 and torch.equal(held.z, rest.z)
    with pytest.raises(ConfigError, match="train.rest_samples = 'some', expected auto or an integer >= 0"):
        rest_samples("some", trajs, data.dataset.effects, vel)

    run = tmp_path / "rest"
    run.mkdir()
    (run / "dataset.h5").symlink_to(out / "dataset.h5")
    train(_cfg(run, "train.epochs=1", "train.rest_samples=3"))
    assert _rows(run)[0]["loss"]


def test_rest_rollout_takes_the_models_own_drift_at_rest_back(trained, tmp_path):
    """train.rest_rollout H: the model's own rollout of the unloaded body over H steps; as many of
    its states as there are rest samples, spread over 1 .. H - 1, are paired with the rest state
    as target. 0 is off; a bad value, or no rest state, is a one-line error naming the key."""
    from thermognn.core.errors import ConfigError
    from thermognn.train.data import make_batch, rest_rollout_steps, rest_trajectory, velocity_columns
    from thermognn.train.loop import drifted_states

    assert rest_rollout_steps(0, 5) == (0, [])
    h, steps = rest_rollout_steps(10, 4)
    assert h == 10 and len(steps) == 4 and max(steps) == 9 and min(steps) == 1
    assert rest_rollout_steps(10, 1) == (10, [9])
    for bad in (1, -3, "long"):
        with pytest.raises(ConfigError, match=f"train.rest_rollout = {bad!r}, expected 0 .off. or an integer >= 2"):
            rest_rollout_steps(bad, 4)
    with pytest.raises(ConfigError, match="train.rest_rollout = 10 needs the rest state: train.rest_samples is 0") as err:
        rest_rollout_steps(10, 0)
    assert "\n" not in str(err.value)

    out, cfg, ckpt = trained
    model = model_from_checkpoint(load_checkpoint(ckpt))
    data = load_data(out / "dataset.h5", cfg.train.split, 0)
    trajs = data.of("train")
    rest = rest_trajectory(trajs, data.dataset.effects, velocity_columns(data.layout), steps=10)
    assert rest.z.shape == (11, *trajs[0].z.shape[1:]) and (rest.z == trajs[0].z[0]).all()
    assert not rest.force.any() and torch.allclose(rest.time[1:] - rest.time[:-1], trajs[0].time[1] - trajs[0].time[0])
    held = drifted_states(model, data.graph, [rest], data.dt)[0]                # [11, N, D]
    batch = make_batch(trajs + [rest], [(len(trajs), 9, 1)], data.graph, [t.z for t in trajs] + [held])
    assert torch.equal(batch.z, held[9]) and torch.equal(batch.z_next, trajs[0].z[0]) and not batch.f.any()

    run = tmp_path / "restroll"
    run.mkdir()
    (run / "dataset.h5").symlink_to(out / "dataset.h5")
    train(_cfg(run, "train.epochs=1", "train.rest_rollout=6"))
    assert _rows(run)[0]["loss"]
    with pytest.raises(ConfigError, match="train.rest_rollout = 6 needs the rest state"):
        train(_cfg(run / "none", "train.epochs=1", "train.rest_rollout=6", "train.rest_samples=0",
                   f"paths.dataset={run / 'dataset.h5'}"))


def test_rest_stability_probes_the_deployed_step_at_rest(trained, tmp_path):
    """rest_growth: the growth of disturbances of the rest state of two sizes over one step of the
    model's own step map (``TIGNN.step``), and the power iterations' next directions (unit norm,
    free entries only); train.rest_stability with two probe sizes logs the growth per epoch and
    keeps a direction per size; bad weights, sizes and intervals, or no rest state, are
    one-line errors."""
    from thermognn.core.errors import ConfigError
    from thermognn.train.data import rest_trajectory, velocity_columns
    from thermognn.train.loop import STABILITY_PROBE, rest_growth

    out, cfg, ckpt = trained
    model = model_from_checkpoint(load_checkpoint(ckpt)).double()
    data = load_data(out / "dataset.h5", cfg.train.split, 0, torch.float64)
    g = data.graph
    rest = rest_trajectory(data.of("train"), data.dataset.effects, velocity_columns(data.layout))
    z0, f, dt = rest.z[0], rest.force[0], torch.tensor(data.dt, dtype=torch.float64)
    free = model.free_entries(g.node_type, z0)
    direction = torch.randn((2, *z0.shape), generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    growth, nxt = rest_growth(model, rest, g, data.dt, direction, [STABILITY_PROBE, 30.0])   # both in one pass
    assert growth.shape == (2,) and nxt.shape == direction.shape
    scale = data.dt * model.dzdt_std
    for k, size in enumerate((STABILITY_PROBE, 30.0)):     # the small probe: the linear step; the large: a secant
        d = direction[k] * free
        d = d * size * float(free.sum()) ** 0.5 / d.norm()
        jd = (model.step(z0 + d * scale, f, g.edge_index, g.node_type, g.ref_pos, dt)
              - model.step(z0, f, g.edge_index, g.node_type, g.ref_pos, dt)) / scale
        assert float(growth[k]) == pytest.approx(float(jd.norm() / d.norm()), rel=1e-9)
        assert float(nxt[k].norm()) == pytest.approx(1.0) and not (nxt[k] * (1 - free)).any()
        assert torch.allclose(nxt[k], jd * free / (jd * free).norm())
    assert growth.requires_grad and not nxt.requires_grad

    run = tmp_path / "stable"
    run.mkdir()
    (run / "dataset.h5").symlink_to(out / "dataset.h5")
    train(_cfg(run, "train.epochs=1", "train.rest_stability=100", "train.rest_stability_probe=[0.3,30]",
               "train.rest_stability_every=2"))
    assert float(_rows(run)[0]["rest_growth"]) > 0
    state = load_checkpoint(last_path(run / "model.ckpt"))
    assert state["identity"]["rest_stability_probe"] == [0.3, 30]
    assert state["rest_direction"].shape == (2, *z0.shape)          # a power iteration per size
    for extra, match in ((("train.rest_stability=-1",), r"train.rest_stability = -1.0, expected 0 \(off\) or a weight > 0"),
                         (("train.rest_stability=1", "train.rest_samples=0"), "where there is a rest state"),
                         (("train.rest_stability=1", "train.rest_stability_probe=[3,0]"),
                          r"train.rest_stability_probe = \[3, 0\], expected a probe size > 0 or a list of up to 8"),
                         (("train.rest_stability=1", "train.rest_stability_probe=-1"),
                          r"train.rest_stability_probe = -1, expected a probe size > 0"),
                         (("train.rest_stability=1", "train.rest_stability_every=0"),
                          r"train.rest_stability_every = 0, expected an integer >= 1")):
        with pytest.raises(ConfigError, match=match):
            train(_cfg(run / "bad", "train.epochs=1", *extra, f"paths.dataset={run / 'dataset.h5'}"))


def test_evaluate_steps_a_trained_model_another_way(trained, tmp_path):
    """``rollout.*`` re-steps the same learned dz/dt at evaluate time (no retraining): the midpoint
    rule leaves less energy drift than the Euler step the model was trained with, the summary says
    which step ran, and bad values are one-line errors naming the key."""
    from thermognn.core.errors import ConfigError
    from thermognn.train import evaluate

    out, cfg, _ = trained
    euler = evaluate(_cfg(out, f"paths.eval_dir={tmp_path / 'euler'}"))
    mid = evaluate(_cfg(out, f"paths.eval_dir={tmp_path / 'mid'}", "rollout.integrator=midpoint",
                        "rollout.implicit_iterations=6"))
    assert mid["energy_balance"] < 0.2 * euler["energy_balance"], (mid, euler)
    assert all(math.isfinite(mid[g]) for g in ("q", "v", "sigma"))
    summary = (tmp_path / "mid" / "summary.md").read_text()
    assert "CPU, midpoint (6 sweeps), learned kinematics" in summary and "integrator midpoint (trained: euler)" in summary
    assert "overrides" not in (tmp_path / "euler" / "summary.md").read_text()
    assert load_checkpoint(out / "model.ckpt")["hparams"]["integrator"] == "euler"     # the checkpoint is untouched
    for bad, msg in (("rollout.integrator=rk4", "rollout.integrator = 'rk4', expected euler | midpoint"),
                     ("rollout.implicit_iterations=0", "rollout.implicit_iterations = 0, expected an integer >= 1"),
                     ("rollout.kinematics=rigid", "rollout.kinematics = 'rigid', expected auto | exact | learned")):
        with pytest.raises(ConfigError, match=msg.replace("|", r"\|")) as err:
            evaluate(_cfg(out, f"paths.eval_dir={tmp_path / 'bad'}", bad))
        assert "\n" not in str(err.value)


def test_evaluate_on_the_datasets_own_test_part(trained, tmp_path):
    """``train.eval_split=dataset`` rolls out the dataset's test part (a dataset grown since
    training) beside the checkpoint's training cases, and refuses, in one line, test trajectories
    the checkpoint trained or validated on; bad values name the key."""
    from thermognn.core.errors import ConfigError, DataError
    from thermognn.core.schema import Dataset
    from thermognn.train import evaluate
    from thermognn.train.data import split_names

    out, cfg, _ = trained
    stored = load_checkpoint(out / "model.ckpt")["split"]
    ds = Dataset(out / "dataset.h5")
    own = evaluate(_cfg(out, f"paths.eval_dir={tmp_path / 'own'}", "train.eval_split=dataset"))
    assert own["q"] == pytest.approx(evaluate(_cfg(out, f"paths.eval_dir={tmp_path / 'ckpt'}"))["q"], rel=1e-6)
    assert "the dataset's own test part (`train.eval_split=dataset`)" in (tmp_path / "own" / "summary.md").read_text()
    assert split_names(ds, cfg.train.split, 0)["test"] == stored["test"]
    other = split_names(ds, cfg.train.split, 3)["test"]        # another draw: its test cases were trained on
    assert set(other) & set(stored["train"] + stored["val"])
    with pytest.raises(DataError, match=r"train.eval_split=dataset: test trajectories .* were trained or validated "
                                        r"on by .*model.ckpt") as err:
        evaluate(_cfg(out, f"paths.eval_dir={tmp_path / 'leak'}", "train.eval_split=dataset", "seed=3"))
    assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match=r"train.eval_split = 'test', expected checkpoint \| dataset"):
        evaluate(_cfg(out, f"paths.eval_dir={tmp_path / 'bad'}", "train.eval_split=test"))


def test_rollout_overrides_accept_checkpoints_of_earlier_versions(trained):
    """A checkpoint written before ``exact_kinematics`` existed (no such hparam) may be re-stepped."""
    from omegaconf import OmegaConf

    from thermognn.train.checkpoint import with_rollout

    out, cfg, ckpt_path = trained
    ckpt = load_checkpoint(ckpt_path)
    ckpt["hparams"] = {k: v for k, v in ckpt["hparams"].items() if k != "exact_kinematics"}
    restepped, note = with_rollout(ckpt, OmegaConf.create({"rollout": {"integrator": "midpoint"}}))
    assert note == "integrator midpoint (trained: euler)"
    assert model_from_checkpoint(restepped).integrator == "midpoint"
    assert with_rollout(ckpt, OmegaConf.create({"rollout": {"kinematics": "learned"}}))[1] == ""


def test_linear_prior_settings_and_datasets_it_cannot_use(trained, tmp_path):
    """model.prior=linear (thermognn/train/hybrid.py): one-line errors for a wrong value, a dataset
    without linearised FE operators (the analytic oscillator) and rollout overrides, which do
    not apply to its Newmark step."""
    from thermognn.core.errors import ConfigError
    from thermognn.train.checkpoint import model_step, with_rollout

    out, _, _ = trained
    data = [f"paths.dataset={out / 'dataset.h5'}", f"paths.checkpoint={tmp_path / 'model.ckpt'}"]
    with pytest.raises(ConfigError, match="model.prior = 'nonlinear', expected none | linear"):
        train(_cfg(tmp_path, *data, "model.prior=nonlinear"))
    with pytest.raises(DataError, match=r"dataset.h5: no linearised FE operators \(/linear\) for model.prior = linear"):
        train(_cfg(tmp_path, *data, "model=linear_prior"))
    with pytest.raises(ConfigError, match="model.prior_sweeps = 0, expected an integer >= 1"):
        train(_cfg(tmp_path, *data, "model=linear_prior", "model.prior_sweeps=0"))
    with pytest.raises(ConfigError, match=r"model.prior_order = 3, expected 1 \| 2"):
        train(_cfg(tmp_path, *data, "model=linear_prior", "model.prior_order=3"))
    with pytest.raises(ConfigError, match=r"model.prior_relax = 'maybe', expected true \| false"):
        train(_cfg(tmp_path, *data, "model=linear_prior", "model.prior_relax=maybe"))
    # the schedule is checked before any dataset is read (this one does not exist)
    nowhere = [f"paths.dataset={tmp_path / 'none.h5'}", f"paths.checkpoint={tmp_path / 'model.ckpt'}"]
    with pytest.raises(ConfigError, match=r"train.rollout_window = -1, expected >= 0 \(0: whole rollouts\)"):
        train(_cfg(tmp_path, *nowhere, "model=linear_prior", "train.rollout_window=-1"))
    with pytest.raises(ConfigError, match=r"train.rollout_scale = 'own', expected one of: data \| trajectory"):
        train(_cfg(tmp_path, *nowhere, "model=linear_prior", "train.rollout_scale=own"))
    ckpt = {"prior": {"kind": "linear", "sweeps": 1, "positions_only": True}, "hparams": {}}
    with pytest.raises(ConfigError, match="rollout.integrator: a model.prior=linear model steps with"):
        with_rollout(ckpt, _cfg(tmp_path, "rollout.integrator=midpoint"))
    # rollout.prior_*: only a law prior's law is stepped another way, as model.prior_* would be
    with pytest.raises(ConfigError, match="rollout.prior_tangent: the checkpoint's prior is not the data's law"):
        with_rollout(ckpt, _cfg(tmp_path, "rollout.prior_tangent=kept"))
    with pytest.raises(ConfigError, match="rollout.prior_newton_max: only a model=law_prior model steps the data's law"):
        with_rollout(load_checkpoint(trained[2]), _cfg(tmp_path, "rollout.prior_newton_max=8"))
    law = {**ckpt, "prior": {**ckpt["prior"], "law": 1}, "config": ""}
    with pytest.raises(ConfigError, match=r"rollout.prior_tangent = kept needs model.prior_law = true and "
                                          r"rollout.prior_newton_max > rollout.prior_newton \(= 1\)"):
        with_rollout(law, _cfg(tmp_path, "rollout.prior_tangent=kept"))
    restepped, note = with_rollout(law, _cfg(tmp_path, "rollout.prior_newton_max=8", "rollout.prior_newton_rtol=1e-6",
                                             "rollout.prior_step_cuts=2"))
    assert restepped["prior"] == {**law["prior"], "law_max": 8, "law_rtol": 1e-6, "law_cuts": 2}
    assert note == ("the law prior's step 1 to 8 Newton iterations to 1e-06, cut down to Δt/4 "
                    "(trained: 1 Newton iteration)")
    assert with_rollout(law, _cfg(tmp_path, "rollout.prior_newton=1"))[1] == ""          # as trained
    # rollout.remainders: a prior model without its network (the prior alone), combined with a law step
    alone, note = with_rollout(law, _cfg(tmp_path, "rollout.remainders=zero", "rollout.prior_newton=2"))
    assert alone["prior"] == {**law["prior"], "law": 2, "remainders": "zero"} and "remainders" not in law["prior"]
    assert note == ("the law prior's step 2 Newton iterations (trained: 1 Newton iteration), "
                    "its remainders zero, the prior alone (trained: learned)")
    assert model_step(alone)["remainders"] == "zero" and "remainders" not in model_step(law)
    assert with_rollout(ckpt, _cfg(tmp_path, "rollout.remainders=learned"))[1] == ""     # as trained
    with pytest.raises(ConfigError, match=r"rollout.remainders = 'none', expected learned \| zero"):
        with_rollout(ckpt, _cfg(tmp_path, "rollout.remainders=none"))
    with pytest.raises(ConfigError, match="rollout.remainders = zero: only a model.prior=linear model"):
        with_rollout(load_checkpoint(trained[2]), _cfg(tmp_path, "rollout.remainders=zero"))
    from thermognn.train.hybrid import prior_settings
    kept = _cfg(tmp_path, "model=law_prior", "model.prior_newton_max=16", "model.prior_newton_rtol=1e-7",
                "model.prior_tangent=kept")                                            # the config's own key
    assert prior_settings(kept.model)["law_tangent"] == "kept"


def test_train_device_is_checked():
    """train.device: cpu | cuda | cuda:N | auto; anything else, or a GPU torch cannot see, is one line."""
    from thermognn.train.device import training_device

    assert training_device("cpu") == torch.device("cpu")
    assert training_device(None) == torch.device("cpu")
    assert training_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    for bad in ("tpu", "meta", "gpu0"):
        with pytest.raises(ConfigError, match=rf"train.device = '{bad}'.*expected cpu, cuda, cuda:N or auto"):
            training_device(bad)
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match=r"train.device = 'cuda', but torch sees no CUDA GPU here"):
            training_device("cuda")


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without a GPU")
def test_training_on_a_missing_gpu_fails_in_one_line(tmp_path):
    write_oscillator_dataset(tmp_path / "dataset.h5", n_trajectories=4, steps=4)
    with pytest.raises(ConfigError, match="train.device = 'cuda', but torch sees no CUDA GPU"):
        train(_cfg(tmp_path, "train.epochs=1", "train.device=cuda"))
    assert not (tmp_path / "model.ckpt").exists()


def test_checkpoints_hold_cpu_tensors(tmp_path):
    """``on_cpu`` keeps a checkpoint's structure (ordered state dicts, lists, tuples, plain values);
    every tensor in it comes back on the CPU (from a GPU, where there is one)."""
    from collections import OrderedDict

    from thermognn.train.checkpoint import on_cpu

    where = "cuda" if torch.cuda.is_available() else "cpu"
    ckpt = {"state_dict": OrderedDict(w=torch.arange(3.0, device=where)), "history": [{"loss": 1.5}],
            "rng": (torch.ones(2, device=where), 7), "name": "x"}
    ckpt["state_dict"]._metadata = {"": {"version": 1}}
    out = on_cpu(ckpt)
    assert out["state_dict"]._metadata == {"": {"version": 1}}   # load_state_dict reads it
    assert type(out["state_dict"]) is OrderedDict and isinstance(out["rng"], tuple)
    assert out["state_dict"]["w"].device.type == "cpu" and out["rng"][0].device.type == "cpu"
    assert out["state_dict"]["w"].tolist() == [0.0, 1.0, 2.0] and out["rng"][1] == 7
    assert out["history"] == [{"loss": 1.5}] and out["name"] == "x"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (train.device=cuda)")
def test_training_on_the_gpu_follows_the_cpu(tmp_path):
    """The same run on the GPU and on the CPU: the same random draws (made on the CPU), so the
    epochs' losses and validation errors agree to float32 round-off; the GPU's checkpoint holds
    CPU tensors and rolls out on the CPU as its validation error says; resumed on the CPU, the
    GPU's interrupted run goes on."""
    runs = {}
    for dev in ("cpu", "cuda"):
        out = tmp_path / dev
        write_oscillator_dataset(out / "dataset.h5", n_trajectories=6, steps=10)
        ckpt = train(_cfg(out, "train.epochs=4", f"train.device={dev}"))
        runs[dev] = (_rows(out), load_checkpoint(ckpt))
    for a, b in zip(runs["cpu"][0], runs["cuda"][0], strict=True):
        for key in ("loss", "val_error"):
            if a[key]:
                assert float(b[key]) == pytest.approx(float(a[key]), rel=1e-2), (key, a, b)
    gpu = runs["cuda"][1]
    assert all(v.device.type == "cpu" for v in gpu["state_dict"].values())
    model = model_from_checkpoint(gpu)
    data = load_data(tmp_path / "cuda" / "dataset.h5", [0.8, 0.1, 0.1], 0, torch.float32)
    t = data.of("val")[0]
    pred = rollout(model, data.graph, t.z[0], t.force, data.dataset.dt)
    assert torch.isfinite(pred).all()
    # the GPU's run, 2 epochs more on the CPU from its model.last.ckpt
    train(_cfg(tmp_path / "cuda", "train.epochs=6", "train.device=cpu"))
    assert [int(r["epoch"]) for r in _rows(tmp_path / "cuda")] == [1, 2, 3, 4, 5, 6]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (train.device=cuda)")
def test_training_windows_in_the_mirrors_on_the_gpu_follow_the_cpu(tmp_path):
    """``train.window_steps`` and ``train.symmetry_augment`` draw their tilings and mirror frames
    from CPU generators whatever ``train.device`` (a CPU generator cannot fill a GPU tensor), so the
    same fine-tune on the GPU and on the CPU sees the same windows in the same mirrors: its losses
    and validation errors agree to float32 round-off."""
    write_oscillator_dataset(tmp_path / "dataset.h5", n_trajectories=6, steps=6)
    data = f"paths.dataset={tmp_path / 'dataset.h5'}"
    init = train(_cfg(tmp_path / "init", "train.epochs=1", data))
    rows = {}
    for dev in ("cpu", "cuda"):
        train(_cfg(tmp_path / dev, "train.epochs=2", "train.window_steps=3", "train.symmetry_augment=true",
                   "train.batch_size=2", f"train.init={init}", f"train.device={dev}", data))
        rows[dev] = _rows(tmp_path / dev)
    assert len(rows["cuda"]) == 2
    for a, b in zip(rows["cpu"], rows["cuda"], strict=True):
        for key in ("loss", "val_error"):
            if a[key]:
                assert float(b[key]) == pytest.approx(float(a[key]), rel=1e-2), (key, a, b)


def test_rate_gradient_term_weighs_the_errors_variation_across_edges(tmp_path):
    """``train.rate_gradient_weight``: the one-step rate error's differences across the mesh edges,
    relative to the target's own. An error the same at every node has none (a stress read off the
    positions, a strain, does not feel it); one alternating from node to node has the largest; edges
    between imposed (clamped) entries do not count. Training with it runs; bad weights are refused."""
    from omegaconf import OmegaConf

    from thermognn.train.loop import rate_gradient_error, rate_gradient_weight

    edges = torch.tensor([[0, 1, 1, 2, 2, 3], [1, 0, 2, 1, 3, 2]])           # a chain of 4 nodes
    target = torch.tensor([[0.0], [1.0], [2.0], [3.0]])                          # differences of 1 on every edge
    free = torch.ones(4, 1)
    assert float(rate_gradient_error(target + 0.5, target, free, edges)) == 0.0
    alternating = target + torch.tensor([[0.1], [-0.1], [0.1], [-0.1]])
    assert math.isclose(float(rate_gradient_error(alternating, target, free, edges)), 0.2 ** 2, rel_tol=1e-5)
    clamped = torch.tensor([[0.0], [0.0], [1.0], [1.0]])                        # nodes 0, 1 imposed
    assert math.isclose(float(rate_gradient_error(alternating, target, clamped, edges)),
                        (2 * 0.1 ** 2 + 2 * 0.2 ** 2) / 4, rel_tol=1e-5)   # edge 0-1 not counted
    assert rate_gradient_weight(OmegaConf.create({})) == 0.0
    for bad in (-1, "much", True, math.inf):
        with pytest.raises(ConfigError, match=rf"^train.rate_gradient_weight = {bad!r}, expected a number >= 0"):
            rate_gradient_weight(OmegaConf.create({"rate_gradient_weight": bad}))
    write_oscillator_dataset(tmp_path / "dataset.h5", n_trajectories=4, steps=6)
    ckpt = load_checkpoint(train(_cfg(tmp_path, "train.epochs=2", "train.rate_gradient_weight=1.0")))
    assert ckpt["epoch"] == 2 and all(math.isfinite(float(r["loss"])) for r in _rows(tmp_path))
    with pytest.raises(ConfigError, match=r"train.rate_gradient_weight: .* model.prior=linear"):
        train(_cfg(tmp_path / "lp", "model=linear_prior", "train.rate_gradient_weight=1.0",
                   f"paths.dataset={tmp_path / 'dataset.h5'}"))


def test_training_windows_roll_the_model_out_and_back_propagate_through_its_steps(tmp_path):
    """``train.window_steps``: windows tile every trajectory from a random offset to its end; a
    one-step window's loss is the one-step MSE (no noise); the rates are differentiable in a state
    that carries a graph only when asked (``through_state``), so the window back-propagates through
    the model's own earlier steps while one-step training and rollouts cut them off as before;
    training on windows runs, and bad settings are refused in one line."""
    from omegaconf import OmegaConf

    from thermognn.train.data import make_batch, make_window_batch, state_images, window_starts
    from thermognn.train.loop import (edge_step_scale, step_loss, window_column_weights, window_loss,
                                      window_steps)

    write_oscillator_dataset(tmp_path / "dataset.h5", n_trajectories=4, steps=6)
    data = load_data(tmp_path / "dataset.h5", [0.5, 0.25, 0.25], 0, torch.float32)
    trajs = data.of("train")
    for w in (1, 2, 4, 6):
        items = window_starts(trajs, w, torch.Generator().manual_seed(w))
        for i in range(len(trajs)):
            starts = [s for j, s in items if j == i]
            assert 1 <= len(starts) <= -(-6 // w) and starts[0] < w and starts[-1] == 6 - w   # from o to the end
            assert all(0 < b - a <= w for a, b in zip(starts, starts[1:]))                  # no gaps between
    ckpt = load_checkpoint(train(_cfg(tmp_path / "a", "train.epochs=1", "model.kinematics=learned",
                                      f"paths.dataset={tmp_path / 'dataset.h5'}")))
    model = model_from_checkpoint(ckpt).train()
    one = make_window_batch(trajs, [(0, 2), (1, 3)], data.graph, 1)
    pairs = make_batch(trajs, [(0, 2), (1, 3)], data.graph)
    assert one.z.shape == (2, 2 * data.graph.n_nodes, data.layout.dim)
    ones = torch.ones(data.layout.dim)
    scale = edge_step_scale(trajs, data.graph.edge_index, data.dt * model.dzdt_std.detach())
    _, win, _ = window_loss(model, one, data.dt, ones, scale, 1.0, 1.0)
    _, mse, _ = step_loss(model, pairs, data.dt, 0.0, torch.Generator(), 1.0, 1.0)
    assert math.isclose(win, mse, rel_tol=1e-4)
    z = one.z[0].clone().requires_grad_(True) * 1.0                  # a state carrying a graph
    for through, reached in ((True, True), (False, False)):
        rate = model.rates(z, one.f[1], one.edge_index, one.node_type, one.pos, True, through)[0]
        grad = torch.autograd.grad(rate.sum(), z, allow_unused=True, retain_graph=True)[0]
        assert (grad is not None and float(grad.abs().sum()) > 0) == reached
    two = make_window_batch(trajs, [(0, 0)], data.graph, 2)
    loss, _, _ = window_loss(model, two, data.dt, ones, scale, 1.0, 1.0, gradient_weight=1.0)
    loss.backward()
    assert all(p.grad is None or torch.isfinite(p.grad).all() for p in model.parameters())
    weights = window_column_weights(OmegaConf.create({"window_weights": {"v": 0.5}}), data.layout, ones)
    assert weights[data.layout.slice("v")].tolist() == [0.5] * 3 and float(weights.sum()) == data.layout.dim - 1.5

    # a fine-tune (from scratch the model's own rollouts run away before it has learned a step)
    mirror = state_images(data.graph, data.layout, None)[-1]          # a window seen in a mirror, as a pair is
    seen, seen_pair = (make_window_batch(trajs, [(1, 4)], data.graph, 1, [mirror]),
                       make_batch(trajs, [(1, 4)], data.graph, frames=[mirror]))
    assert torch.equal(seen.z[0], seen_pair.z) and torch.equal(seen.z[1], seen_pair.z_next)
    assert torch.equal(seen.f[1], seen_pair.f)
    out = train(_cfg(tmp_path / "w", "train.epochs=2", "train.window_steps=3", "train.rate_gradient_weight=0.5",
                     "model.kinematics=learned", "train.lr=3e-4",
                     f"train.init={tmp_path / 'a' / 'model.ckpt'}", f"paths.dataset={tmp_path / 'dataset.h5'}"))
    rows = _rows(tmp_path / "w")
    assert load_checkpoint(out)["epoch"] == 2 and all(float(r["data_loss"]) < 100 for r in rows), rows
    assert window_steps(OmegaConf.create({})) == 0
    for bad in (-1, 2.5, True, "five"):
        with pytest.raises(ConfigError, match=rf"^train.window_steps = {bad!r}, expected 0"):
            window_steps(OmegaConf.create({"window_steps": bad}))
    for bad, says in (({"tau": 1}, r"unknown state group 'tau'"), ({"v": -1}, r"train.window_weights.v = -1"),
                      ({n: 0 for n in data.layout.names}, r"every group weighs 0"), ([1, 2], r"expected a mapping")):
        with pytest.raises(ConfigError, match=says):
            window_column_weights(OmegaConf.create({"window_weights": bad}), data.layout, ones)
    with pytest.raises(ConfigError, match=r"^train.window_steps = 9: longer than the shortest training trajectory \(6 steps\)"):
        train(_cfg(tmp_path / "x", "train.window_steps=9", f"paths.dataset={tmp_path / 'dataset.h5'}"))
    with pytest.raises(ConfigError, match=r"train.window_steps: windows step by the Euler rule"):
        train(_cfg(tmp_path / "y", "train.window_steps=2", "model.integrator=midpoint",
                   f"paths.dataset={tmp_path / 'dataset.h5'}"))
    with pytest.raises(ConfigError, match=r"train.window_steps: .* model.prior=linear"):
        train(_cfg(tmp_path / "lp", "model=linear_prior", "train.window_steps=2",
                   f"paths.dataset={tmp_path / 'dataset.h5'}"))


def test_window_readout_term_weighs_the_stress_read_off_the_predicted_positions(tmp_path, capsys):
    """``train.window_readout_weight``: along each window the init's stress readout (fixed) reads the
    stress off the predicted positions and loads, and its error against the true stress, in a
    typical step's change, adds weight x its mean square over the free stress entries to the data
    term, as a rollout of the window computes it; its gradient reaches the network through the
    positions; a fine-tune with it runs and refits the readout; bad settings are refused in one line."""
    from thermognn.train.data import make_window_batch
    from thermognn.train.loop import edge_step_scale, window_loss

    write_oscillator_dataset(tmp_path / "dataset.h5", n_trajectories=12, steps=8)
    data_arg = f"paths.dataset={tmp_path / 'dataset.h5'}"
    small = ("model.hidden=16", "model.message_passing=2", "model.kinematics=exact", "model.stress_readout=1", data_arg)
    init = train(_cfg(tmp_path / "init", "train.epochs=1", *small))
    model = model_from_checkpoint(load_checkpoint(init)).train()
    readout = model.readout
    data = load_data(tmp_path / "dataset.h5", [0.8, 0.1, 0.1], 0, torch.float32)
    trajs = data.of("train")
    ones = torch.ones(data.layout.dim)
    scale = edge_step_scale(trajs, data.graph.edge_index, data.dt * model.dzdt_std.detach())
    items, W = [(0, 1), (2, 4)], 3
    batch = make_window_batch(trajs, items, data.graph, W)
    off_loss, off, _ = window_loss(model, batch, data.dt, ones, scale, 1.0, 0.0)
    on_loss, on, _ = window_loss(model, batch, data.dt, ones, scale, 1.0, 0.0, readout=readout, readout_weight=2.0)
    sig = list(range(*data.layout.slice("sigma").indices(data.layout.dim)))
    step = (data.dt * model.dzdt_std.detach())[sig]
    model.use_readout = False                          # the network's own states, read below
    X = data.graph.ref_pos
    per_step = torch.zeros(W)
    free = model.free_entries(data.graph.node_type, trajs[0].z[0])[:, sig]
    for i, s in items:                                 # each window rolled out on its own
        t = trajs[i]
        pred = rollout(model, data.graph, t.z[s], t.force[s: s + W + 1], data.dt)         # [W+1, N, D]
        with torch.no_grad():
            for k in range(1, W + 1):
                r = (readout(pred[k, :, :3] - X, t.force[s + k]) - t.z[s + k][:, sig]) / step
                per_step[k - 1] += (r.pow(2) * free).sum()
    expected = 2.0 * float(per_step.sum()) / (W * len(items) * float(free.sum()))
    assert on - off == pytest.approx(expected, rel=1e-3) and expected > 0
    (on_loss - off_loss).backward()                    # the readout term alone
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert grads and any(float(g.abs().sum()) > 0 for g in grads) and all(torch.isfinite(g).all() for g in grads)
    assert not any(p.requires_grad for p in readout.parameters())
    # validation reads the stress off as the product's rollouts report it (TIGNN.read_stress)
    val = data.of("val")
    model.eval()
    own = validation_error(model, data.graph, val, data.layout, data.dt)
    read = validation_error(model, data.graph, val, data.layout, data.dt, readout)
    model.use_readout = True
    assert read == pytest.approx(validation_error(model, data.graph, val, data.layout, data.dt), rel=1e-6)
    assert read != pytest.approx(own, rel=1e-3)

    capsys.readouterr()
    ckpt = load_checkpoint(train(_cfg(tmp_path / "ft", "train.epochs=1", "train.window_steps=2",
                                      "train.window_readout_weight=1.0", f"train.init={init}", *small)))
    assert "weighed 1 in the window loss (train.window_readout_weight), and the validation" in capsys.readouterr().out
    assert ckpt["epoch"] == 1 and ckpt["hparams"]["stress_readout"]["hops"] == 1
    assert all(math.isfinite(float(r["loss"])) for r in _rows(tmp_path / "ft"))
    for bad, shown in (("yes", "'yes'"), ("-1.0", "-1.0"), ("inf", "inf")):
        with pytest.raises(ConfigError, match=rf"^train.window_readout_weight = {shown}, expected a number >= 0"):
            train(_cfg(tmp_path / "x", "train.window_steps=2", f"train.window_readout_weight={bad}", f"train.init={init}", *small))
    refusals = ((("train.window_readout_weight=1", f"train.init={init}", *small), "set train.window_steps >= 1"),
                (("train.window_readout_weight=1", "train.window_steps=2", f"train.init={init}",
                  *(a for a in small if "stress_readout" not in a)),
                 "set model.stress_readout"),
                (("train.window_readout_weight=1", "train.window_steps=2", *small), "needs train.init with a fitted stress readout"))
    for args, says in refusals:
        with pytest.raises(ConfigError, match=rf"^train.window_readout_weight = 1.*{says}"):
            train(_cfg(tmp_path / "y", *args))


def test_training_windows_resume_within_an_epoch_as_if_uninterrupted(tmp_path, monkeypatch):
    """``train.window_steps`` with ``train.checkpoint_minutes``: an epoch's tiling and mirrors come
    from (seed, epoch) alone, so a window run interrupted within its second epoch goes on at its
    next batch and ends with the uninterrupted run's weights and metrics (rest windows included)."""
    import thermognn.train.loop as loop

    write_oscillator_dataset(tmp_path / "dataset.h5", n_trajectories=4, steps=6)
    data = f"paths.dataset={tmp_path / 'dataset.h5'}"
    train(_cfg(tmp_path / "init", "train.epochs=1", "model.kinematics=learned", data))
    extra = ("train.epochs=2", "train.window_steps=2", "model.kinematics=learned", "train.lr=3e-4",
             "train.batch_size=2", "train.val_every=1", "train.rate_gradient_weight=0.5",
             f"train.init={tmp_path / 'init' / 'model.ckpt'}", data, "train.checkpoint_minutes=1e-9")
    ref = load_checkpoint(last_path(train(_cfg(tmp_path / "a", *extra))))

    real_save = loop.save_checkpoint

    def interrupt(state, path):                 # KeyboardInterrupt right after epoch 2's first batch
        real_save(state, path)
        if "mid_epoch" in state and len(state["history"]) == 1 and state["mid_epoch"]["batch"] == 1:
            raise KeyboardInterrupt

    monkeypatch.setattr(loop, "save_checkpoint", interrupt)
    with pytest.raises(KeyboardInterrupt):
        train(_cfg(tmp_path / "b", *extra))
    monkeypatch.setattr(loop, "save_checkpoint", real_save)
    got = load_checkpoint(last_path(train(_cfg(tmp_path / "b", *extra))))
    for a, b in zip(ref["history"], got["history"]):
        assert {k: v for k, v in a.items() if k != "seconds"} == {k: v for k, v in b.items() if k != "seconds"}
    for k in ref["state_dict"]:
        assert torch.allclose(ref["state_dict"][k], got["state_dict"][k], rtol=1e-5, atol=1e-7), k
