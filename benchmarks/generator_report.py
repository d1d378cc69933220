"""Per-generator report of ``bench_fit_recovery.py --generators`` (issue #43, item 6).

For every generator (``hidden``: tests/hidden_effects.py; ``mystery``: synth/lab/mystery.py, written
independently from the Kinect literature; ``blind``: tests/blind_sensor.py, written without reading the
lab, the simulator or the other two generators, from the file formats and the CLI's effect help alone),
every hidden effect and seed, one sequence is made and run through the lab as a user would:

* rank-first: ``diagnose`` from ``axial_noise, range_limits`` at the preset's defaults names the
  hidden effect first;
* recovery: ``fit_model`` with the true effect recovers the generator's parameters within the
  tolerances of bench_fit_recovery's table (noise at 2 m, bias at 1/2/3 m where the data has those
  depths - :data:`DEPTH_SPAN_PERCENTILES` -, dropout angle, k1, step,
  edge radius, and for the mystery and blind sensors also signal50 within 25 % and the rolling-shutter
  readout within 20 %); for the rolling shutter also, counted apart (``recovered_band``), the band time
  readout x (band row - reference row) within 20 %, the quantity the data fix (:func:`band_row`);
* closure: (gap without - gap with) / (gap without - floor) by the lab's gap, ``without`` the base
  model fitted, ``with`` the base + the true effect fitted, ``floor`` the measurement against the
  generator re-run with another noise seed (mean of ``draws`` simulation seeds / re-runs);
* unobservable: the true effect's gain (gap without - gap with, and its gain in the diagnosis) is
  within 2 standard deviations of the gap's own noise (from :data:`FLOOR_RERUNS` re-runs of the
  generator): even the truth cannot be told apart on these frames, so the case is reported apart,
  not as a miss (:func:`observable`);
* implausible: every fitted parameter (diagnose's refit base model and best candidate, the base-only
  fit, the fit with the true effect) outside what a Kinect-class sensor can have
  (:data:`SENSOR_LIMITS`), and range limits that discard measured pixels (a fitted minimum above the
  measured valid depths' 0.5th percentile, a maximum below their 99.5th, issue #43 item 1).
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

SENSOR_LIMITS = {"axial_noise.sigma0_m": (0.0, 0.01), "axial_noise.sigma1": (0.0, 0.01),
                 "axial_noise.sigma2_per_m": (0.0002, 0.01), "depth_bias.disparity_offset_px": (-1.5, 1.5),
                 "depth_bias.scale": (-0.05, 0.05), "depth_bias.offset_m": (-0.05, 0.05),
                 "depth_bias.radial_disparity_px": (-1.0, 1.0), "lens_distortion.k1": (-0.4, 0.4),
                 "lens_distortion.k2": (-0.4, 0.4), "incidence_dropout.angle50_deg": (40.0, 89.9),
                 "edge_fattening.radius_px": (0.0, 10.0), "disparity_quantization.step_px": (0.0, 0.6),
                 "range_limits.min_depth_m": (0.0, 1.2), "range_limits.max_depth_m": (0.0, 12.0)}
"""What a Kinect-class structured-light sensor can have (this bench's own judgement, wider than any
generator's draws, narrower than the lab's search bounds where those allow nonsense)."""


def make(gen: str, path: Path, effect: str, seed: int, frames: int, w: int, h: int, noise_seed=None) -> dict:
    """Generate one sequence; the truth as {"effect", "params", "noise2m", "bias"} (common keys)."""
    if gen == "hidden":
        from tests import hidden_effects as he
        kw = {} if noise_seed is None else {"noise_seed": noise_seed}
        t = he.generate(path, effect, seed=seed, n_frames=frames, width=w, height=h, **kw)
        return {"effect": effect, "raw": t, "noise2m": None,
                "bias": None if effect != "depth_bias" else
                {z: t["c0_m"] + t["c1"] * (z - 2) + t["c2_per_m"] * (z - 2) ** 2 for z in (1.0, 2.0, 3.0)}}
    if gen == "blind":
        from tests import blind_sensor
        a = blind_sensor.generate(path, effect, seed=seed, n_frames=frames, width=w, height=h, noise_seed=noise_seed)
        # the noise-free bias, as depth_bias's model value (the lab simulates the noise on top; the mean over
        # the noise adds E[fb / (D + n)] - fb / D, ~2 mm at 3 m for this generator's 160 px noise)
        return {"effect": effect, "raw": a, "noise2m": float(a["noise2m"]),
                "bias": {float(z): v for z, v in a["params"]["bias_noise_free_at_m"].items()}
                if effect == "depth_bias" else None}
    from synth.lab import mystery
    a = mystery.generate(path, effect, seed=seed, n_frames=frames, width=w, height=h, noise_seed=noise_seed)
    return {"effect": effect, "raw": a, "noise2m": 4.0 * a["base"]["axial_noise"]["sigma2_per_m"],
            "bias": {float(z): v for z, v in a["bias_at_m"].items()} if effect == "depth_bias" else None}


def band_row(ms) -> float:
    """The rolling shutter's band-centre row (0 = first row, 1 = last, v / (H - 1) as both the model
    and the mystery generator write a row's time): the mean row of the usable pixels - measured valid
    with reference geometry (ideal depth > 0), every frame, each pixel weighing one. The data fix the
    exposure time of this band relative to the frame's timestamp, readout x (band row - reference
    row), not the readout alone (docs/lab_generalisation.md, "rolling_shutter")."""
    rows, n = 0.0, 0
    for k in range(len(ms)):
        ok = (ms.measured_depth(k) > 0) & (ms.render(k).depth > 0)
        H = ok.shape[0]
        v = np.nonzero(ok)[0]
        rows += float(v.sum()) / max(H - 1, 1)
        n += v.size
    return rows / n if n else float("nan")


BAND_QUANTITY = "band time [s]"
"""The rolling shutter's observable row (:func:`band_row`): reported beside the readout, counted
apart (``recovered_band``) so the readout-only ``recovered`` stays comparable with earlier runs."""


def recovery_rows(gen: str, truth: dict, cfg, fb: float, at_bound: set) -> list[dict]:
    """Recovery rows of one fitted model (bench_fit_recovery's table; the hidden generator through
    its ``compare``). The rolling shutter's band time is a row of its own (:func:`band_time_rows`)."""
    from benchmarks.bench_fit_recovery import _model_bias, _model_sigma, compare
    if gen == "hidden":
        return compare(truth["effect"], truth["raw"], cfg, fb, at_bound)
    rows = []
    p = truth["raw"]["params"]
    eff = truth["effect"]

    def row(q, t, f, tol, rel=False, key=None, depth_m=None):
        rows.append(_row(eff, q, t, f, tol, rel, bool(key and key in at_bound)))
        if depth_m is not None:
            rows[-1]["depth_m"] = depth_m

    row("noise at 2 m [m]", truth["noise2m"], _model_sigma(cfg, 2.0), 0.10, rel=True, key="axial_noise.sigma2_per_m")
    if eff == "depth_bias":
        for z, t in truth["bias"].items():
            row(f"bias at {z:.0f} m [m]", t, _model_bias(cfg, z), 0.002, depth_m=z)
    elif eff == "incidence_dropout":
        row("dropout angle [deg]", p["angle50_deg"], cfg.effect(eff).params.angle50_deg, 2.0,
            key="incidence_dropout.angle50_deg")
    elif eff == "lens_distortion":
        row("k1", p["k1"], cfg.effect(eff).params.k1, 0.02, key="lens_distortion.k1")
    elif eff == "disparity_quantization":
        row("disparity step [px]", p["step_px"], cfg.effect(eff).params.step_px, 0.03, rel=True,
            key="disparity_quantization.step_px")
    elif eff == "edge_fattening":
        r = cfg.effect(eff).params.radius_px or cfg.preset.block_size // 2
        row("edge radius [px]", float(p["radius_px"]), float(r), 0.0, key="edge_fattening.radius_px")
    elif eff == "rolling_shutter":
        # both in the same convention: readout first row -> last row; the generator stamps the first
        # row's exposure (answer reference_row 0), the model fits its reference row (not compared:
        # with a slow camera it is weakly constrained)
        fp = cfg.effect(eff).params
        row("readout [s]", p["readout_time_s"], fp.readout_time_s, 0.2, rel=True,
            key="rolling_shutter.readout_time_s")
    elif eff == "low_reflectance":
        row("signal50", p["signal50"], cfg.effect(eff).params.signal50, 0.25, rel=True, key="low_reflectance.signal50")
    return rows


