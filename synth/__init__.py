"""realgap synth package: built-in scenes, loaders, camera trajectories, ideal ray-cast rendering
and synthetic sequence generation (depth-sensor models live in ``synth.sensor``).

Main entry points (importing them is cheap; Open3D is loaded on first render)::

    from synth import build_scene, IdealRenderer, generate_sequence, SequenceConfig
    scene = build_scene("room", seed=0)
    result = IdealRenderer(scene).render(pose_c2w, intrinsics)
"""
from synth.render import IdealRenderer, RenderResult
from synth.scenes import SCENES, build_scene, register_scene, scene_names
from synth.sequence import GenerateResult, SequenceConfig, generate_sequence
from synth.trajectories import TRAJECTORY_KINDS, handheld_jitter, orbit, walkthrough

__all__ = ["IdealRenderer", "RenderResult", "SCENES", "build_scene", "register_scene", "scene_names",
           "GenerateResult", "SequenceConfig", "generate_sequence", "TRAJECTORY_KINDS", "handheld_jitter",
           "orbit", "walkthrough"]
