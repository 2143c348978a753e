"""Atomic writes and provenance (software versions) shared by every stage."""

from __future__ import annotations

import contextlib
import importlib.metadata
import json
import os
import platform
import tempfile
from pathlib import Path
from typing import Iterator


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` only on success.

    The temporary file lives in the same directory (same file system) so the final
    ``os.replace`` is atomic. On any exception the temporary file is removed and
    ``path`` is left untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    umask = os.umask(0)
    os.umask(umask)
    try:
        yield tmp_path
        os.chmod(tmp_path, 0o666 & ~umask)  # mkstemp makes 0600; give the file the usual mode
        os.replace(tmp_path, path)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


def software_versions() -> dict[str, str]:
    """Versions of the packages that shape the results (only those installed)."""
    versions = {"python": platform.python_version()}
    for dist in ("thermognn", "numpy", "h5py", "torch", "torch_geometric", "fenics-dolfinx",
                 "hydra-core", "meshio"):
        with contextlib.suppress(importlib.metadata.PackageNotFoundError):
            versions[dist] = importlib.metadata.version(dist)
    with contextlib.suppress(Exception):  # Debian's dolfinx has no dist-info
        import sys
        if "dolfinx" in sys.modules:
            versions["dolfinx"] = sys.modules["dolfinx"].__version__
    return versions


def versions_json() -> str:
    return json.dumps(software_versions(), sort_keys=True)
