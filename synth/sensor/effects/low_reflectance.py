"""Direct model: dark or distant surfaces return too little light."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.sensor.effects._common import (check_draw, cos_incidence, drop_with_probability, sigmoid,
                                          uniform_draw)
from synth.sensor.registry import STAGE_DROPOUT, Effect, Signature, param, register_effect


@dataclass
class LowReflectanceParams:
    signal50: float = param(0.004, "1")
    """Relative returned signal at which half the pixels drop; signal = albedo (1 - specular)
    cos(incidence) / r^2 with r in metres (a white wall facing the sensor at 1 m = 1)."""
    width_decades: float = param(0.25, "decades")
    """Width of the transition in decades of signal (logistic scale)."""
    signal: str = param("irradiance", "", choices=("irradiance", "albedo"))
    """What decides: ``irradiance`` - the returned light, albedo (1 - specular) cos(incidence) /
    r^2 (a sensor near its noise floor: far and oblique surfaces drop too); ``albedo`` - the
    material alone, albedo (1 - specular) (IR-absorbing materials lost at any distance inside
    the working range; then signal50 is an albedo). ``sensor fit`` picks it from the data."""
    law: str = param("logistic", "", choices=("logistic", "normal"))
    """Shape of the transition in log10 signal, both with the same 50 % point and the same slope
    there (``width_decades`` is the logistic scale; the normal law's standard deviation is
    width_decades 4 / sqrt(2 pi)): ``logistic`` (tails falling as exp(-x / w)) or ``normal`` (a
    cumulative normal: each pixel's threshold spread log-normally, tails falling as
    exp(-x^2 / 2 s^2)). The two differ only in the tails, and where the range limit leaves only the
    tail in view (the 50 % point beyond the measured depths) the 50 % point is an extrapolation
    through the law. ``sensor fit`` picks it from the data (likelihood of the holes)."""


NORMAL_SCALE = 4.0 / np.sqrt(2.0 * np.pi)
"""Standard deviation of the ``normal`` law per unit of logistic width: a cumulative normal with
sigma = width x this has the logistic's slope 1 / (4 width) at its 50 % point."""


def transition(u: np.ndarray, law: str, precise: bool = False) -> np.ndarray:
    """(float32, shape of ``u``) the drop probability at ``u`` = log10(signal50 / signal) / width:
    the logistic 1 / (1 + exp(-u)) or the cumulative normal Phi(u / :data:`NORMAL_SCALE`).
    ``precise``: float64 (the likelihood fit of :func:`_logistic_ml`, whose tails matter)."""
    from scipy.special import ndtr
    if law == "logistic":
        if not precise:
            return sigmoid(u)
        return 1.0 / (1.0 + np.exp(-np.clip(np.asarray(u, np.float64), -50, 50)))
    p = ndtr(np.asarray(u, np.float64) / NORMAL_SCALE)
    return p if precise else p.astype(np.float32)


def returned_signal(view, preset, form: str) -> np.ndarray:
    """(H, W) the signal of :class:`LowReflectanceParams` (``form`` irradiance or albedo)."""
    base = view.albedo * (1 - view.specular)
    if form == "albedo":
        return base
    cos_i, r = cos_incidence(view, preset.projector_offset_m)
    return base * cos_i / np.maximum(r * r, 1e-9)