DEPTH_SPAN_PERCENTILES = (2.0, 98.0)
"""A depth bias is scored at those of 1, 2, 3 m that lie inside this percentile range of the ideal
depths of the measured valid pixels (:func:`depth_span`), and where none does, at the one nearest
their median. Beyond the data the bias's three terms (offset, scale, disparity offset) are nearly
collinear (blind sensor 15: 1.9-3.8 m, the fit's bias at 2 and 3 m within 1 mm, at 1 m 6 mm off),
and the bias extrapolated there is the choice of terms, not a measurement."""


def depth_span(ms) -> tuple[float, float, float]:
    """(low, high, median) ideal depth, m, of the measured valid pixels of every frame of ``ms``
    (:data:`DEPTH_SPAN_PERCENTILES`)."""
    z = []
    for k in range(len(ms)):
        ideal = ms.render(k).depth
        z.append(ideal[(ms.measured_depth(k) > 0) & (ideal > 0)])
    z = np.concatenate(z)
    lo, hi, med = np.percentile(z, [*DEPTH_SPAN_PERCENTILES, 50.0])
    return float(lo), float(hi), float(med)


def mark_scored(rows: list[dict], span: tuple[float, float, float]) -> list[dict]:
    """Set ``scored`` on every row: False for a bias row whose depth lies outside ``span`` (low, high,
    median; :data:`DEPTH_SPAN_PERCENTILES`), unless no bias row lies inside, then the one nearest
    the median is scored."""
    lo, hi, med = span
    deep = [r for r in rows if "depth_m" in r]
    inside = [r for r in deep if lo <= r["depth_m"] <= hi]
    if deep and not inside:
        inside = [min(deep, key=lambda r: abs(r["depth_m"] - med))]
    for r in rows:
        r["scored"] = "depth_m" not in r or any(r is x for x in inside)
    return rows


