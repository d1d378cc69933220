"""A SynDA generator as one file: a header (format, version, domain), its :class:`SyndaConfig`,
an ``info`` dict (what made it: command, seed, final losses) and the network's weights.

    GEN (torch.save of a dict; read with ``weights_only=True``, so no code is unpickled)
      format   "realgap-synda-generator"
      version  :data:`GENERATOR_VERSION`
      domain   "rgb" | "depth"
      config   the SyndaConfig as JSON data
      info     free JSON data
      state    the Generator's state_dict

Loading checks the header before building anything: a file of another format, version or
domain is a one-line :class:`~data_tools.errors.FormatError` naming the file.
"""
from __future__ import annotations

import io
import os
from pathlib import Path

import torch

from data_tools.config import config_from_dict, config_to_dict
from data_tools.errors import FormatError, RealgapError
from data_tools.results import atomic_write_bytes
from recog.synda.config import SyndaConfig
from recog.synda.model import Generator

__all__ = ["GENERATOR_FORMAT", "GENERATOR_VERSION", "save_generator", "load_generator"]

GENERATOR_FORMAT = "realgap-synda-generator"
GENERATOR_VERSION = 1


def save_generator(path: str | os.PathLike, net: Generator, cfg: SyndaConfig, info: dict | None = None) -> Path:
    """Write ``net`` with ``cfg`` and ``info`` to ``path`` atomically; returns the path."""
    if net.domain != cfg.domain:
        raise FormatError(path, f"generator domain {net.domain} differs from its config's {cfg.domain}")
    buf = io.BytesIO()
    torch.save({"format": GENERATOR_FORMAT, "version": GENERATOR_VERSION, "domain": cfg.domain,
                "config": config_to_dict(cfg), "info": dict(info or {}),
                "state": {k: v.detach().cpu() for k, v in net.state_dict().items()}}, buf)
    return atomic_write_bytes(path, buf.getvalue())


def load_generator(path: str | os.PathLike, domain: str | None = None,
                   device: str = "cpu") -> tuple[Generator, SyndaConfig, dict]:
    """(generator in eval mode, its config, its info) from ``path``; ``domain``, when given, is
    the domain the caller needs (another one is an error)."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, "generator file not found (made by 'realgap synda train')")
    try:
        blob = torch.load(path, map_location=device, weights_only=True)
    except Exception as e:  # torch raises many types for a file that is not its format
        raise FormatError(path, f"not a SynDA generator file ({type(e).__name__})") from None
    if not isinstance(blob, dict) or blob.get("format") != GENERATOR_FORMAT:
        raise FormatError(path, f"not a {GENERATOR_FORMAT} file")
    if blob.get("version") != GENERATOR_VERSION:
        raise FormatError(path, f"SynDA generator version {blob.get('version')!r}, this realgap reads version "
                                f"{GENERATOR_VERSION}: retrain it with 'realgap synda train'")
    if domain is not None and blob.get("domain") != domain:
        raise FormatError(path, f"a SynDA generator for {blob.get('domain')!r} inputs, {domain!r} needed")
    try:
        cfg = config_from_dict(SyndaConfig, blob.get("config", {}), str(path))
    except RealgapError as e:
        raise FormatError(path, f"bad generator config ({e})") from None
    if cfg.domain != blob.get("domain"):
        raise FormatError(path, f"header domain {blob.get('domain')!r} differs from its config's {cfg.domain!r}")
    net = Generator(cfg.generator, cfg.domain)
    try:
        net.load_state_dict(blob["state"])
    except Exception as e:
        raise FormatError(path, f"weights do not fit the generator of its config ({type(e).__name__})") from None
    net.to(device).eval()
    return net, cfg, dict(blob.get("info", {}))
