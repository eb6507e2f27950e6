"""cupnet.config: a checkpoint's JSON read strictly, and what each speed preset promises."""

from __future__ import annotations

import json
from dataclasses import asdict

import pytest

from cupnet.config import CupNetConfig, apply_speed_preset
from cupnet.model import DEFAULT_CHECKPOINT, config_path

# What --fast and --fastest promise (cupnet predict --help, README's table of presets),
# written out here rather than read from SPEED_PRESETS, so a setting dropped from a preset
# fails: --fast skips the verification (and so the search) of doubtful cups; --fastest also
# the dome-outline refinement, the thin-rim hypotheses and every later look.
PROMISED = {
    "fast": {"verify_gate": None},
    "fastest": {"verify_gate": None, "outline_passes": 0, "thin_rim_gate": None,
                "second_look": False, "third_look_gamma": None, "high_gamma_look": None,
                "fourth_look_turned": False, "rod_look": False},
}


def shipped_config() -> CupNetConfig:
    """The shipped model's config (its JSON alone: the weights are not needed here)."""
    return CupNetConfig.from_dict(json.loads(config_path(DEFAULT_CHECKPOINT).read_text()))


@pytest.mark.parametrize("preset", sorted(PROMISED))
def test_speed_presets_turn_off_what_they_promise_and_nothing_else(preset: str) -> None:
    """Each setting a preset promises to turn off is on in the shipped model (else the
    check would pass whatever the preset did) and off after it; every other setting is the
    shipped one."""
    shipped = asdict(shipped_config())
    promised = PROMISED[preset]
    assert all(shipped[key] != value for key, value in promised.items())
    changed = asdict(apply_speed_preset(shipped_config(), preset))
    assert {key: changed[key] for key in promised} == promised
    assert ({key: value for key, value in changed.items() if key not in promised}
            == {key: value for key, value in shipped.items() if key not in promised})


@pytest.mark.parametrize("values", [{"rim_channels": True}, {"coarse_rim_channels": False},
                                    {"crop_fill": True}, {"verify_gate": False},
                                    {"search_anteversions": [3.0, True]}])
def test_a_bool_is_no_number(values: dict) -> None:
    """JSON's true is not 1 to an int or float field (Python's bool is an int): a
    checkpoint's ``"rim_channels": true`` is a mistake, not a network of width 1."""
    key = next(iter(values))
    with pytest.raises(ValueError, match=f"CupNet config {key}: expected .*, got (True|False)"):
        CupNetConfig.from_dict(values)


def test_an_unknown_key_is_refused_by_name() -> None:
    """A misspelt key in a checkpoint's JSON had silently left its field at the default."""
    with pytest.raises(ValueError, match=r"^unknown CupNet config keys: \['verify_gat'\]$"):
        CupNetConfig.from_dict({"verify_gat": 1.0, "rim_channels": 8})


def test_a_side_both_enlarged_and_reduced_is_refused() -> None:
    # A bar to reduce under the bar to enlarge would leave sides between them both.
    with pytest.raises(ValueError, match=r"reduce_above \(400\) must be at least enlarge_below"):
        CupNetConfig(enlarge_below=496, reduce_above=400)
    assert CupNetConfig(enlarge_below=496, reduce_above=496).reduce_above == 496


def test_a_field_set_on_a_made_config_is_checked_as_the_constructor_checks_it() -> None:
    """Presets, ``cupnet predict``'s options and a user's own settings set fields on a made
    config; each is refused as the constructor refuses it, the config left as it was."""
    config = CupNetConfig(enlarge_below=496, reduce_above=1024)
    refusals = {"reduce_above": (400, r"reduce_above \(400\) must be at least enlarge_below"),
                "enlarge_below": (1500, r"reduce_above \(1024\) must be at least "
                                        r"enlarge_below \(1500\)"),
                "metal": ("shiny", "unknown metal display 'shiny'"),
                "blurred": (True, "blurred needs blur_rim"),
                "search_screen": (2, r"search_screen \(2\) must be at least search_keep")}
    for name, (value, message) in refusals.items():
        with pytest.raises(ValueError, match=message):
            setattr(config, name, value)
    with pytest.raises(TypeError):  # a text bar cannot be compared with the other bar
        config.reduce_above = "2000"
    assert config == CupNetConfig(enlarge_below=496, reduce_above=1024)
    # Bars moved past each other together are one consistent change.
    assert config.update(enlarge_below=1500, reduce_above=2000) is config
    assert (config.enlarge_below, config.reduce_above) == (1500, 2000)
    with pytest.raises(ValueError, match=r"reduce_above \(50\) must be at least"):
        config.update(enlarge_below=100, reduce_above=50)
    assert (config.enlarge_below, config.reduce_above) == (1500, 2000)


def test_a_misspelt_field_is_refused_not_added() -> None:
    """Python would add the misspelt attribute and leave the field the model reads as it was."""
    config = CupNetConfig()
    with pytest.raises(AttributeError, match="unknown CupNetConfig field 'blured'"):
        config.blured = True
    with pytest.raises(AttributeError, match=r"unknown CupNetConfig fields: \['verify_gat'\]"):
        config.update(verify_gat=1.0, rim_channels=8)
    assert config == CupNetConfig() and "blured" not in vars(config)
