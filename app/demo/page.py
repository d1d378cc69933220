"""``demo_out/index.html``: the demo's three parts on one page, key figures inline, plain words on
what each shows, links to every report the demo wrote."""
from __future__ import annotations

import html
import os
from pathlib import Path

__all__ = ["write_index"]


def _rel(path: str | None, root: Path) -> str:
    return os.path.relpath(path, root).replace(os.sep, "/") if path else ""


def _img(path: str | None, root: Path, alt: str, width: str = "100%") -> str:
    if not path or not Path(path).is_file():
        return f"<p class='note'>({html.escape(alt)}: not available)</p>"
    return f"<img src='{html.escape(_rel(path, root))}' alt='{html.escape(alt)}' style='max-width:{width}'>"


def _link(path: str | None, root: Path, text: str) -> str:
    if not path or not Path(path).exists():
        return html.escape(text) + " (missing)"
    return f"<a href='{html.escape(_rel(path, root))}'>{html.escape(text)}</a>"


def _fmt_params(p: dict | None) -> str:
    if not p:
        return "-"
    return ", ".join(f"{k} = {v:.4g}" if isinstance(v, float) else f"{k} = {v}" for k, v in p.items())


def _lab(f: dict, root: Path) -> str:
    hist = "".join(f"<tr><td>{html.escape(str(h.get('label') or h.get('effects') or ''))}</td>"
                   f"<td>{h['gap']:.3f}</td></tr>" for h in f["history"])
    verdict = "found it" if f["found_effect"] == f["hidden_effect"] else "named another effect"
    return f"""
<h2>1. The sensor lab finds what a depth sensor does that the model does not</h2>
<p>A <em>mystery sensor</em> (a generator written apart from our simulator: its own camera, its own
raw-disparity conversion and scenes) recorded a sequence with one physical effect hidden. The lab compared it
with the ideal model and with a base model (axial noise and range limits, fitted), then asked every effect it
knows which one would explain the rest of the difference, added the winner with fitted parameters and compared
again. The <b>gap</b> measures how differently the errors of the measured and simulated depth are distributed
(0 = indistinguishable).</p>
<table><tr><th>model</th><th>gap</th></tr>{hist}</table>
<p><b>Diagnosis:</b> <code>{html.escape(f['found_effect'])}</code>
(gain {100 * (f['found_gain'] or 0):.0f} %). Evidence: <i>{html.escape(f['evidence'] or '-')}</i></p>
<p><b>The hidden answer:</b> <code>{html.escape(str(f['hidden_effect']))}</code>
({html.escape(_fmt_params(f['hidden_parameters']))}); the lab {verdict}, fitted
{html.escape(_fmt_params(f['fitted_parameters']))}.</p>
<p>{_link(f['report'], root, 'lab report (gap history, where the model fails)')} &middot;
{_link(f['diagnosis'], root, 'diagnosis (each candidate with its signature figure)')}</p>
"""


def _explore(f: dict, root: Path) -> str:
    rows = "".join(
        f"<tr><td>{b}</td><td>{html.escape(str(r.get('align') or 'se3'))}</td>"
        f"<td>{(r.get('ate_rmse_m') or float('nan')) * 100:.1f}</td>"
        f"<td>{(r.get('ape_median_m') or float('nan')) * 100:.1f}</td>"
        f"<td>{(r.get('frames_per_second') or float('nan')):.1f}</td><td>{'ok' if r.get('ok') else 'failed'}</td></tr>"
        for b, r in f["backends"].items())
    shot = (_img(f["screenshot"], root, "viewer screenshot") if f.get("screenshot")
            else f"<p class='note'>{html.escape(f.get('screenshot_note') or 'no viewer screenshot')}</p>")
    return f"""
<h2>2. Exploration: classic and neural registration of the same walk</h2>
<p>A ground robot walked {f['frames']} frames through a furnished room the neural model never saw in training,
measured by our full Kinect v1 simulation (projector, IR camera, block matching). <code>icp</code> registers
every frame against a TSDF model; <code>neural</code> writes every tenth frame into an allocentric neural memory
(thesis ch. 4) and localises in it. ATE and APE median after the alignment in the second column (auto: SE(3)
when a run's motion determines a rotation - at least 10 poses spread in two directions - else its first pose).</p>
<table><tr><th>backend</th><th>alignment</th><th>ATE RMSE (cm, after alignment)</th>
<th>APE median (cm, after alignment)</th><th>frames/s</th><th></th></tr>{rows}</table>
{_img(f['comparison_plot'], root, 'comparison plot', '45%')}
<p>Novel views at one pose: the TSDF ray cast copies what was seen; the memory recalls it from its features, and
turned 90 deg to the right its hallucination module fills cells nobody observed.</p>
{_img(f['views']['figure'], root, 'novel views')}
<p>The viewer (<code>realgap view</code>) on the same runs: mesh, trajectories coloured by error, current frame.</p>
{shot}
<p>{_link(f['report'], root, 'batch report (table, per-sequence pages)')}</p>
"""


def _recog(f: dict, root: Path) -> str:
    figs = " &middot; ".join(_link(p, root, Path(p).stem) for p in f["figures"])
    rot_b, rot_a = f["rot_err_deg_median_before_icp"], f["rot_err_deg_median"]
    fmt = (lambda x: "-" if x is None else f"{x:.1f}")
    return f"""
<h2>3. Recognition from simulated scans only</h2>
<p>{f['scans']} scans of three office chairs made by another sensor (the Structure preset) than the one the
recogniser was trained with; no real image was used in training. The triplet-CNN descriptor votes for the chair
and its pose, ICP against the CAD models verifies and refines.</p>
<table><tr><th>accuracy</th><th>descriptor vote alone</th><th>rotation error median before / after ICP</th>
<th>translation error median</th></tr>
<tr><td>{100 * f['accuracy']:.0f} %</td><td>{100 * f['accuracy_descriptor']:.0f} %</td>
<td>{fmt(rot_b)} / {fmt(rot_a)} deg</td><td>{fmt((f['trans_err_m_median'] or 0) * 1000)} mm</td></tr></table>
{_img(f['overlay'], root, 'CAD models over the scans')}
<p>{_link(f['eval'], root, 'eval.json')} &middot; {figs}</p>
"""


def write_index(out: Path, facts: dict) -> Path:
    """Write ``out/index.html`` from the facts of :func:`app.demo.run.run_demo`."""
    from data_tools.results import atomic_write_text
    out = Path(out)
    body = _lab(facts["lab"], out) + _explore(facts["explore"], out) + _recog(facts["recog"], out)
    page = f"""<!doctype html><html><head><meta charset='utf-8'><title>realgap demo</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:2em auto;line-height:1.45;color:#222}}
table{{border-collapse:collapse;margin:0.6em 0}}td,th{{border:1px solid #bbb;padding:3px 9px;text-align:right}}
th{{background:#eee}}td:first-child{{text-align:left}}code{{background:#f3f3f3;padding:0 3px}}
.note{{color:#777}}img{{display:block;margin:0.5em 0;border:1px solid #ddd}}</style></head><body>
<h1>realgap: the demo</h1>
<p>realgap bridges the realism gap between simulated and real depth data. This page was written by
<code>realgap demo</code> in {facts['seconds']:.0f} s; every number comes from this run
(configuration: {_link(str(out / 'demo_config.json'), out, 'demo_config.json')},
numbers: {_link(str(out / 'summary.json'), out, 'summary.json')}).</p>
{body}
</body></html>
"""
    return atomic_write_text(out / "index.html", page)
