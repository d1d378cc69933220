"""The contract every registered sensor effect passes (like kornia's shared test base or
scikit-learn's ``check_estimator``): a new effect gets these tests for free, parametrised over
:func:`synth.sensor.registry.effect_names`.

For each effect the checks run it where it belongs: a direct (analytic) effect alone on the
ideal depth, a stage of the physical pipeline inside its preset's physical pipeline. The scene
is a small room view (64x48 crop of the preset, a camera moving at walking speed so the motion
effects act), on the first preset whose sensor type the effect models.

Checked: same seed -> same output; another seed -> another draw (effects that draw); disabled
-> identity (for effects the pipeline can run without); the effect's declared zero-strength
parameters (``Effect.IDENTITY_PARAMS``) -> identity; dtypes and shapes kept; pixels invalid
before the effect stay invalid unless ``Effect.KEEPS_INVALID`` is False (its documented purpose
is to make new ones); no NaN/inf; parameters round-trip through the model JSON; an
out-of-bound fittable parameter gives a one-line ConfigError naming the effect and the
parameter; direct effects work on 1x1 and 3x640 images.
"""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from data_tools.errors import ConfigError
from synth.scenes import build_scene
from synth.sensor import SensorConfig, SensorSimulator, get_preset
from synth.sensor.registry import effect_class, effect_names
from synth.sensor.simulator import SimResult

PRESET_FOR_TYPE = {"structured_light": "kinect_v1", "active_stereo": "realsense_d435", "tof": "kinect_v2"}
W, H = 64, 48


def _pose(t: float) -> np.ndarray:
    """A camera 1.5 m up in the room, looking along +x and a little down, at time t (s)."""
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]) @ \
        np.array([[1.0, 0.0, 0.0], [0.0, np.cos(0.35), -np.sin(0.35)], [0.0, np.sin(0.35), np.cos(0.35)]])
    T[:3, 3] = [-1.2 + 0.8 * t, -0.4 + 0.3 * t, 1.5]
    return T


@pytest.fixture(scope="module")
def scene():
    return build_scene("room", seed=0)


def _preset_for(cls):
    types = cls.sensor_types or ("structured_light",)
    return get_preset(PRESET_FOR_TYPE[types[0]]).cropped(W, H)


def _model(cls, params=None, enabled=True) -> SensorConfig:
    """The effect where it runs: in its preset's physical pipeline when it is a stage of it,
    else alone on the ideal depth."""
    pre = _preset_for(cls)
    spec = {"name": cls.name, "enabled": enabled, "params": {**pre.effect_params.get(cls.name, {}), **(params or {})}}
    if cls.name in pre.physical_effects and pre.type != "tof":
        names = list(pre.physical_effects)
        effs = [spec if n == cls.name else {"name": n, "params": pre.effect_params.get(n, {})} for n in names]
    else:
        effs = [spec]
    return SensorConfig.build(pre, effs)


def _without(cls) -> SensorConfig:
    cfg = _model(cls)
    return dataclasses.replace(cfg, effects=[e for e in cfg.effects if e.name != cls.name])


def _run(cfg: SensorConfig, scene, seed: int = 1) -> SimResult:
    sim = SensorSimulator(cfg, scene=scene)
    return sim.simulate(_pose(1 / 30), seed=seed, prev_pose=_pose(0.0))


def _same(a: SimResult, b: SimResult) -> bool:
    return np.array_equal(a.depth, b.depth) and np.array_equal(a.valid, b.valid)


NAMES = effect_names()


def test_every_registered_effect_is_covered():
    assert len(NAMES) >= 20, NAMES


@pytest.mark.parametrize("name", NAMES)
def test_same_seed_same_output_and_sane_arrays(name, scene):
    cls = effect_class(name)
    a, b = _run(_model(cls), scene), _run(_model(cls), scene)
    assert _same(a, b)
    assert a.depth.dtype == np.float32 and a.depth.shape == (H, W)
    assert a.valid.dtype == bool and a.valid.shape == (H, W)
    assert np.isfinite(a.depth).all()
    assert np.array_equal(a.valid, a.depth > 0)
    replay = SensorSimulator(_model(cls), scene=scene).simulate(_pose(1 / 30), prev_pose=_pose(0.0), draws=a.draws)
    assert _same(a, replay)


def _draw_arrays(d):
    if d is None:
        return []
    if isinstance(d, dict):
        return [np.asarray(v) for v in d.values() if v is not None]
    return [np.asarray(d)]


@pytest.mark.parametrize("name", NAMES)
def test_another_seed_another_draw(name, scene):
    cls = effect_class(name)
    a, b = _run(_model(cls), scene, seed=1), _run(_model(cls), scene, seed=2)
    da, db = _draw_arrays(a.draws.get(name)), _draw_arrays(b.draws.get(name))
    if not da:
        pytest.skip(f"{name} draws nothing at random")
    assert any(not np.array_equal(x, y) for x, y in zip(da, db)), f"{name}: seeds 1 and 2 gave the same draw"