def _row(eff: str, q: str, t: float, f: float, tol: float, rel: bool, at_bound: bool = False) -> dict:
    """One recovery row: the true and fitted value of quantity ``q`` and whether the error (relative
    to the truth when ``rel``) is within ``tol``."""
    err = (f - t) / t if rel else f - t
    return {"effect": eff, "quantity": q, "true": t, "fitted": f, "error": err, "tolerance": tol,
            "relative": rel, "within": abs(err) <= tol, "at_bound": at_bound}


def band_time_rows(gen: str, truth: dict, cfg, band: float) -> list[dict]:
    """The rolling shutter's band-time row (the mystery and blind generators'): readout x (band row -
    reference row), what the data fix (``band``: the band-centre row, :func:`band_row`), true against fitted,
    the readout's 20 % tolerance; none for another generator or effect, or a band row that is not
    finite."""
    if gen not in ("mystery", "blind") or truth["effect"] != "rolling_shutter" or not math.isfinite(band):
        return []
    p = truth["raw"]["params"]
    fp = cfg.effect("rolling_shutter").params
    # the mystery generator stamps the first row (answer reference_row 0), the blind one row 0, 0.5 or 1
    # of the image (its answer's reference_row, in the lab's convention v / (H - 1))
    return [_row("rolling_shutter", BAND_QUANTITY, p["readout_time_s"] * (band - p.get("reference_row", 0.0)),
                 fp.readout_time_s * (band - fp.reference_row), 0.2, True)]


