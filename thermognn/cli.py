"""The ``thermognn`` command line: one sub-command per pipeline stage.

Every stage command takes Hydra overrides as trailing arguments, e.g.::

    thermognn generate scene=block scene.loads.n_trajectories=5
    thermognn train train.epochs=5
    thermognn serve --device sim --duration 10

Stages are imported lazily, so ``generate`` never loads torch and ``serve`` never loads dolfinx.
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path
from typing import Callable, List, Optional

import typer

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Thermodynamics-informed GNNs from FE simulations of soft solids, served to haptic devices.")
import_app = typer.Typer(no_args_is_help=True, help="Convert external datasets into thermognn's HDF5 schema.")
app.add_typer(import_app, name="import")

OVERRIDES_HELP = "Hydra overrides, e.g. scene=block train.epochs=5 out=runs/x"


def _user_errors(fn: Callable) -> Callable:
    """Turn user errors into one line on stderr and exit code 2 (Ctrl-C: 130)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        from thermognn.core.errors import ThermoGNNError

        try:
            return fn(*args, **kwargs)
        except ThermoGNNError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None
        except KeyboardInterrupt:
            typer.echo("interrupted", err=True)
            raise typer.Exit(130) from None

    return wrapper


def _write_json(path: Path, data: dict) -> None:
    """Write a stage's figures as JSON (atomically), for scripts and `thermognn demo`."""
    import json

    from thermognn.core.io import atomic_path

    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=1, default=str))


def _config(overrides: Optional[List[str]], extra: Optional[List[str]] = None):
    from thermognn.core.config import load_config

    return load_config(list(overrides or []) + list(extra or []))


@app.command()
@_user_errors
def generate(overrides: Optional[List[str]] = typer.Argument(None, help=OVERRIDES_HELP)) -> None:
    """Stage 1: solve the scene's load cases with FEniCSx and write the HDF5 dataset (paths.dataset)."""
    cfg = _config(overrides)
    from thermognn.generate import generate as run

    path = run(cfg)
    typer.echo(f"dataset: {path}")


@app.command()
@_user_errors
def train(overrides: Optional[List[str]] = typer.Argument(None, help=OVERRIDES_HELP)) -> None:
    """Stage 2: train the GENERIC / Hamiltonian graph network on the dataset; write the checkpoint (paths.checkpoint).

    Resumes from the last checkpoint when one exists for the same configuration.
    """
    cfg = _config(overrides)
    from thermognn.train import train as run

    path = run(cfg)
    typer.echo(f"checkpoint: {path}")


@app.command()
@_user_errors
def evaluate(overrides: Optional[List[str]] = typer.Argument(None, help=OVERRIDES_HELP)) -> None:
    """Roll out the test trajectories and report relative RMSE per variable group (figures in paths.eval_dir)."""
    cfg = _config(overrides)
    from thermognn.train import evaluate as run

    _write_json(Path(cfg.paths.eval_dir) / "rrmse.json", run(cfg))


@app.command()
@_user_errors
def export(overrides: Optional[List[str]] = typer.Argument(None, help=OVERRIDES_HELP)) -> None:
    """Stage 3: write the checkpoint as TorchScript (paths.exported), checked against the eager model."""
    cfg = _config(overrides)
    from thermognn.export import export as run

    path = run(cfg)
    typer.echo(f"exported: {path}")


@app.command()
@_user_errors
def serve(
    overrides: Optional[List[str]] = typer.Argument(None, help=OVERRIDES_HELP),
    device: Optional[str] = typer.Option(None, "--device", "-d", help="device plugin (see `thermognn devices`)"),
    duration: Optional[float] = typer.Option(None, "--duration", help="seconds to run; <= 0 until Ctrl-C"),
) -> None:
    """Stage 4: the 1 kHz haptic loop: device position in, force out, the exported network stepping the body."""
    extra = []
    if device is not None:
        extra.append(f"serve.device={device}")
    if duration is not None:
        extra.append(f"serve.duration={duration}")
    cfg = _config(overrides, extra)
    from thermognn.serve import serve as run

    _write_json(Path(cfg.out) / "serve_summary.json", run(cfg))


@app.command()
@_user_errors
def devices() -> None:
    """List the haptic device plugins found through the `thermognn.devices` entry points."""
    from thermognn.devices import available

    found = available()
    if not found:
        typer.echo("no device plugins found (is thermognn installed?)")
    for name, ep in sorted(found.items()):
        typer.echo(f"{name:12s} {ep.value}")


@import_app.command("tignn")
@_user_errors
def import_tignn(
    source: Path = typer.Argument(Path("../shared/datasets/tignn_beam"), help="folder with beam_K.pt files"),
    out: Path = typer.Option(Path("runs/tignn_beam/dataset.h5"), "--out", help="HDF5 file to write"),
) -> None:
    """Convert the public TIGNN beam dataset (Hernández et al. 2022) into thermognn's HDF5 schema, loading it safely."""
    from thermognn.train.tignn_import import import_tignn as run

    path = run(source, out)
    typer.echo(f"dataset: {path}")


@app.command()
@_user_errors
def demo(
    out: Path = typer.Option(Path("runs/demo"), "--out", help="folder for every stage's output"),
    duration: float = typer.Option(5.0, "--duration", help="seconds of haptic serving"),
    overrides: Optional[List[str]] = typer.Argument(None, help=OVERRIDES_HELP),
) -> None:
    """The whole pipeline on the default scene: generate -> train -> evaluate -> export -> serve --device sim.

    Each stage runs as its own `thermognn` process, exactly as a user would type it, so the stages'
    dependencies stay apart (dolfinx and torch are never loaded into one process).
    """
    import json
    import subprocess
    import time

    from thermognn.core.config import load_config
    from thermognn.core.errors import ThermoGNNError

    common = [f"out={out}"] + list(overrides or [])
    cfg = load_config(common)  # bad overrides fail here, before any work
    stages = [("generate", []), ("train", []), ("evaluate", []), ("export", []),
              ("serve", ["--device", "sim", "--duration", str(duration)])]
    timings = {}
    for name, extra in stages:
        typer.secho(f"\n== {name} ==", bold=True)
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "thermognn.cli", name, *extra, *common])
        timings[name] = time.perf_counter() - t0
        if proc.returncode != 0:
            raise ThermoGNNError(f"demo: stage '{name}' failed (exit code {proc.returncode}); see its output above")

    typer.secho("\n== demo summary ==", bold=True)
    for name, seconds in timings.items():
        typer.echo(f"{name:9s} {seconds:8.1f} s")
    errors = json.loads((Path(cfg.paths.eval_dir) / "rrmse.json").read_text())
    extra = ("ms_per_step", "energy_balance")
    typer.echo("test RRMSE: " + ", ".join(f"{k} {v:.3g}" for k, v in errors.items() if k not in extra)
               + f" (network step {errors.get('ms_per_step', float('nan')):.1f} ms, energy balance "
               + f"{errors.get('energy_balance', float('nan')):.2g})")
    summary = json.loads((Path(cfg.out) / "serve_summary.json").read_text())
    keys = ("loop_rate_hz", "period_p50_ms", "period_p99_ms", "period_p999_ms", "worst_gap_ms",
            "physics_rate_hz", "max_force_N", "final_force_N")
    typer.echo("haptic loop: " + ", ".join(f"{k} {summary[k]:.4g}" for k in keys if k in summary))


def main() -> None:  # pragma: no cover - console entry
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
