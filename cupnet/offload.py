"""CupNet's networks on an accelerator, everything between them on the CPU.

:meth:`cupnet.model.CupNet.detect` spends its time in two kinds of work: the four networks
(locator, refiner, fine and coarse rim networks), and a great many small geometric steps
between their calls (connected components in OpenCV, ellipse fits, pose solves in float64,
strips sampled across each rim, the verification's bookkeeping). On a GPU each of the small
steps would be a kernel launch or a device-to-host copy, slower than on the CPU, so only the
networks move: their inputs go to the device and their outputs come back, and the rest of
``detect`` runs as it does on a CPU. On a GPU the rim networks take each call's strips as one
batch (:meth:`cupnet.rim.RimNet.forward`). Networks run on another device round their
float32 sums differently, so a few hard cups can come out differently (as on another CPU).
"""

from __future__ import annotations

import copy
from typing import TYPE_CHECKING

import torch
from torch import Tensor, nn

if TYPE_CHECKING:  # the command line checks devices without loading the model's libraries
    from cupnet.model import CupNet

# The CupNet attributes that hold its networks.
NETWORKS = ("locator", "refiner", "rim", "coarse_rim", "blur_rim")


def _moved(value: object, device: torch.device) -> object:
    """Tensors, and tuples of them, on ``device``; anything else as it is."""
    if isinstance(value, Tensor):
        return value.to(device)
    if isinstance(value, tuple):  # the rim networks' (logits, log sigma)
        return tuple(_moved(v, device) for v in value)
    return value


class PassThrough(nn.Module):
    """A wrapper of the child ``module`` whose attributes it lacks are the child's."""

    module: nn.Module

    def __getattr__(self, name: str) -> object:
        try:
            return super().__getattr__(name)
        except AttributeError:
            modules = self.__dict__.get("_modules", {})
            if "module" not in modules:  # while being built or copied
                raise
            return getattr(modules["module"], name)


class OnDevice(PassThrough):
    """``module`` on ``device``: called with tensors anywhere, it runs them there and gives
    its outputs back on the device of its first input.

    Attributes the wrapped module has and this wrapper does not (``RimNet.columns_seen``)
    are the wrapped module's.
    """

    def __init__(self, module: nn.Module, device: torch.device | str) -> None:
        """Moves ``module`` to ``device`` (in place, as ``nn.Module.to`` does)."""
        super().__init__()
        self.device = torch.device(device)
        self.module = module.to(self.device)

    def forward(self, *inputs: Tensor) -> object:
        # Where the module's weights are now (a later .to() moves them), else where it was put.
        weight = next(self.module.parameters(), None)
        device = weight.device if weight is not None else self.device
        home = inputs[0].device
        return _moved(self.module(*(_moved(x, device) for x in inputs)), home)


def resolve_device(name: str) -> torch.device:
    """``name`` (``cpu``, ``cuda``, ``cuda:1``, ``mps``) as a device this machine has; a
    ValueError naming the problem where it has none."""
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ValueError(f"unknown device {name!r}: use cpu, cuda, cuda:N or mps") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"device {name!r}: CUDA is not available on this machine "
                             f"(torch {torch.__version__}, built for CUDA "
                             f"{torch.version.cuda or 'none'}, sees no GPU)")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ValueError(f"device {name!r}: this machine has "
                             f"{torch.cuda.device_count()} CUDA device(s)")
    elif device.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"device {name!r}: MPS is not available on this machine")
    elif device.type not in ("cpu", "cuda", "mps"):
        raise ValueError(f"device {name!r}: use cpu, cuda, cuda:N or mps")
    return device


def networks_on(model: CupNet, device: torch.device | str) -> CupNet:
    """A copy of ``model`` whose networks run on ``device`` (:class:`OnDevice`) and whose
    :meth:`~cupnet.model.CupNet.detect` otherwise runs on the CPU; ``model`` itself is left
    as it is. For inference: the copy's state dict carries the wrappers' ``module.`` keys,
    so save ``model``, not the copy. On the CPU the copy's detections equal ``model``'s."""
    device = resolve_device(str(device))
    moved = copy.deepcopy(model)
    for name in NETWORKS:
        net = getattr(moved, name)
        if net is not None:
            setattr(moved, name, OnDevice(net, device))
    return moved