@register_effect
class LowReflectance(Effect):
    """Pixels drop with probability F(log10(signal50 / signal) / width), F the logistic or the
    slope-matched cumulative normal (``law``).

    Physics: the pattern (or ToF amplitude) returned by a surface scales with its diffuse
    albedo, the cosine of incidence and the inverse squared distance; below the sensor's noise
    floor no match (no phase) is found - black fabric, dark plastics and far surfaces turn into
    holes. Draw: one U(0, 1) per pixel.
    """

    name = "low_reflectance"
    SIGNATURE = Signature(
        "holes where little light returns",
        "The invalid fraction differs by material (dark surfaces) and grows with distance and "
        "obliquity (the returned signal falls with z² and cos θ).",
        panels=(("material", "invalid_fraction"), ("distance", "invalid_fraction"), ("incidence", "invalid_fraction")))
    DRAW_FROM_SHAPE = True
    Params = LowReflectanceParams
    FITTABLE = {"signal50": (1e-6, 1.0), "width_decades": (0.01, 3.0)}
    stage = STAGE_DROPOUT
    SIGNAL_HOLES = True

    def sample(self, rng, state):
        return uniform_draw(rng, state.shape)

    def apply(self, state, draw) -> None:
        u = check_draw(draw, "u", state.shape, self.name)
        v = state.view
        s = returned_signal(v, state.preset, self.params.signal)
        with np.errstate(divide="ignore"):
            x = np.log10(self.params.signal50) - np.log10(np.maximum(s, 1e-12))
        p = transition(x / self.params.width_decades, self.params.law)
        p[~v.hit] = 0
        drop_with_probability(state, p, u, self.name)

    START_ONLY_PARAMS = ("signal", "law")

    @classmethod
    def fit_start(cls, measured, config, frames) -> dict:
        """signal50, width and the signal form from the measured holes: for each form, the pixels'
        signal (ideal geometry, the materials' albedos) is binned in 0.05-decade bins; the hole
        rate per bin, less the rate of the brightest quarter of the pixels (other holes),
        normalised, gives signal50 where it crosses 0.5 (scanning from bright to dark) and the
        width from its 0.25 and 0.75 crossings (the logistic's quartiles: width = (x75 - x25) /
        (2 ln 3) decades); both are then refined by maximum likelihood on every pixel
        (:func:`_logistic_ml`, which also starts from the tail when no bin reaches 0.5). The form whose logistic predicts the holes of every pixel best (Brier
        score) wins; for it the ``normal`` law is fitted the same way and taken when its likelihood
        is higher (same number of parameters): the laws agree where the 50 % point is in view and
        part in the tails, where a range limit may leave the only evidence. Only pixels whose ideal depth lies where the sensor measures at all,
        and not within 3 noise sd of the nearest or farthest measured depth, count
        (``_common.uncensored_samples``): the holes beyond a range limit are far and weak too, and the
        ones its noise makes just inside it lie at bright signals no dropout reaches - one logistic
        fitted to both puts signal50 between the two clusters.
        Nothing when no form's excess reaches 0.5."""
        from synth.sensor.effects._common import uncensored_samples
        from synth.sensor.state import ViewGeometry
        rng = np.random.default_rng(0)
        renderer = measured.renderer
        logs = {"irradiance": [], "albedo": []}
        holes = []
        for _, m, r, ok in uncensored_samples(measured, config):      # range-limit holes left out
            idx = np.flatnonzero(ok)
            if idx.size > 40000:
                idx = np.sort(rng.choice(idx, 40000, replace=False))
            if not idx.size:
                continue
            alb, spec = renderer.albedo_specular(r.instance_ids, check=False)
            H, W = r.depth.shape
            view = ViewGeometry(r.points_cam, r.normals_cam, r.hit, r.instance_ids, np.asarray(alb, np.float32),
                                np.asarray(spec, np.float32), r.points_world, np.broadcast_to(np.eye(4), (H, 4, 4)))
            for form in logs:
                sig = returned_signal(view, config.preset, form).ravel()[idx]
                logs[form].append(np.log10(np.maximum(sig, 1e-12)))
            holes.append(m.ravel()[idx] <= 0)
        if not holes:
            return {}
        h = np.concatenate(holes).astype(float)
        best = None
        for form, parts in logs.items():
            x = np.concatenate(parts)
            rates = _logistic_from_rates(x, h)
            est = _logistic_ml(x, h, rates)
            if est is None:
                continue
            x50, w, base, ll = est
            p = base + (1 - base) / (1.0 + np.exp(np.clip((x - x50) / w, -50, 50)))
            brier = float(np.mean((p - h) ** 2))
            if best is None or brier < best[0]:
                best = (brier, form, x50, w, ll, x, rates)
        if best is None:
            return {}
        _, form, x50, w, ll, x, rates = best
        x50, w, law = _pick_law(x, h, rates, (x50, w, ll))
        lo, hi = cls.FITTABLE["signal50"]
        wl, wh = cls.FITTABLE["width_decades"]
        return {f"{cls.name}.signal50": float(np.clip(10.0 ** x50, lo, hi)),
                f"{cls.name}.width_decades": float(np.clip(w, wl, wh)), f"{cls.name}.signal": form,
                f"{cls.name}.law": law}

    @classmethod
    def evidence(cls, ctx, params: dict, gain: float | None = None) -> str:
        """Measured hole rate on dark (albedo < 0.2) vs brighter materials.

        Signature present: the dark-material rate exceeds the brighter materials' rate and the
        current model's dark-material rate by :data:`ctx.MIN_RATE_EXCESS` and is at least 1.5x the
        brighter materials' rate."""
        ids = ctx.material_ids()
        alb = np.array([ctx.albedo.get(int(i), np.nan) for i in range(int(ids.max()) + 1)])[ids]
        names = {}
        for o in ctx.observations:
            names.update(o.material_names)
        hole = ctx.measured <= 0
        known = np.isfinite(alb)
        if not known.any():
            return ctx.weak("reflectance signature", gain, "no material albedos are known")
        cut = 0.2
        dark = known & (alb < cut)
        bright = known & (alb >= cut)
        if not dark.any():
            return ctx.weak("reflectance signature", gain,
                         f"no material darker than albedo {cut} is in view; bright surfaces lose {ctx.pct(ctx.rate(hole, bright))}")
        dark_names = sorted({names.get(int(i), str(i)) for i in np.unique(ids[dark])})
        r_d, r_b, r_mod = ctx.rate(hole, dark), ctx.rate(hole, bright), ctx.rate(ctx.simulated <= 0, dark)
        numbers = (f"dark materials (albedo < {cut}: {', '.join(dark_names[:4])}) lose {ctx.pct(r_d)} of their pixels, "
                   f"brighter ones {ctx.pct(r_b)} (current model: {ctx.pct(r_mod)} on the dark ones)")
        if not (ctx.ge(r_d, r_b + ctx.MIN_RATE_EXCESS) and ctx.ge(r_d, 1.5 * r_b) and ctx.ge(r_d, r_mod + ctx.MIN_RATE_EXCESS)):
            return ctx.weak("reflectance signature", gain, numbers)
        return (f"dark materials (albedo < {cut}: {', '.join(dark_names[:4])}) lose {ctx.pct(r_d)} of their pixels, "
                f"more than brighter ones ({ctx.pct(r_b)}) and than the current model on the dark ones ({ctx.pct(r_mod)}).")