@pytest.mark.parametrize("name", NAMES)
def test_disabled_is_identity(name, scene):
    cls = effect_class(name)
    if cls.REQUIRED_IN_PIPELINE and name in _preset_for(cls).physical_effects:
        pytest.skip(f"{name} is a stage the physical pipeline cannot run without")
    assert _same(_run(_model(cls, enabled=False), scene), _run(_without(cls), scene))


@pytest.mark.parametrize("name", NAMES)
def test_zero_strength_is_identity(name, scene):
    cls = effect_class(name)
    if cls.IDENTITY_PARAMS is None:
        pytest.skip(f"{name} has no zero-strength setting (a stage of the physical pipeline)")
    assert _same(_run(_model(cls, cls.IDENTITY_PARAMS), scene), _run(_without(cls), scene)), \
        f"{name} with {cls.IDENTITY_PARAMS} changed the output"


@pytest.mark.parametrize("name", NAMES)
def test_invalid_pixels_stay_invalid(name, scene):
    """Pixels removed before the effect runs stay removed (unless the effect's purpose is to
    make new measurements: KEEPS_INVALID = False)."""
    cls = effect_class(name)
    if not cls.KEEPS_INVALID:
        pytest.skip(f"{name} makes new measurements by design (KEEPS_INVALID = False)")
    sim = SensorSimulator(_model(cls), scene=scene)
    state, _, _ = sim.make_state(_pose(1 / 30), _pose(0.0))
    rng = np.random.default_rng(0)
    holes = rng.random(state.shape) < 0.3
    effects = list(state.model.values())
    k = [e.name for e in effects].index(name)
    for e in effects[:k]:
        e.apply(state, e.sample(e.rng(1), state))
    state.invalidate(holes, "test")
    e = effects[k]
    e.apply(state, e.sample(e.rng(1), state))
    assert not (state.valid & holes).any() and not (state.depth[holes] != 0).any(), \
        f"{name} gave a value to {(state.valid & holes).sum()} pixels that were invalid"


@pytest.mark.parametrize("name", NAMES)
def test_parameters_round_trip_through_model_json(name, tmp_path):
    cls = effect_class(name)
    cfg = _model(cls)
    path = cfg.save(tmp_path / "model.json")
    back = SensorConfig.load(path)
    assert json.dumps(back.to_json(), sort_keys=True) == json.dumps(cfg.to_json(), sort_keys=True)
    assert back.effect(name).params == cfg.effect(name).params


@pytest.mark.parametrize("name", NAMES)
def test_out_of_bound_parameter_is_a_one_line_error(name):
    cls = effect_class(name)
    if not cls.FITTABLE:
        pytest.skip(f"{name} has no bounded parameter")
    for key, (lo, hi) in cls.FITTABLE.items():
        bad = hi + (hi - lo) + 1.0
        if isinstance(getattr(cls.Params(), key), int):
            bad = int(np.ceil(bad))
        with pytest.raises(ConfigError) as e:
            cls({key: bad})
        msg = str(e.value)
        assert name in msg and key in msg and "\n" not in msg, msg


def _tiny_state(name, h, w, scene):
    """The state of an h x w view of the room (direct effects need only the state)."""
    from data_tools.camera import Intrinsics
    from synth.render import IdealRenderer, pinhole_ray_dirs
    from synth.sensor.state import FrameContext, SensorState, geometry_from_render
    cls = effect_class(name)
    pre = _preset_for(cls)
    intr = Intrinsics(w, h, pre.fx, pre.fy, (w - 1) / 2, (h - 1) / 2)
    renderer = IdealRenderer(scene)
    T, Tp = _pose(1 / 30), _pose(0.0)
    view = geometry_from_render(renderer.render(T, intr), renderer, T)
    e = cls(pre.effect_params.get(name))
    return e, SensorState(pre, intr, FrameContext(T, Tp, 1 / 30), renderer, pinhole_ray_dirs(intr), view, view,
                          view.depth.copy(), view.hit.copy(), {name: e}, False)


@pytest.mark.parametrize("shape", [(1, 1), (3, 640)])
@pytest.mark.parametrize("name", NAMES)
def test_tiny_and_thin_images_work(name, shape, scene):
    cls = effect_class(name)
    if cls.physical:
        pytest.skip(f"{name} is a stage of the physical pipeline (needs a matching window of pixels)")
    e, state = _tiny_state(name, *shape, scene)
    e.apply(state, e.sample(e.rng(3), state))
    assert state.depth.shape == shape and state.depth.dtype == np.float32
    assert np.isfinite(state.depth).all()
