"""Candidate restarts for :mod:`synth.lab.diagnose`'s stage 3 (:func:`~synth.lab.diagnose.fit_candidate`):
the refitted model's own parameters put back at their closed-form starts when a candidate added at
its data-driven start does better from there. ``cx`` is diagnose's stage context (measured sequence,
search objective ``obj``, frames, settings ``fc`` / ``dc``)."""
from __future__ import annotations

from collections.abc import Sequence

from synth.lab.fit import set_params, start_values


def _limit_keys(cfg, names: Sequence[str]) -> set[str]:
    """The ``effect.param`` keys of the depth limits (``Effect.DEPTH_LIMIT_PARAMS``) of effects ``names``."""
    return {f"{n}.{k}" for n in names for k in type(cfg.effect(n)).DEPTH_LIMIT_PARAMS}


def _keep_if_better(cx, cfg, gap: float, starts: dict) -> tuple[object, float]:
    """(config, gap): ``cfg`` with ``starts`` set when that lowers the gap below ``gap``; else unchanged."""
    if not starts:
        return cfg, gap
    alt = set_params(cfg, starts)
    g = cx.obj(alt)
    return (alt, g) if g < gap else (cfg, gap)


def model_restart(cx, model_names: Sequence[str], cfg, gap: float) -> tuple[object, float]:
    """(config, gap): ``cfg`` (gap ``gap``, a candidate at its data-driven start on the refitted model)
    with the model's own parameters reset to their closed-form starts (``fit_start``, as
    :func:`~synth.lab.diagnose.refit_base` begins) when that lowers the gap; else unchanged. The base refit, without the
    candidate, explains what it can of the candidate's effect with the model's parameters (a depth
    bias that widens the error distribution read as extra axial noise, sigma2 +30 %); the candidate
    added at its own start then counts the effect twice, and a local search of a few evaluations
    does not undo it, while the closed-form noise start (local differences, blind to a smooth bias)
    is right. The depth limits (``Effect.DEPTH_LIMIT_PARAMS``) are left to :func:`limits_restart`
    (only a candidate whose holes follow the signal restarts them). Only when the search
    configuration asks for data-driven starts and the model is refitted."""
    if not (cx.fc.data_starts and cx.dc.refit_model and model_names):
        return cfg, gap
    limits = _limit_keys(cfg, model_names)
    ds = start_values(cx.measured, cfg, list(model_names), cx.frames)
    return _keep_if_better(cx, cfg, gap, {k: v for k, v in ds.items() if not isinstance(v, str) and k not in limits})


def limits_restart(cx, model_names: Sequence[str], name: str, cfg, gap: float) -> tuple[object, float]:
    """(config, gap): ``cfg`` (gap ``gap``) with the model's depth limits (``Effect.DEPTH_LIMIT_PARAMS``)
    set to their closed-form start (the farthest / nearest measured depth) when candidate ``name``
    removes pixels where little signal returns (``Effect.SIGNAL_HOLES``) and that lowers the gap;
    else unchanged. The base refit, without the candidate, may have pulled the maximum range in to
    explain the far low-signal holes; the candidate added on top would then count them twice and
    lose to a rival whose holes the pulled-in range does not already explain."""
    if not type(cfg.effect(name)).SIGNAL_HOLES:
        return cfg, gap
    limits = _limit_keys(cfg, model_names)
    owners = [n for n in model_names if type(cfg.effect(n)).DEPTH_LIMIT_PARAMS]
    ds = start_values(cx.measured, cfg, owners, cx.frames) if owners else {}
    return _keep_if_better(cx, cfg, gap, {k: v for k, v in ds.items() if k in limits})
