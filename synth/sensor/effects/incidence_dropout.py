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
    """Width of the transition (logistic scale), degrees; small = a hard cut (0.1° is a step at
    the pixel level)."""
    reference: str = param("camera", "", choices=("camera", "projector", "both"))
    """The ray the incidence angle is measured against: the camera's viewing ray (matching fails
    on surfaces seen at grazing angles), the projector's ray (structured light: dots are lost where
    the pattern arrives at grazing angles) or ``both`` (the larger of the two angles). Measured on
    the IDEAL geometry's normals, never noisy ones. ``sensor fit`` picks it from the data."""


def incidence_angles_deg(normals_cam: np.ndarray, ray_dirs_cam: np.ndarray, points_cam: np.ndarray | None,
                         projector_offset_m, reference: str) -> np.ndarray:
    """(H, W) incidence angle in degrees against the camera ray, the projector ray or the larger
    of the two (``reference``); surface normals facing the camera."""
    c = np.abs(np.einsum("hwk,hwk->hw", normals_cam, ray_dirs_cam))
    th_cam = np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))
    if reference == "camera" or points_cam is None:
        return th_cam
    L = points_cam - np.asarray(projector_offset_m, np.float32)
    r = np.maximum(np.linalg.norm(L, axis=-1), 1e-9)
    cp = np.abs(np.einsum("hwk,hwk->hw", normals_cam, L)) / r
    th_proj = np.degrees(np.arccos(np.clip(cp, 0.0, 1.0)))
    return th_proj if reference == "projector" else np.maximum(th_cam, th_proj)


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
    START_ONLY_PARAMS = ("reference",)
    stage = STAGE_DROPOUT
    SIGNAL_HOLES = True

    def sample(self, rng, state):
        return uniform_draw(rng, state.shape)

    def apply(self, state, draw) -> None:
        u = check_draw(draw, "u", state.shape, self.name)
        if self.params.reference == "camera":          # (the original code path, bit for bit)
            c = cos_view(state.view, state.ray_dirs_cam)
            theta = np.degrees(np.arccos(np.clip(c, 0, 1)))
        else:
            theta = incidence_angles_deg(state.view.normals_cam, state.ray_dirs_cam, state.view.points_cam,
                                         state.preset.projector_offset_m, self.params.reference)
        p = sigmoid((theta - self.params.angle50_deg) / self.params.width_deg)
        p[~state.view.hit] = 0
        drop_with_probability(state, p, u, self.name)

    @classmethod
    def fit_start(cls, measured, config, frames) -> dict[str, float]:
        """The 50 % angle, the width and the reference ray from the measured hole rate vs incidence
        angle (the angle between the IDEAL geometry's normal and the camera ray, the projector ray,
        or the larger of both; the reference with the sharpest transition wins, since measuring
        against another ray blurs it): per 0.25° bin (>= 40 pixels) the excess hole rate over the rate below 40° (other holes;
        on an oblique view with too few pixels there, the rate of the quarter of the pixels at the smallest angles), normalised to
        [0, 1]; angle50 is where it first reaches 0.5, the width (theta75 - theta25) / (2 ln 3)
        (the logistic's quartiles), at least 0.1° - a hard cut gives the smallest width. Nothing
        when the excess never reaches 0.5 (no dropout, or no data at grazing angles). Only pixels
        whose ideal depth lies where the sensor measures at all, and not within 3 noise sd of the
        nearest or farthest measured depth, count (``_common.uncensored_samples``: a floor beyond the
        range limit is grazing and all holes, and just inside it noise alone makes holes)."""
        from synth.sensor.effects._common import uncensored_samples
        refs = ("camera",) if config.preset.type == "tof" else ("camera", "projector", "both")
        edges = np.arange(0.0, 90.01, 0.25)
        curves = {ref: (np.zeros(len(edges) - 1), np.zeros(len(edges) - 1)) for ref in refs}
        for _, m, r, ok in uncensored_samples(measured, config):      # range-limit holes left out
            pts = getattr(r, "points_cam", None)
            for ref in refs:
                th = incidence_angles_deg(r.normals_cam, r.ray_dirs_cam, pts, config.preset.projector_offset_m,
                                          ref)[ok]
                h = (m[ok] <= 0)
                curves[ref][0][:] += np.histogram(th[h], edges)[0]
                curves[ref][1][:] += np.histogram(th, edges)[0]
        best = None
        for ref in refs:   # the true reference gives the sharpest transition (any other blurs it)
            est = cls._from_curve(*curves[ref], edges)
            if est is not None and (best is None or (est[1], est[2]) < (best[1][1] - 0.05, best[1][2])):
                best = (ref, est)
        if best is None:
            return {}
        ref, (a50, width, _) = best
        lo, hi = cls.FITTABLE["width_deg"]
        out = {f"{cls.name}.angle50_deg": float(np.clip(a50, *cls.FITTABLE["angle50_deg"])),
               f"{cls.name}.width_deg": float(np.clip(width, lo, hi))}
        if len(refs) > 1:
            out[f"{cls.name}.reference"] = ref
        return out

    @staticmethod
    def _from_curve(holes, total, edges):
        """(angle50, width, misfit) of one hole-rate curve, None when it never reaches 0.5."""
        have = total >= 40
        centres = 0.5 * (edges[:-1] + edges[1:])
        low = centres < 40
        if have[low].sum() < 3:     # an oblique view (within the range, nothing faces the sensor):
            # the other holes' rate from the quarter of the pixels at the smallest angles
            q = float(np.searchsorted(np.cumsum(total), 0.25 * total.sum()))
            low = centres <= centres[min(int(q), len(centres) - 1)]
        if have[low].sum() < 3 or not have[~low].any():
            return None
        rate = np.where(have, holes / np.maximum(total, 1), np.nan)
        base = float(np.nanmedian(rate[low]))
        if base >= 0.95:
            return None
        ex = (rate - base) / (1.0 - base)

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
            return None
        a25, a75 = crossing(0.25), crossing(0.75)
        width = (a75 - a25) / (2 * np.log(3.0)) if a25 is not None and a75 is not None else 2.0
        width = max(width, 0.1)
        # misfit of the logistic to the normalised excess curve (pixel-weighted): the reference whose
        # curve a logistic explains best is the one the sensor uses
        pred = 1.0 / (1.0 + np.exp(-np.clip((centres - a50) / width, -50, 50)))
        w = np.where(have, total, 0.0)
        misfit = float(np.nansum(w * (np.nan_to_num(ex) - pred) ** 2) / max(w.sum(), 1.0))
        return a50, width, misfit

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
