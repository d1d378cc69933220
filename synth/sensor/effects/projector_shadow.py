"""Direct model: pixels the projector (or the second stereo camera) cannot see are holes."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.sensor.registry import STAGE_DROPOUT, Effect, Signature, param, register_effect


@dataclass
class ProjectorShadowParams:
    eps_m: float = param(0.002, "m")
    """Free gap at both ends of each shadow ray, metres (no self-shadowing)."""
    method: str = param("hybrid", "", choices=("hybrid", "raycast"))
    """``raycast``: one shadow ray per valid pixel; ``hybrid`` (default): the same shadows
    with exact rays only where the rectified-rig ordering test cannot rule a shadow out (see
    :func:`synth.sensor.effects.pattern_projection.hybrid_shadow`)."""


@register_effect
class ProjectorShadow(Effect):
    """Holes where the surface is hidden from the projector (structured light) or from the
    second camera (active stereo).

    Physics: the projector sits ``baseline`` to the side of the camera, so a foreground object
    casts a shadow on the background that the camera can see: no pattern, no depth. With the
    projector at +x (right of the camera in the image) the shadow band lies on the LEFT (-u)
    side of the object, ``f b (1/z_fg - 1/z_bg)`` pixels wide. The same geometry makes a band
    of background visible to only one camera of a stereo pair. Implementation: one shadow ray
    per valid pixel through the scene's RaycastingScene, plus back-facing surfaces (projector
    behind the surface), ruled out for most pixels by the ordering test of ``method`` hybrid.
    The physical pipeline gets this inside ``pattern_projection``; this is the direct
    stand-in. No-op for ToF (illuminator next to the lens).
    """

    name = "projector_shadow"
    SIGNATURE = Signature(
        "holes beside foreground objects on the projector side",
        "Holes on the background next to depth edges, only on the side where the projector is "
        "occluded (+ distances: shadow side), as wide as the disparity step; the lit side (- "
        "distances) stays valid.",
        plot="shadow_sides")
    sensor_types = ("structured_light", "active_stereo")  # triangulation
    Params = ProjectorShadowParams
    FITTABLE = {"eps_m": (0.0, 0.05)}
    stage = STAGE_DROPOUT

    def source_offset(self, preset):
        if preset.type == "active_stereo":
            return (preset.projector_side * preset.baseline_m, 0.0, 0.0)
        return tuple(preset.projector_offset_m)

    def apply(self, state, draw) -> None:
        from synth.sensor.effects.pattern_projection import hybrid_shadow, normalized_coords, shadow_test
        if state.preset.type == "tof" or state.baseline_free():
            state.log[self.name] = {"active": False}
            return
        renderer = state.require_renderer(self.name)
        v = state.view
        src = np.asarray(self.source_offset(state.preset), np.float32)
        xn, yn = normalized_coords(state.ray_dirs_cam)
        Z = np.where(v.hit, v.points_cam[..., 2], np.float32(0)).astype(np.float32)
        Lx, Ly, Lz = xn * Z - src[0], yn * Z - src[1], Z - src[2]
        n = v.normals_cam
        back = (n[..., 0] * Lx + n[..., 1] * Ly + n[..., 2] * Lz) >= 0   # source behind the surface
        cand = state.valid & v.hit & ~back
        r = np.sqrt(Lx * Lx + Ly * Ly + Lz * Lz)
        if self.params.method == "hybrid":
            ok = v.hit & (Lz > 1e-4)
            # column of the source's image (any pinhole along the camera axes orders rays the
            # same way; the camera's focal length sets the scale of the 0.05 px tolerance)
            up = np.where(ok, np.float32(state.intr.fx) * Lx / np.where(ok, Lz, np.float32(1.0)),
                          np.float32(-10.0)).astype(np.float32)
            sh, n_rays = hybrid_shadow(renderer, v, src, up, ok, xn, yn, Lx, Lz, r, cand, self.params.eps_m)
        else:
            sh, n_rays = shadow_test(renderer, v, src, r, cand, self.params.eps_m), int(cand.sum())
        shadow = (back & v.hit) | sh
        state.invalidate(shadow, self.name)
        state.log[self.name]["shadow_rays"] = n_rays

    @classmethod
    def evidence(cls, ctx, params: dict, gain: float | None = None) -> str:
        """Hole rate within 6 px of depth edges on the projector-shadow side vs the lit side.

        Signature present: the shadow-side rate exceeds the lit-side rate and the current model's
        shadow-side rate by :data:`ctx.MIN_RATE_EXCESS` and is at least 1.5x the lit-side rate."""
        off = ctx.observations[0].projector_offset_m
        if off is None:
            return "the sensor has no projector offset: no projector shadows can form."
        es = ctx.shadow_edge_distance()
        hole_m = ctx.measured <= 0
        hole_s = ctx.simulated <= 0
        near = 6.0
        sh = (es > 0) & (es <= near)
        lit = (es < 0) & (es >= -near)
        if int(sh.sum()) < 50:
            return ctx.weak("projector-shadow signature", gain,
                         f"only {int(sh.sum())} pixels lie within {near:g} px on the projector-shadow side of depth edges")
        r_sh, r_lit, r_mod = ctx.rate(hole_m, sh), ctx.rate(hole_m, lit), ctx.rate(hole_s, sh)
        share = float((hole_m & sh).sum()) / max(int(hole_m.sum()), 1)
        numbers = (f"within {near:g} px of depth edges the sensor loses {ctx.pct(r_sh)} of the pixels on the "
                   f"projector-shadow side and {ctx.pct(r_lit)} on the lit side (current model: {ctx.pct(r_mod)} on the "
                   f"shadow side)")
        strong = (ctx.ge(r_sh, r_lit + ctx.MIN_RATE_EXCESS) and ctx.ge(r_sh, 1.5 * r_lit)
                  and ctx.ge(r_sh, r_mod + ctx.MIN_RATE_EXCESS))
        if not strong:
            return ctx.weak("projector-shadow signature", gain, numbers)
        return (f"within {near:g} px of depth edges the sensor loses {ctx.pct(r_sh)} of the pixels on the "
                f"projector-shadow side against {ctx.pct(r_lit)} on the lit side (current model: {ctx.pct(r_mod)} on the "
                f"shadow side); these shadow-side holes are {ctx.pct(share)} of all measured holes.")
