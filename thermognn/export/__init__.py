"""Export stage: checkpoint -> TorchScript ``model.pt`` (needs only torch to load).

Entry point ``export(cfg) -> Path``; the file follows the "Exported model" contract in
docs/stages.md. Imports torch, never dolfinx.
"""

from __future__ import annotations

from pathlib import Path


def export(cfg) -> Path:
    """See ``thermognn.export.exporter.export``."""
    from .exporter import export as _export

    return _export(cfg)


__all__ = ["export"]
