"""Learned model stage: TIGNN (thermodynamics-informed graph network), training and evaluation.

Entry points (called by the CLI with the composed config):

- ``train(cfg) -> Path``    trains on ``cfg.paths.dataset``, writes ``cfg.paths.checkpoint``
- ``evaluate(cfg) -> dict`` rolls out the test trajectories, writes figures/CSV into ``cfg.paths.eval_dir``

Imports torch and torch_geometric, never dolfinx.
"""

from __future__ import annotations

from pathlib import Path


def train(cfg) -> Path:
    """See ``thermognn.train.loop.train``."""
    from .loop import train as _train

    return _train(cfg)


def evaluate(cfg) -> dict:
    """See ``thermognn.train.evaluation.evaluate``."""
    from .evaluation import evaluate as _evaluate

    return _evaluate(cfg)


__all__ = ["train", "evaluate"]