def implausible(params: dict, ms) -> list[str]:
    """Fitted parameters outside :data:`SENSOR_LIMITS`, and range limits cutting measured pixels."""
    out = []
    for k, v in params.items():
        if k in SENSOR_LIMITS and isinstance(v, (int, float)):
            lo, hi = SENSOR_LIMITS[k]
            if not lo - 1e-12 <= v <= hi + 1e-12:
                out.append(f"{k}={v:.4g} outside [{lo:g}, {hi:g}]")
    z = np.concatenate([ms.measured_depth(k)[ms.measured_depth(k) > 0] for k in range(len(ms))])
    lo, hi = np.percentile(z, [0.5, 99.5])
    mn, mx = params.get("range_limits.min_depth_m", 0.0), params.get("range_limits.max_depth_m", 0.0)
    if mn and mn > lo:
        out.append(f"range_limits.min_depth_m={mn:.3f} above the measured 0.5th percentile {lo:.3f}")
    if mx and mx < hi:
        out.append(f"range_limits.max_depth_m={mx:.3f} below the measured 99.5th percentile {hi:.3f}")
    return out


def generator_effects(gen: str) -> tuple[str, ...]:
    """The hidden effects a generator can hide."""
    if gen == "hidden":
        from tests import hidden_effects as he
        return tuple(he.HIDDEN_EFFECTS)
    if gen == "blind":
        from tests import blind_sensor
        return tuple(blind_sensor.EFFECTS)
    from synth.lab import mystery
    return mystery.EFFECTS


def run_case(gen: str, effect: str, seed: int, tmp: Path, frames: int, w: int, h: int, draws: int,
             fit_config, diagnose_config) -> dict:
    """One sequence through diagnose, the two fits and the floor; returns the case's record."""
    from synth.lab import MeasuredSequence, diagnose, fit_model
    from synth.lab.compare import CompareConfig, compare
    t0 = time.perf_counter()
    path = tmp / f"{gen}_{effect}_{seed}"
    truth = make(gen, path, effect, seed, frames, w, h)
    ms = MeasuredSequence.load(path)
    base = ["axial_noise", "range_limits"]
    rec = {"generator": gen, "effect": effect, "seed": seed}
    try:
        d = diagnose(ms, ms.default_config(base), fit_config=fit_config, diagnose_config=diagnose_config)
        rec["ranking"] = [(c.effect, round(float(c.gain), 4)) for c in d.ranking[:4]]
        rec["rank_first"] = bool(d.ranking) and d.ranking[0].effect == effect
        rec["ties"] = list(getattr(d, "ties", []))
        rec["tie_first"] = (not rec["rank_first"] and bool(d.ranking)
                            and any(effect in t and d.ranking[0].effect in t for t in rec["ties"]))
        rec["diagnose_implausible"] = sorted(set(implausible(getattr(d, "model_params", {}) or {}, ms)
                                                 + (implausible(d.ranking[0].params, ms) if d.ranking else [])))
    except Exception as exc:         # an error in the diagnosis is a failed case, reported
        rec["ranking"], rec["rank_first"], rec["diagnose_implausible"] = f"error: {exc}", False, []
    cc = CompareConfig()
    meas_gaps = {}
    for name, effects in (("without", base), ("with", base + [effect])):
        res = fit_model(ms, ms.default_config(effects), fit_config=fit_config)
        meas_gaps[name] = float(np.mean([compare(ms.observations(ms.simulate(res.config, i)), cc).gap
                                         for i in range(draws)]))
        if name == "without":
            rec["base_implausible"] = implausible(res.params, ms)
        if name == "with":
            rec["depth_span_m"] = span = depth_span(ms)
            rec["rows"] = mark_scored(recovery_rows(gen, truth, res.config, ms.preset.fb, set(res.at_bound)), span)
            rec["recovered"] = all(r["within"] for r in rec["rows"] if r["scored"])
            # recovered with the observable band time in place of the readout (= recovered elsewhere)
            rec["recovered_band"] = rec["recovered"]
            if effect == "rolling_shutter":
                rec["band_row"] = band = band_row(ms)
                rec["band_rows"] = band_time_rows(gen, truth, res.config, band)
                rec["recovered_band"] = all(r["within"] for r in rec["rows"] + rec["band_rows"]
                                            if r["quantity"] != "readout [s]" and r.get("scored", True))
            rec["fit_implausible"] = implausible(res.params, ms)
            rec["fitted"] = {k: v for k, v in res.params.items() if isinstance(v, (int, float))}
    floors = []
    for i in range(max(draws, FLOOR_RERUNS)):       # >= 3 re-runs: the floor and the gap's own noise
        again = path.with_name(path.name + f"_again{i}")
        make(gen, again, effect, seed, frames, w, h, noise_seed=seed + 1000 + i)
        am = MeasuredSequence.load(again)
        floors.append(compare(ms.observations([am.measured_depth(k) for k in range(len(ms))]), cc).gap)
    rec["floor_gap"] = float(np.mean(floors[:max(draws, 1)]))
    rec["floor_gaps"] = [float(f) for f in floors]
    rec.update({f"{k}_gap": v for k, v in meas_gaps.items()})
    den = rec["without_gap"] - rec["floor_gap"]
    rec["closure"] = (rec["without_gap"] - rec["with_gap"]) / den if den > 0 else float("nan")
    rec["gap_noise"] = gap_noise(floors)
    rec["observable"] = observable(rec["without_gap"], rec["with_gap"], floors,
                                   diagnosed_gain(rec.get("ranking"), effect))
    rec["seconds"] = time.perf_counter() - t0
    return rec


