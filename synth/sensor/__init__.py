"""Physical depth-sensor simulation (DepthSynth-style): projector -> IR capture -> block matching.

Public API::

    from synth.sensor import SensorSimulator, SensorConfig, SimResult, get_preset, effect_names
    sim = SensorSimulator("kinect_v1", scene=scene)      # physical pipeline
    res = sim.simulate(pose_c2w, seed=0, prev_pose=None)
    sim.camera()                                         # camera.json with the sensor block
    render_views(model, sim, out_dir)                    # object-centred views (synth.sensor.views)

Submodules: presets (devices), registry (effect base class + registry), effects/ (one module
per effect), pattern (dot patterns), matching (block matching), state (what effects share within
a frame), config (SensorConfig: a preset + effects), simulator (SensorSimulator, one frame), pool
(trajectories, worker processes), views (object-centred views), validation (checks against physics).
"""
from synth.sensor.pattern import DotPattern, generate_dot_pattern, load_pattern
from synth.sensor.presets import PRESETS, SensorPreset, get_preset
from synth.sensor.registry import Effect, effect_class, effect_names, make_effect, register_effect
from synth.sensor.config import MotionLimits, SensorConfig
from synth.sensor.pool import SimulationPool, simulate_trajectory
from synth.sensor.simulator import SensorSimulator, SimResult, list_presets

__all__ = ["DotPattern", "generate_dot_pattern", "load_pattern", "PRESETS", "SensorPreset", "get_preset",
           "Effect", "effect_class", "effect_names", "make_effect", "register_effect", "MotionLimits", "SensorConfig",
           "SensorSimulator", "SimResult", "list_presets", "simulate_trajectory", "SimulationPool", "render_views"]


def render_views(*args, **kwargs):
    """See :func:`synth.sensor.views.render_views` (imported lazily)."""
    from synth.sensor.views import render_views as _rv
    return _rv(*args, **kwargs)
