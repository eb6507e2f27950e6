"""SynthConfig: defaults, YAML/dict loading, and errors that name the bad key."""

from __future__ import annotations

import pytest

from cupnet.io.images import MAX_SIDE
from data_synth import SynthConfig
from data_synth.config import MAX_IMAGE_SIDE


def test_defaults_follow_the_paper_protocol():
    config = SynthConfig()
    assert config.theta_deg == (0.0, 50.0) and config.phi_deg == (-90.0, 90.0)
    assert config.k_mm == (-100.0, 100.0) and config.h_mm == (100.0, 520.0)
    assert config.cup_diameter_mm == (44.0, 64.0)


def test_from_yaml_reads_lists_and_ints(tmp_path):
    path = tmp_path / "synth.yaml"
    path.write_text("image_size: [320, 240]\nsdd_mm: [1000, 1040]\np_bilateral: 1\n")
    config = SynthConfig.from_yaml(path)
    assert config.image_size == (320, 240)
    assert config.sdd_mm == (1000.0, 1040.0)
    assert config.p_bilateral == 1.0
    assert SynthConfig.from_dict(config.to_dict()) == config


@pytest.mark.parametrize(
    ("values", "named"),
    [
        ({"thetta_deg": [0, 10]}, "thetta_deg"),
        ({"p_head": 1.5}, "p_head"),
        ({"sdd_mm": [1200, 1000]}, "sdd_mm"),
        ({"theta_deg": [0, 120]}, "theta_deg"),
        # CONVENTIONS: phi in (-90, 90], radiographic inclination.
        ({"phi_deg": [-120, 0]}, "phi_deg"),
        ({"phi_deg": [0, 120]}, "phi_deg"),
        ({"mu_shell": "titanium"}, "mu_shell"),
        ({"image_size": [256]}, "image_size"),
        ({"image_size": [100_000, 512]}, r"image_size must be \(width, height\), integers "
                                         r"from 16 to 4096"),
        ({"supersample": 0}, "supersample"),
        ({"h_mm": [100, 1000]}, "h_mm"),
        ({"anatomy_ct": "/no/such/ct.nii.gz"}, "anatomy_ct"),
    ],
)
def test_bad_values_name_the_key(values, named):
    with pytest.raises(ValueError, match=named):
        SynthConfig.from_dict(values)



def test_a_number_yaml_reads_as_text_is_named_with_the_way_to_write_it(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("photons: [1.0e9, 2.0e9]\n")  # YAML 1.1: text, for want of a sign
    with pytest.raises(ValueError, match=r"got '1.0e9' \(YAML reads .* write 1.0e\+9\)"):
        SynthConfig.from_yaml(path)
    path.write_text("photons: [1.0e+9, 2.0e+9]\n")
    assert SynthConfig.from_yaml(path).photons == (1e9, 2e9)
    path.write_text("photons: [nan, 2.0e+9]\n")  # text too, but no exponent to mend
    with pytest.raises(ValueError, match=r"got 'nan'$"):
        SynthConfig.from_yaml(path)

def test_yaml_that_is_not_a_mapping(tmp_path):
    path = tmp_path / "synth.yaml"
    path.write_text("- 1\n- 2\n")
    with pytest.raises(ValueError, match="mapping"):
        SynthConfig.from_yaml(path)


def test_a_field_set_on_a_made_config_is_checked_and_a_misspelt_one_refused():
    """A script's ``config.p_bilateral = 1.5`` is refused as the constructor refuses it, the
    config left as it was; bounds moved past each other go together."""
    config = SynthConfig()
    with pytest.raises(ValueError, match="p_bilateral must be a probability"):
        config.p_bilateral = 1.5
    with pytest.raises(ValueError, match=r"h_mm \(100.0, 520.0\) plus the largest cup's"):
        config.sdd_mm = (300.0, 400.0)  # the default h_mm puts cups behind the source
    with pytest.raises(AttributeError, match="unknown SynthConfig field 'p_bilaterall'"):
        config.p_bilaterall = 0.5
    assert config == SynthConfig()
    config.update(sdd_mm=(300.0, 400.0), h_mm=(50.0, 200.0))
    assert (config.sdd_mm, config.h_mm) == ((300.0, 400.0), (50.0, 200.0))



@pytest.mark.parametrize("fields, message", [
    # The rim centre below 0.9 SDD, a rim point at the source: the run had stopped midway.
    (dict(sdd_mm=(300.0, 300.0), h_mm=(268.0, 269.0), cup_diameter_mm=(64.0, 64.0),
          theta_deg=(0.0, 2.0)), r"plus the largest cup's radius \(32 mm\)"),
    # A wall past the radius: a hollow no cup has.
    (dict(cup_diameter_mm=(12.0, 12.0), shell_wall_mm=(8.0, 8.0)),
     r"shell_wall_mm \(8.0, 8.0\) must stay below the smallest cup's radius \(6 mm"),
])
def test_a_cup_that_cannot_be_drawn_is_refused_before_the_run(fields, message):
    with pytest.raises(ValueError, match=message):
        SynthConfig(**fields)

def test_the_largest_side_drawn_is_the_largest_predict_reads():
    assert MAX_IMAGE_SIDE == MAX_SIDE
