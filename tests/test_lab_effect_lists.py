"""Pipeline words (``physical``, ``direct``) inside comma effect lists (issue 43 item 5)."""
import pytest

from data_tools.errors import ConfigError
from synth.lab.runs import effect_names_option, parse_effects
from synth.sensor.config import SensorConfig, expand_pipelines
from synth.sensor.presets import get_preset


def test_pipeline_word_in_list_expands_to_pipeline_plus_extra():
    pre = get_preset("kinect_v1")
    names = parse_effects("physical,disparity_distortion")
    assert names == ["physical", "disparity_distortion"]
    cfg = SensorConfig.build(pre, names)
    assert cfg.names() == [*pre.physical_effects, "disparity_distortion"]
    assert SensorConfig.build(pre, "physical").names() == list(pre.physical_effects)
    # the comma string goes the same way, and the word is case-blind
    assert SensorConfig.build(pre, "Direct,flying_pixels").names() == [*pre.direct_effects, "flying_pixels"]


def test_effect_already_in_pipeline_is_not_doubled_but_hand_duplicates_fail():
    pre = get_preset("kinect_v1")
    assert "range_limits" in pre.physical_effects
    assert expand_pipelines(["physical", "range_limits"], pre) == list(pre.physical_effects)
    with pytest.raises(ConfigError, match="twice"):
        parse_effects("axial_noise,axial_noise")
    with pytest.raises(ConfigError, match="unknown sensor effect"):
        parse_effects("physical,no_such_effect")


def test_candidate_lists_refuse_pipeline_words():
    with pytest.raises(ConfigError, match="pipeline word"):
        effect_names_option("physical,axial_noise", "--candidates")
    assert effect_names_option("axial_noise", "--candidates") == ["axial_noise"]
