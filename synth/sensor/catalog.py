"""What the sensor model knows, generated from the effect registry and the presets (never written by
hand): every effect with its one-line physics, stage, sensor types, signature and parameters
(unit, default, value per preset, plausible range, fit range), and every preset with its device
numbers and effect lists. ``realgap sensor effects [NAME]`` and ``realgap sensor presets [NAME]``
print these tables (``--json``: the dicts below).
"""
from __future__ import annotations

import dataclasses

from data_tools.config import field_docs
from data_tools.errors import ConfigError
from data_tools.results import format_table
from synth.sensor.presets import PRESETS, get_preset
from synth.sensor.registry import effect_class, effect_names

__all__ = ["effect_catalog", "preset_catalog", "format_effects", "format_presets"]


def _first_line(doc: str | None) -> str:
    return " ".join((doc or "").strip().split("\n\n")[0].split())


def effect_catalog(name: str | None = None) -> list[dict]:
    """One dict per registered effect (or only ``name``): name, physics (first docstring paragraph),
    stage, sensor types, signature title, where presets use it, and its parameters (name, type,
    unit, default, value per preset that sets one, bounds, choices, fit range, doc)."""
    names = effect_names() if name is None else [effect_class(name).name]
    out = []
    for n in names:
        cls = effect_class(n)
        params = []
        for s in cls.param_specs():
            per_preset = {p: pre.effect_params[n][s.name] for p, pre in PRESETS.items()
                          if s.name in pre.effect_params.get(n, {})}
            params.append({"name": s.name, "type": s.type, "unit": s.unit, "default": _plain(s.default),
                           "presets": per_preset, "bounds": _plain(s.bounds), "choices": _plain(s.choices),
                           "fit_range": _plain(s.fit_range), "doc": s.doc,
                           "data_file": s.name in cls.FILE_PARAMS})
        for key, cp in sorted(getattr(cls, "CONFIG_PARAMETERS", {}).items()):
            params.append({"name": key, "type": "float", "unit": cp.unit, "default": None, "presets": {},
                           "bounds": [cp.low, cp.high], "choices": None, "fit_range": [cp.low, cp.high],
                           "doc": cp.doc + " (lives in the sensor config, not in the effect's params)"})
        out.append({
            "name": n, "physics": _first_line(cls.__doc__), "stage": int(cls.stage),
            "sensor_types": list(getattr(cls, "sensor_types", ()) or ()),
            "signature": cls.SIGNATURE.title if cls.SIGNATURE is not None else None,
            "used_by": {p: [k for k, lst in (("physical", pre.physical_effects), ("direct", pre.direct_effects))
                            if n in lst] for p, pre in PRESETS.items()
                        if n in pre.physical_effects or n in pre.direct_effects},
            "parameters": params})
    return out


def preset_catalog(name: str | None = None) -> list[dict]:
    """One dict per preset (or only ``name``): every device field with its docstring, and the
    effects of its physical and direct models with the parameter values it sets."""
    presets = list(PRESETS.values()) if name is None else [get_preset(name)]
    out = []
    for pre in presets:
        docs = field_docs(type(pre))
        fields = []
        for f in dataclasses.fields(pre):
            if f.name in ("physical_effects", "direct_effects", "effect_params", "name", "description", "source"):
                continue
            fields.append({"name": f.name, "value": _plain(getattr(pre, f.name)), "doc": docs.get(f.name, "")})
        out.append({"name": pre.name, "type": pre.type, "description": pre.description, "source": pre.source,
                    "fields": fields, "physical_effects": list(pre.physical_effects),
                    "direct_effects": list(pre.direct_effects),
                    "effect_params": {k: dict(v) for k, v in pre.effect_params.items()}})
    return out


def _plain(x):
    if isinstance(x, tuple):
        return [_plain(v) for v in x]
    return x


def _num(x) -> str:
    if x is None:
        return "-"
    if isinstance(x, bool) or isinstance(x, str):
        return str(x).lower() if isinstance(x, bool) else x
    if isinstance(x, float):
        return f"{x:g}"
    if isinstance(x, list):
        return "(" + ", ".join(_num(v) for v in x) + ")"
    return str(x)


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    return format_table(header, rows, align="l" * len(header)).splitlines()


def format_effects(entries: list[dict], detail: bool) -> str:
    """Text for ``realgap sensor effects``: one line per effect, or (``detail``) the parameter table."""
    if not detail:
        rows = [[e["name"], str(len(e["parameters"])), ",".join(e["sensor_types"]) or "all", e["physics"]]
                for e in entries]
        return "\n".join(_table(["effect", "params", "sensors", "physics"], rows))
    lines = []
    for e in entries:
        lines += [f"{e['name']}: {e['physics']}",
                  f"  stage {e['stage']}; sensors: {', '.join(e['sensor_types']) or 'all'}; used by: "
                  + (", ".join(f"{p} ({'/'.join(k)})" for p, k in e["used_by"].items()) or "no preset"),
                  f"  lab signature: {e['signature'] or '-'}", ""]
        rows = []
        for p in e["parameters"]:
            rng = _num(p["bounds"]) if p["bounds"] is not None else ("|".join(p["choices"]) if p["choices"] else "-")
            per = ", ".join(f"{k} {_num(v)}" for k, v in p["presets"].items())
            rows.append([p["name"], _num(p["unit"]) if p["unit"] not in (None, "") else "-", _num(p["default"]),
                         per or "-", rng, _num(p["fit_range"]) if p["fit_range"] else
                         ("from data" if p.get("data_file") else "no")])
        lines += ["  " + ln for ln in _table(["parameter", "unit", "default", "presets", "range", "fit"], rows)]
        lines += [""] + [f"  {p['name']}: {p['doc']}" for p in e["parameters"]] + [""]
    return "\n".join(lines).rstrip()


def format_presets(entries: list[dict], detail: bool) -> str:
    """Text for ``realgap sensor presets``: one line per preset, or (``detail``) every field."""
    if not detail:
        rows = [[p["name"], p["type"], f"{_field(p, 'width')}x{_field(p, 'height')}",
                 _num(_field(p, "baseline_m")), f"{_num(_field(p, 'min_depth_m'))}-{_num(_field(p, 'max_depth_m'))}",
                 p["description"]] for p in entries]
        return "\n".join(_table(["preset", "type", "image", "baseline m", "range m", "device"], rows))
    lines = []
    for p in entries:
        lines += [f"{p['name']} ({p['type']}): {p['description']}", f"  source: {p['source'] or '-'}", ""]
        lines += ["  " + ln for ln in _table(["field", "value", "meaning"],
                                             [[f["name"], _num(f["value"]), f["doc"]] for f in p["fields"]])]
        lines += ["", f"  physical model: {', '.join(p['physical_effects']) or '-'}",
                  f"  direct model:   {', '.join(p['direct_effects']) or '-'}"]
        for eff, vals in p["effect_params"].items():
            lines.append(f"  {eff}: " + ", ".join(f"{k}={_num(v)}" for k, v in vals.items()))
        lines.append("")
    return "\n".join(lines).rstrip()


def _field(p: dict, name: str):
    for f in p["fields"]:
        if f["name"] == name:
            return f["value"]
    raise ConfigError(f"preset {p['name']!r} has no field {name!r}")
