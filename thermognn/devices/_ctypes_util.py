"""Finding and loading vendor shared libraries (ctypes), with one-line DeviceErrors."""

from __future__ import annotations

import ctypes
import ctypes.util
import os

from thermognn.core.errors import DeviceError


def load_vendor_library(env_var: str, names: tuple[str, ...], explicit: str | None, what: str, install: str) -> ctypes.CDLL:
    """Load ``explicit`` path, else ``$env_var``, else the first of ``names`` the loader finds.

    DeviceError (one line) says what to install or set when none loads.
    """
    candidates: list[str] = []
    if explicit:
        candidates.append(str(explicit))
    elif os.environ.get(env_var):
        candidates.append(os.environ[env_var])
    else:
        for name in names:
            found = ctypes.util.find_library(name)
            candidates.append(found or (name if name.endswith(".so") or ".so." in name else f"lib{name}.so"))
    errors = []
    for path in candidates:
        try:
            return ctypes.CDLL(path)
        except OSError as exc:
            errors.append(f"{path}: {exc}")
    raise DeviceError(f"{what}: vendor library not found ({'; '.join(errors) or 'no candidates'}); {install}, "
                      f"or set {env_var}=/path/to/library")


def bind_signatures(lib: ctypes.CDLL, signatures: dict, what: str, install: str) -> ctypes.CDLL:
    """Set ``restype``/``argtypes`` of each vendor function ``{name: (restype, [argtypes])}``.

    DeviceError (one line) names the first function the library lacks and what to install.
    """
    for name, (restype, argtypes) in signatures.items():
        try:
            fn = getattr(lib, name)
        except AttributeError:
            raise DeviceError(f"{what}: library {lib._name} lacks {name}; {install}") from None
        fn.restype, fn.argtypes = restype, argtypes
    return lib
