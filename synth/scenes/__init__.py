"""Scenes: the registry (:mod:`~synth.scenes.registry`), the embedded procedural scenes
(:mod:`~synth.scenes.builtin`: room, chair_a/b/c) and file-based scenes (:mod:`~synth.scenes.loaders`:
SceneNN/SceneNet rooms, T-LESS objects). Importing this package registers all of them::

    from synth.scenes import build_scene
    scene = build_scene("room", seed=0)
"""
from synth.scenes.registry import (SCENES, SceneBuilder, build_scene, describe_scenes, register_scene,
                                   scene_names, scene_parameters)
from synth.scenes.builtin import (CHAIR_VARIANTS, MATERIALS, chair_meshes, object_instance_ids,  # noqa: E402
                                  object_name, pose_matrix)
import synth.scenes.loaders  # noqa: E402,F401  (registers scenenet_room, tless_obj)

__all__ = ["SCENES", "SceneBuilder", "build_scene", "describe_scenes", "register_scene", "scene_names",
           "scene_parameters", "CHAIR_VARIANTS", "MATERIALS", "chair_meshes", "object_instance_ids",
           "object_name", "pose_matrix"]
