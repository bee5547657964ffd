"""Reading a machine description file (:func:`load_config`) and the embedded default."""
from __future__ import annotations

import os
import tomllib
from importlib import resources
from pathlib import Path

from ..errors import ConfigError
from .machine import MachineConfig, parse_config

#: path of the embedded default machine (simulated drives, no root needed)
DEFAULT_CONFIG_NAME = "default.toml"


def default_config_path() -> Path:
    """Path of ``config/default.toml`` (repository) or the packaged copy."""
    repo = Path(__file__).resolve().parents[2] / "config" / DEFAULT_CONFIG_NAME
    if repo.exists():
        return repo
    return Path(str(resources.files("hexacnc") / "data" / DEFAULT_CONFIG_NAME))


def read_toml(p: Path, what: str = "machine description") -> dict:
    """The TOML document of file ``p``; ConfigError naming the file and ``what`` it should hold."""
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read {what}: {exc.strerror or exc}") from exc
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from exc


def load_config(path: str | os.PathLike | None = None) -> MachineConfig:
    """Read and check a machine description; ``None`` gives the embedded default."""
    p = Path(path) if path is not None else default_config_path()
    return parse_config(read_toml(p), str(p))
