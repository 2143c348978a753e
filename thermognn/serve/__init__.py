"""serve stage: the 1 kHz haptic loop on an exported model (two processes, shared memory).

``serve(cfg) -> dict`` (``thermognn.serve.runner``). Importing this package does not import
torch: the haptic process (``thermognn.serve.loop``) never does; the physics process
(``thermognn.serve.physics``) imports it inside its entry function.
"""

from __future__ import annotations


def serve(cfg, monitor=None) -> dict:
    """Run a haptic session; see :func:`thermognn.serve.runner.serve`."""
    from .runner import serve as _serve
    return _serve(cfg, monitor=monitor)


__all__ = ["serve"]
