"""Haptic device plugins, found through the entry-point group ``thermognn.devices``.

Imports neither torch nor dolfinx (numpy and ctypes only), so the 1 kHz haptic process can
load a plugin without pulling in the learning stack. The interface is
:class:`thermognn.devices.base.Device`; SI units inside (m, m/s, N), each plugin converts.
"""

from __future__ import annotations

import importlib.metadata

from thermognn.core.errors import DeviceError

GROUP = "thermognn.devices"


def available() -> dict[str, importlib.metadata.EntryPoint]:
    """Installed device plugins by name (entry points of the group ``thermognn.devices``)."""
    return {ep.name: ep for ep in importlib.metadata.entry_points(group=GROUP)}


def load(name: str) -> type:
    """The plugin class registered as ``name``; DeviceError (one line) lists the known names."""
    plugins = available()
    if name not in plugins:
        raise DeviceError(f"serve.device: unknown device plugin '{name}', expected one of {sorted(plugins)}")
    try:
        return plugins[name].load()
    except (ImportError, AttributeError) as exc:
        raise DeviceError(f"serve.device: plugin '{name}' ({plugins[name].value}) cannot be imported: {exc}") from None


__all__ = ["available", "load", "DeviceError", "GROUP"]