FLOOR_RERUNS = 3
"""Re-runs of the generator (other noise seeds) compared with the measurement: their mean is the
floor, their spread the gap's own sampling noise on these frames."""
NOISE_SIGMAS = 2.0
"""The true effect's gain must exceed this many standard deviations of a difference of two gaps."""


def gap_noise(floors) -> float:
    """Standard deviation of the difference of two gaps of one sequence (sqrt 2 x the sample std of
    the re-run floors: each is one draw of the gap at zero model error); NaN with < 2 floors."""
    f = np.asarray(floors, float)
    return float(math.sqrt(2.0) * f.std(ddof=1)) if f.size >= 2 else float("nan")


def observable(without_gap: float, with_gap: float, floors, diagnosed_gain: float | None = None) -> bool:
    """False when the hidden effect is shown to be unobservable on these frames: the base model plus
    the TRUE effect, fitted, lowers the gap of the base model alone by no more than
    :data:`NOISE_SIGMAS` x :func:`gap_noise` (the data cannot tell the model with the effect from
    the one without, even knowing which effect it is; e.g. an edge fattening whose jump threshold no
    edge of the drawn scene reaches), and so does the diagnosis (``diagnosed_gain``: the true
    effect's relative gain there, x ``without_gap``; a fit that missed what the diagnosis found
    does not make an effect unobservable). Such a case is reported apart, not as a miss."""
    noise = gap_noise(floors)
    if not math.isfinite(noise):
        return True
    gains = [without_gap - with_gap] + ([diagnosed_gain * without_gap] if diagnosed_gain is not None else [])
    return max(gains) > NOISE_SIGMAS * noise


def diagnosed_gain(ranking, effect: str) -> float | None:
    """The true effect's relative gain in a case's ``ranking`` (the top few, (effect, gain)); when
    it is not among them, the smallest listed gain (an upper bound); None without a ranking."""
    if not isinstance(ranking, list) or not ranking:
        return None
    g = dict((e, float(x)) for e, x in ranking)
    return g.get(effect, max(min(g.values()), 0.0))


