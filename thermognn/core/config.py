"""Hydra configuration, composed with the compose API (no @hydra.main, no working-dir change).

Overrides are the trailing arguments of every CLI command, e.g.
``thermognn train scene=block train.epochs=5``. The resolved config is stored in every
output (HDF5 attribute, checkpoint, exported model) as YAML.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

from omegaconf import DictConfig, OmegaConf

from .errors import ConfigError

#: ``conf/`` at the project root; ``THERMOGNN_CONF`` points elsewhere.
CONF_DIR = Path(os.environ.get("THERMOGNN_CONF", Path(__file__).resolve().parents[2] / "conf"))
#: project root, against which relative paths in configs (``meshes/...``) resolve.
PROJECT_ROOT = Path(__file__).resolve().parents[2]


def load_config(overrides: Sequence[str] = (), config_name: str = "config") -> DictConfig:
    """Compose ``conf/<config_name>.yaml`` with ``overrides``; raise ConfigError on bad keys."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    if not CONF_DIR.is_dir():
        raise ConfigError(f"config directory {CONF_DIR} not found (set THERMOGNN_CONF)")
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose(config_name=config_name, overrides=list(overrides))
    except (HydraException, OmegaConfBaseException) as exc:
        raise ConfigError(f"config: {_one_line(str(exc))}") from None
    finally:
        GlobalHydra.instance().clear()
    try:
        OmegaConf.resolve(cfg)
    except OmegaConfBaseException as exc:
        raise ConfigError(f"config: {str(exc).splitlines()[0]}") from None
    OmegaConf.set_struct(cfg, True)  # later reads of unknown keys fail loudly
    return cfg


def _one_line(message: str) -> str:
    """Condense Hydra's multi-line composition errors into one line naming the key and what exists."""
    import re

    lines = [ln.strip() for ln in message.strip().splitlines() if ln.strip()]
    if not lines:
        return "composition failed"
    m = re.search(r"Could not override '([^']+)'", lines[0])
    if m:
        key = m.group(1)
        return f"unknown key '{key}' (check the spelling against conf/, or prefix '+' to add a new key)"
    m = re.search(r"Could not find '([^/']+)/([^']+)'", lines[0])
    if m:
        group, option = m.groups()
        options = []
        for ln in lines[1:]:
            if ln.startswith("Config search"):
                break
            if not ln.startswith("Available"):
                options.append(ln)
        return f"no '{option}' in config group '{group}'; available: {', '.join(options)}"
    return lines[0]


def to_yaml(cfg: DictConfig) -> str:
    return OmegaConf.to_yaml(cfg, resolve=True)


def from_yaml(text: str) -> DictConfig:
    return OmegaConf.create(text)


def project_path(p: str | os.PathLike) -> Path:
    """Resolve a config path: absolute as is, else relative to cwd if it exists, else to the project root."""
    p = Path(p)
    if p.is_absolute() or p.exists():
        return p
    return PROJECT_ROOT / p


#: HHT's dissipation h (α = −h) a scene may declare for serving: 0 to 1/3, where HHT is unconditionally
#: stable (``thermognn.train.law_prior.MAX_HHT``)
MAX_SERVED_HHT = 1.0 / 3.0


def scene_served_hht(name: str, scene=None) -> float | None:
    """The HHT dissipation h (α = −h) that scene ``name`` declares for serving its law
    (``scene.time.served_hht``), read from ``scene`` (a composed scene config) where it is that
    scene, so that ``scene.time.served_hht=null`` on the command line turns it off, else from
    ``conf/scene/<name>.yaml``; None where the scene declares none (or 0) or is not found.
    ``export`` steps a law model of the scene so, ``evaluate`` reports its errors so stepped beside
    the data's rule's, ``serve`` notes a law served without it. A served body is pressed for
    minutes where its data ran 0.6 s: the liver's law at its data's undamped Newmark rule rang up
    in its smallest cells and collapsed within 30 s of the sim press, at HHT 0.02 it held 60 s,
    1.11 % from its data against 0.563 % (docs/accuracy.md, sessions 94–95). ConfigError (one
    line) for a value that is not a number 0 to 1/3."""
    if scene is None or str(OmegaConf.select(scene, "name", default="")) != name:
        path = CONF_DIR / "scene" / f"{name}.yaml"
        if not name or not path.is_file():
            return None
        scene = OmegaConf.load(path)
    h = OmegaConf.select(scene, "time.served_hht", default=None)
    if h is None:
        return None
    if isinstance(h, bool) or not isinstance(h, (int, float)) or not 0.0 <= float(h) <= MAX_SERVED_HHT:
        raise ConfigError(f"scene.time.served_hht = {h!r} (scene '{name}'): expected null or a number 0 to 1/3 "
                          f"(HHT's dissipation, α = -served_hht, that export gives a law model of the scene)")
    return float(h) or None
