"""Sensor-model files of the lab: a :class:`~synth.sensor.config.SensorConfig` JSON plus fit info.

A model file is ``SensorConfig.to_json()`` (``{"preset": {...}, "effects": [...]}``), so
``synth sequence --sensor model.json`` and :class:`SensorSimulator` read it directly; the lab
adds an optional ``"fit"`` object (gaps, fitted parameters, sequence, timings) and, for
``sensor fit``, the result ``"header"`` of :mod:`data_tools.results`; both are ignored when the
model is loaded.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

from data_tools.errors import ConfigError, FormatError

__all__ = ["load_model", "save_model", "load_fit_info"]


def _read(path: Path) -> dict:
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise FormatError(path, "file not found") from None
    except IsADirectoryError:
        raise FormatError(path, "is a folder, expected a model JSON file") from None
    except json.JSONDecodeError as e:
        raise FormatError(path, f"not valid JSON ({e.msg} at line {e.lineno})") from None
    if not isinstance(d, dict):
        raise FormatError(path, "a sensor model must be a JSON object")
    return d


def load_model(path: str | os.PathLike):
    """The :class:`SensorConfig` stored in a model JSON (FormatError naming the file otherwise)."""
    from synth.sensor.config import SensorConfig
    path = Path(path)
    d = _read(path)
    d = {k: v for k, v in d.items() if k not in ("fit", "header")}
    try:
        return SensorConfig.from_json(d, base_dir=path.parent)
    except ConfigError as e:
        raise FormatError(path, str(e)) from None
    except (TypeError, ValueError) as e:
        raise FormatError(path, f"bad sensor model ({e})") from None


def load_fit_info(path: str | os.PathLike) -> dict | None:
    """The ``"fit"`` object of a model JSON, or None."""
    return _read(Path(path)).get("fit")


def save_model(config, path: str | os.PathLike, fit_info: dict | None = None, header: dict | None = None) -> Path:
    """Write ``config`` (+ ``fit_info`` under ``"fit"``, + the result ``header`` of
    :mod:`data_tools.results` when given) to ``path`` atomically (folders created); returns the path."""
    from data_tools.results import atomic_write_json
    d = config.to_json(base_dir=Path(path).parent)
    if fit_info is not None:
        d["fit"] = fit_info
    if header is not None:
        d = {"header": header, **d}
    return atomic_write_json(path, d, indent=2)