def summary(records: list[dict]) -> str:
    """One block per generator: rank-first, recovered, median closure, implausible fits."""
    lines = []
    for gen in sorted({r["generator"] for r in records}):
        rs = [r for r in records if r["generator"] == gen]
        rows = [x for r in rs for x in r["rows"] if x.get("scored", True)]
        clo = [r["closure"] for r in rs if not math.isnan(r["closure"])]
        imp = [(r["effect"], r["seed"], x) for r in rs
               for x in r["fit_implausible"] + r["diagnose_implausible"] + r.get("base_implausible", [])]
        lines += [f"{gen}: rank-first {sum(r['rank_first'] for r in rs)} of {len(rs)}; recovered (every scored row of the case) "
                  f"{sum(r['recovered'] for r in rs)} of {len(rs)}; parameter rows within tolerance "
                  f"{sum(x['within'] for x in rows)} of {len(rows)}; closure >= 50 % in "
                  f"{sum(c >= 0.5 for c in clo)} of {len(clo)} (median {np.median(clo) if clo else float('nan'):.2f}); "
                  f"implausible fitted parameters: {len(imp)}"]
        obs = [r for r in rs if r.get("observable", True)]
        rsh = [r for r in rs if r.get("band_rows")]
        if rsh:
            lines += [f"    rolling shutter, band time readout x (band row - reference row) instead of the readout: "
                      f"recovered {sum(r['recovered_band'] for r in rsh)} of {len(rsh)} (readout: "
                      f"{sum(r['recovered'] for r in rsh)}); every case with the band time: "
                      f"{sum(r.get('recovered_band', r['recovered']) for r in rs)} of {len(rs)}, observable "
                      f"{sum(r.get('recovered_band', r['recovered']) for r in obs)} of {len(obs)}"]
        ties = [r for r in rs if r.get("tie_first")]
        lines += [f"    observable cases (the true effect's gain > {NOISE_SIGMAS:g} x the gap's noise): rank-first "
                  f"{sum(r['rank_first'] for r in obs)} of {len(obs)}, recovered {sum(r['recovered'] for r in obs)} "
                  f"of {len(obs)}; unobservable (not counted as misses): {len(rs) - len(obs)} "
                  f"{[(r['effect'], r['seed']) for r in rs if not r.get('observable', True)]}; "
                  f"rank misses inside a named tie (the first and the truth named together: the data cannot tell them "
                  f"apart): {len(ties)} {[(r['effect'], r['seed']) for r in ties]}"]
        lines += [f"    implausible: {e} seed {s}: {x}" for e, s, x in imp]
    return "\n".join(lines)


def print_case(r: dict) -> None:
    imp = r["fit_implausible"] + r["diagnose_implausible"] + r.get("base_implausible", [])
    bad = [f"{x['quantity']} true {x['true']:.4g} fitted {x['fitted']:.4g}" for x in r["rows"]
           if not x["within"] and x.get("scored", True)]
    out = [f"{x['quantity']} {x['error'] * 1000:+.1f} mm" for x in r["rows"] if not x.get("scored", True)]
    if out:
        lo, hi, _ = r["depth_span_m"]
        bad_or_ok = f" (not scored, outside the data's {lo:.2f}-{hi:.2f} m: {', '.join(out)})"
    else:
        bad_or_ok = ""
    print(f"{r['generator']:8s} {r['effect']:23s} seed {r['seed']:3d}: rank-first {'yes' if r['rank_first'] else 'NO '} "
          f"{r['ranking']}; recovered {'yes' if r['recovered'] else 'NO: ' + '; '.join(bad)}{bad_or_ok}; "
          + "".join(f"band time (row {r['band_row']:.2f}) true {x['true']:.4f} fitted {x['fitted']:.4f} "
                    f"{'yes' if x['within'] else 'NO'}; " for x in r.get("band_rows", []))
          + f"closure "
          f"{100 * r['closure']:.0f} % (gap {r['without_gap']:.3f} -> {r['with_gap']:.3f}, floor {r['floor_gap']:.3f}); "
          f"noise {r.get('gap_noise', float('nan')):.4f}; {r['seconds']:.0f} s"
          + ("" if r.get("observable", True) else "; UNOBSERVABLE")
          + (f"; TIE {r['ties']}" if r.get("ties") else "") + (f"; IMPLAUSIBLE {imp}" if imp else ""), flush=True)