MIN_LL_GAIN = 10.0
"""The maximum-likelihood logistic must explain the holes better than a constant rate by this many
nats (a likelihood ratio of e^10) to be a start."""


def _logistic_ml(x: np.ndarray, hole: np.ndarray, est, law: str = "logistic"):
    """(x50, width, base, log-likelihood) maximising the Bernoulli likelihood of ``hole`` under
    base + (1 - base) F((x50 - x) / width) (F: :func:`transition` of ``law``, the logistic
    1 / (1 + exp(-u)) by default; base: the brightest quarter's rate, fixed), from ``est`` (the
    binned crossings of :func:`_logistic_from_rates`) or, when those never reach 0.5, from the
    weakest percentile of x: within the range limits a sensor may measure only the tail of the
    transition (its 50 % point lies where the range cut already holes every pixel) - the tail's
    rise still fixes it. None when the logistic does not beat the constant rate by
    :data:`MIN_LL_GAIN` nats."""
    from scipy.optimize import minimize
    if x.size < 200:
        return None
    base = float(hole[x >= np.quantile(x, 0.75)].mean()) if est is None else float(est[2])
    if base >= 0.95:
        return None
    start = (float(est[0]), float(est[1])) if est is not None else (float(np.quantile(x, 0.01)), 0.25)
    y = hole.astype(np.float64)

    def nll(v):
        p = base + (1.0 - base) * transition((v[0] - x) / np.exp(v[1]), law, precise=True)
        p = np.clip(p, 1e-12, 1 - 1e-12)
        return -float(np.sum(y * np.log(p) + (1 - y) * np.log(1 - p)))

    r = minimize(nll, [start[0], np.log(max(start[1], 0.01))], method="Nelder-Mead",
                 options={"xatol": 1e-4, "fatol": 1e-3, "maxiter": 400})
    pc = float(np.clip(y.mean(), 1e-12, 1 - 1e-12))
    ll0 = float(np.sum(y * np.log(pc) + (1 - y) * np.log(1 - pc)))
    if not (-float(r.fun) - ll0 >= MIN_LL_GAIN):
        return None
    return float(r.x[0]), float(np.exp(r.x[1])), base, -float(r.fun)


def _pick_law(x: np.ndarray, hole: np.ndarray, rates, logistic: tuple[float, float, float]):
    """(x50, width, law): the logistic fit ``logistic`` (x50, width, log-likelihood of
    :func:`_logistic_ml`) or the ``normal`` law's maximum-likelihood fit from the same start
    (``rates``: :func:`_logistic_from_rates`), whichever explains ``hole`` better. Both have two
    parameters, so the likelihood alone chooses; it matters where only a tail is in view."""
    alt = _logistic_ml(x, hole, rates, law="normal")
    if alt is not None and alt[3] > logistic[2]:
        return alt[0], alt[1], "normal"
    return logistic[0], logistic[1], "logistic"


def _logistic_from_rates(x: np.ndarray, hole: np.ndarray, bin_w: float = 0.05):
    """(x50, width, base rate) of a hole rate falling from 1 (low x) to ``base`` (high x), from
    per-bin rates (>= 30 pixels); None when the normalised excess never reaches 0.5."""
    if x.size < 200:
        return None
    base = float(hole[x >= np.quantile(x, 0.75)].mean())
    if base >= 0.95:
        return None
    lo, hi = np.floor(x.min() / bin_w) * bin_w, np.ceil(x.max() / bin_w) * bin_w + bin_w
    edges = np.arange(lo, hi + 1e-9, bin_w)
    tot = np.histogram(x, edges)[0]
    hol = np.histogram(x[hole > 0], edges)[0]
    have = tot >= 30
    centres = 0.5 * (edges[:-1] + edges[1:])
    ex = np.where(have, (hol / np.maximum(tot, 1) - base) / (1 - base), np.nan)

    def crossing(level):
        # from bright (high x) towards dark: the first bin at or above the level
        for i in range(len(centres) - 1, -1, -1):
            if have[i] and ex[i] >= level:
                j = i + 1
                while j < len(centres) and not have[j]:
                    j += 1
                if j >= len(centres) or ex[j] >= level:
                    return float(centres[i])
                return float(centres[i] + (ex[i] - level) / (ex[i] - ex[j]) * (centres[j] - centres[i]))
        return None

    x50 = crossing(0.5)
    if x50 is None:
        return None
    x25, x75 = crossing(0.25), crossing(0.75)
    w = abs(x25 - x75) / (2 * np.log(3.0)) if x25 is not None and x75 is not None else 0.25
    return x50, max(w, 0.01), base
