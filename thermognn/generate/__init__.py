"""Stage 1: finite-element simulations (dolfinx) -> HDF5 dataset. Never imports torch.

``generate(cfg)`` is the entry point; the FE core lives in ``materials`` (laws), ``solid``
(weak forms, Newton, time stepping), ``meshing`` (gmsh/meshio -> dolfinx), ``scene`` (node
types, loads) and ``continuation`` (snap-through paths).
"""

from __future__ import annotations


def generate(cfg):
    """Simulate ``cfg.scene`` and write ``cfg.paths.dataset``; returns its path."""
    if cfg.scene.get("imported", False):  # e.g. tignn_beam: its dataset comes from `thermognn import`
        from thermognn.core.errors import ConfigError

        raise ConfigError(f"scene '{cfg.scene.name}' is imported, not generated: run `thermognn import "
                          f"{cfg.scene.name.split('_')[0]}`")
    from .pipeline import generate as _generate

    return _generate(cfg)


__all__ = ["generate"]
