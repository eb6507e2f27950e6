"""``python -m train.merge``: one checkpoint from networks trained in separate processes.

The hour recipe (``make train-hour``) trains the fine and coarse rim networks in one chain of
processes and the locator in another, side by side on the two cores; this puts the rim
networks into the locator chain's export:

    python -m train.merge runs/hour_locator/cupnet.safetensors \\
        --take rim=runs/hour_rim/cupnet.safetensors \\
        --take coarse_rim=runs/hour_coarse/cupnet.safetensors \\
        --out runs/hour_merged/cupnet.safetensors

and the shipped model's blur-trained fine rim network (``blur_rim``) is the fine rim network
of a run that fine-tuned it on blurrier images (``configs/blur_rim.yaml``):

    python -m train.merge cupnet/assets/cupnet_default.safetensors \\
        --take blur_rim=runs/blur_rim/cupnet.safetensors --out runs/blurred/cupnet.safetensors
"""

from __future__ import annotations

import argparse
from pathlib import Path

from torch import Tensor, nn

from cupnet.model import CupNet, load_model, save_model
from cupnet.rim import RimNet

# The settings that give each network's input its meaning (its view's size, the crop's
# framing, the strips' sampling): a network taken into a model that sets them otherwise
# would see inputs it never learnt, with weights of the same shapes.
INPUT_SETTINGS = {"locator": ("locator_size",), "refiner": ("crop_size", "crop_fill"),
                  "rim": ("rim_samples", "rim_step"),
                  "coarse_rim": ("rim_samples", "rim_step", "coarse_rim_reach"),
                  "blur_rim": ("rim_samples", "rim_step")}
# The donor's network each network is taken from where not its namesake: the blur-trained
# network is a run's fine rim network, trained on blurrier images.
DONOR_NETWORK = {"blur_rim": "rim"}


def merged(base: CupNet, parts: dict[str, CupNet]) -> CupNet:
    """``base`` with each named network (``"rim"``, ``"coarse_rim"``, ``"locator"``,
    ``"refiner"``) replaced by the same network of ``parts[name]``, in place; ``"blur_rim"``
    (given to a base without one, ``CupNetConfig.blur_rim``) is the donor's fine rim network.

    Raises ValueError naming a network that ``base`` or its donor lacks, whose weights do
    not fit (another width), or whose donor sets one of its :data:`INPUT_SETTINGS`
    otherwise. Every part is checked before any is loaded, so a merge never half-loads.
    """
    # A base with a fine rim network but no blur-trained one gets one, once all is checked.
    added = (RimNet(base.config.rim_channels) if "blur_rim" in parts and base.blur_rim is None
             and base.rim is not None else None)
    for name, donor in parts.items():
        mine = added if name == "blur_rim" and added is not None else getattr(base, name, None)
        theirs = getattr(donor, DONOR_NETWORK.get(name, name), None)
        if not (isinstance(mine, nn.Module) and isinstance(theirs, nn.Module)):
            owner = "the donor" if isinstance(mine, nn.Module) else "the base model"
            raise ValueError(f"cannot take {name!r}: {owner} has no such network")
        misfit = _first_misfit(mine.state_dict(), theirs.state_dict())
        if misfit is not None:
            raise ValueError(f"cannot take {name!r}: its weights do not fit the base "
                             f"model's ({name}.{misfit})")
        for setting in INPUT_SETTINGS.get(name, ()):
            ours, donors = getattr(base.config, setting), getattr(donor.config, setting)
            if ours != donors:
                raise ValueError(f"cannot take {name!r}: it learnt {setting} = {donors}, the "
                                 f"base model runs it at {ours}")
    if added is not None:
        base.config.blur_rim, base.blur_rim = True, added
    for name, donor in parts.items():
        getattr(base, name).load_state_dict(
            getattr(donor, DONOR_NETWORK.get(name, name)).state_dict())
    return base


def _first_misfit(mine: dict[str, Tensor], theirs: dict[str, Tensor]) -> str | None:
    """The first tensor name that one state dict lacks or holds in another shape."""
    for key in sorted(mine.keys() | theirs.keys()):
        if key not in mine or key not in theirs or mine[key].shape != theirs[key].shape:
            return key
    return None


def _part(text: str) -> tuple[str, Path]:
    name, sep, path = text.partition("=")
    if not sep or not name or not path:
        raise argparse.ArgumentTypeError(f"expected NETWORK=CHECKPOINT, got {text!r}")
    return name, Path(path)


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(prog="python -m train.merge", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("base", type=Path, help="checkpoint whose other networks are kept")
    parser.add_argument("--take", type=_part, action="append", required=True,
                        metavar="NETWORK=CHECKPOINT",
                        help="take this network's weights from that checkpoint (repeatable)")
    parser.add_argument("--out", type=Path, required=True,
                        help="merged safetensors (its JSON config is written beside it)")
    args = parser.parse_args(argv)
    try:
        parts = {name: load_model(path) for name, path in args.take}
        return save_model(merged(load_model(args.base), parts), args.out)
    except (OSError, ValueError) as error:  # a missing or unreadable checkpoint, a misfit
        parser.exit(2, f"{parser.prog}: error: {error}\n")


if __name__ == "__main__":
    print(main())
