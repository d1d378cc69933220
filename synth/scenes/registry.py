"""The scene registry: ``@register_scene("name")`` adds a builder ``f(seed=0, **params) -> SceneSpec``
to :data:`SCENES`; :func:`build_scene` looks it up by name and checks the parameters.

The builders live in :mod:`synth.scenes.builtin` (procedural scenes) and
:mod:`synth.scenes.loaders` (file-based scenes); importing :mod:`synth.scenes` registers both.
"""
from __future__ import annotations

import inspect
from typing import Callable

from data_tools.errors import ConfigError
from data_tools.scene_spec import SceneSpec

__all__ = ["SCENES", "SceneBuilder", "register_scene", "scene_names", "scene_parameters", "describe_scenes",
           "build_scene"]

SceneBuilder = Callable[..., SceneSpec]

SCENES: dict[str, SceneBuilder] = {}
"""Scene builders by name; each is ``f(seed=0, **params) -> SceneSpec``."""


def register_scene(name: str) -> Callable[[SceneBuilder], SceneBuilder]:
    """Decorator adding a scene builder to :data:`SCENES` under ``name``."""
    def deco(fn: SceneBuilder) -> SceneBuilder:
        if name in SCENES and SCENES[name] is not fn:
            raise ValueError(f"scene {name!r} is registered twice")
        SCENES[name] = fn
        return fn
    return deco


def scene_names() -> list[str]:
    """Names of all registered scenes, sorted."""
    return sorted(SCENES)


def scene_parameters(name: str) -> dict[str, object]:
    """Keyword parameters (besides ``seed``) a scene builder accepts, with their defaults
    (``inspect.Parameter.empty`` for required ones)."""
    if name not in SCENES:
        raise ConfigError(f"unknown scene {name!r}; known scenes: {', '.join(sorted(SCENES))}")
    sig = inspect.signature(SCENES[name])
    return {p.name: p.default for p in sig.parameters.values()
            if p.name != "seed" and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}


def describe_scenes() -> list[tuple[str, str, list[str]]]:
    """(name, first docstring line, ["key=default" or "key=<required>", ...]) of every registered scene."""
    out = []
    for name in scene_names():
        params = [f"{k}=<required>" if v is inspect.Parameter.empty else f"{k}={v!r}"
                  for k, v in scene_parameters(name).items()]
        out.append((name, (inspect.getdoc(SCENES[name]) or "").split("\n")[0], params))
    return out


def build_scene(name: str, seed: int = 0, **params) -> SceneSpec:
    """Build the registered scene ``name`` (deterministic given ``seed`` and ``params``).

    Unknown names and unknown or missing parameters raise :class:`ConfigError` listing what
    is allowed.
    """
    accepted = scene_parameters(name)
    unknown = sorted(set(params) - set(accepted))
    if unknown:
        allowed = ", ".join(accepted) or "none"
        raise ConfigError(f"scene {name!r} has no parameter(s) {', '.join(unknown)} (accepted: {allowed})")
    missing = [k for k, v in accepted.items() if v is inspect.Parameter.empty and k not in params]
    if missing:
        raise ConfigError(f"scene {name!r} needs parameter(s) {', '.join(missing)} "
                          f"(e.g. --scene-param {missing[0]}=...)")
    return SCENES[name](seed=int(seed), **params)
