"""Direct model: grazing surfaces are lost."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.sensor.effects._common import check_draw, cos_view, drop_with_probability, sigmoid, uniform_draw
from synth.sensor.registry import STAGE_DROPOUT, Effect, Signature, param, register_effect


@dataclass
class IncidenceDropoutParams:
    angle50_deg: float = param(78.0, "deg")
    """Angle between the surface normal and the viewing ray at which half the pixels drop."""
    width_deg: float = param(2.5, "deg")
    """Width of the transition (logistic scale), degrees."""


@register_effect
class IncidenceDropout(Effect):
    """Pixels drop with probability logistic((theta - angle50) / width), theta the angle between
    the surface normal and the viewing ray.

    Physics: at grazing incidence the returned signal falls with cos(theta) and, for
    structured light, the pattern is compressed by the steep disparity gradient until the
    correlation window no longer matches (the physical pipeline shows this through the
    matcher's speckle/consistency filter); real Kinect v1 data loses most pixels beyond
    ~75-80 degrees. Draw: one U(0, 1) per pixel.
    """

    name = "incidence_dropout"
    SIGNATURE = Signature(
        "holes on oblique surfaces",
        "The invalid fraction climbs steeply at grazing incidence angles.",
        panels=(("incidence", "invalid_fraction"), ("incidence", "std")))
    DRAW_FROM_SHAPE = True
    Params = IncidenceDropoutParams
    FITTABLE = {"angle50_deg": (30.0, 90.0), "width_deg": (0.1, 30.0)}
    stage = STAGE_DROPOUT

    def sample(self, rng, state):
        return uniform_draw(rng, state.shape)

    def apply(self, state, draw) -> None:
        u = check_draw(draw, "u", state.shape, self.name)
        c = cos_view(state.view, state.ray_dirs_cam)
        theta = np.degrees(np.arccos(np.clip(c, 0, 1)))
        p = sigmoid((theta - self.params.angle50_deg) / self.params.width_deg)
        p[~state.view.hit] = 0
        drop_with_probability(state, p, u, self.name)

    @classmethod
    def fit_start(cls, measured, config, frames) -> dict[str, float]:
        """The 50 % angle and the width from the measured hole rate vs incidence angle (the angle
        between the IDEAL geometry's normal and the viewing ray, as the effect uses): per 1° bin
        (>= 40 pixels) the excess hole rate over the rate below 40° (other holes), normalised to
        [0, 1]; angle50 is where it first reaches 0.5, the width (theta75 - theta25) / (2 ln 3)
        (the logistic's quartiles), at least 0.1° - a hard cut gives the smallest width. Nothing
        when the excess never reaches 0.5 (no dropout, or no data at grazing angles)."""
        from synth.sensor.effects._common import measured_samples
        edges = np.arange(0.0, 91.0, 1.0)
        holes = np.zeros(len(edges) - 1)
        total = np.zeros(len(edges) - 1)
        for _, m, r, ok in measured_samples(measured):
            c = np.abs(np.einsum("hwk,hwk->hw", r.normals_cam, r.ray_dirs_cam))
            th = np.degrees(np.arccos(np.clip(c[ok], 0.0, 1.0)))
            h = (m[ok] <= 0)
            total += np.histogram(th, edges)[0]
            holes += np.histogram(th[h], edges)[0]
        have = total >= 40
        if have[:40].sum() < 3 or not have[40:].any():
            return {}
        rate = np.where(have, holes / np.maximum(total, 1), np.nan)
        base = float(np.nanmedian(rate[:40]))
        if base >= 0.95:
            return {}
        ex = (rate - base) / (1.0 - base)
        centres = 0.5 * (edges[:-1] + edges[1:])

        def crossing(level):
            idx = np.flatnonzero(have & (ex >= level) & (centres >= 40))
            if not idx.size:
                return None
            i = int(idx[0])
            j = i - 1
            while j >= 0 and not have[j]:
                j -= 1
            if j < 0 or ex[j] >= level:
                return float(centres[i])
            return float(centres[j] + (level - ex[j]) / (ex[i] - ex[j]) * (centres[i] - centres[j]))

        a50 = crossing(0.5)
        if a50 is None:
            return {}
        a25, a75 = crossing(0.25), crossing(0.75)
        width = (a75 - a25) / (2 * np.log(3.0)) if a25 is not None and a75 is not None else 2.0
        lo, hi = cls.FITTABLE["width_deg"]
        return {f"{cls.name}.angle50_deg": float(np.clip(a50, *cls.FITTABLE["angle50_deg"])),
                f"{cls.name}.width_deg": float(np.clip(width, lo, hi))}

    @classmethod
    def evidence(cls, ctx, params: dict, gain: float | None = None) -> str:
        """Measured hole rate per incidence-angle band (bands with >= 50 pixels).

        Signature present: the rate above 60° exceeds the rate below 40° and the current model's
        rate above 60° by :data:`ctx.MIN_RATE_EXCESS`."""
        ang = ctx.incidence_deg()
        hole = ctx.measured <= 0
        ok = np.isfinite(ang)
        rates = []
        for lo, hi in ((0, 40), (40, 60), (60, 70), (70, 80), (80, 90.1)):
            sel = ok & (ang >= lo) & (ang < hi)
            if sel.sum() >= 50:
                rates.append(f"{ctx.pct(ctx.rate(hole, sel))} at {lo:g}-{min(hi, 90):g}°")
        low, high = ok & (ang < 40), ok & (ang >= 60)
        a50 = params.get("incidence_dropout.angle50_deg")
        tail = f" (fitted 50 % angle {a50:.0f}°)" if a50 is not None else ""
        if int(high.sum()) < 50:
            return ctx.weak("incidence signature", gain, f"fewer than 50 pixels are seen at more than 60° incidence "
                                                      f"({', '.join(rates) or 'no angle band with data'})")
        r_hi, r_lo, r_mod = ctx.rate(hole, high), ctx.rate(hole, low), ctx.rate(ctx.simulated <= 0, high)
        numbers = f"measured hole rate {', '.join(rates)} (current model: {ctx.pct(r_mod)} above 60°)"
        if not (ctx.ge(r_hi, r_lo + ctx.MIN_RATE_EXCESS) and ctx.ge(r_hi, r_mod + ctx.MIN_RATE_EXCESS)):
            return ctx.weak("incidence signature", gain, numbers)
        return (f"the measured hole rate rises at grazing incidence: {', '.join(rates)}, against "
                f"{ctx.pct(r_mod)} above 60° in the current model{tail}.")
