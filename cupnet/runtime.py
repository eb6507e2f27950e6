"""CupNet's networks run by ONNX Runtime on the CPU, for inference.

On a CPU :meth:`cupnet.model.CupNet.detect` spends most of its time in its networks, called
on small inputs: 128 x 128 crops and 64 x 128 rim strips, one strip at a time. PyTorch
runs each convolution through oneDNN in its own memory layout, reordering every layer's
input and output; ONNX Runtime keeps a blocked layout across the layers and fuses each
convolution with its ReLU. Measured on the 2-core machine (1 thread; shipped weights,
BatchNorm folded): a rim strip 2.7-3.0 ms against 4.5, a U-Net on one crop 4.7-4.9 ms
against 11.1-11.5 (on 8 crops at once 4.7 against 5.5 ms a crop). The outputs equal
PyTorch's to float rounding (about 1e-5 of the logits), so a few hard cups can come out
differently, as on another CPU.

Each network is exported once (``torch.onnx.export``, a few seconds a network) and cached
on disk under a key of its weights, class source and library versions
(:func:`cache_dir`); later runs load the cached graph. Inference only: the wrapped
networks have no gradients.
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import importlib.util
import inspect
import os
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor, nn

from cupnet.environment import library_versions
from cupnet.errors import error_reason
from cupnet.offload import NETWORKS, PassThrough
from cupnet.rim import RimNet, strips_one_by_one

if TYPE_CHECKING:
    import onnxruntime

    from cupnet.model import CupNet

# What can run the networks on a CPU (cupnet predict --runtime).
RUNTIMES = ("torch", "onnx")
# A rim network's example strips for the export: every dimension but the channel is
# dynamic (strips of any length and count). A U-Net's graph has its input's side
# fixed (a dynamic one takes minutes to export) and its batch dynamic.
_STRIPS_EXAMPLE = (2, 1, 64, 128)
# Bumped when the export itself changes (its options, the wrapper below), to drop old graphs.
_EXPORT_VERSION = 1


class _StripsAtOnce(nn.Module):
    """A :class:`RimNet`'s whole-batch forward as the module to export."""

    def __init__(self, rim: RimNet) -> None:
        super().__init__()
        self.rim = rim

    def forward(self, strips: Tensor) -> tuple[Tensor, Tensor]:
        return self.rim.forward_batch(strips)


def cache_dir() -> Path:
    """Where exported graphs are kept: ``$CUPNET_CACHE_DIR/onnx``, else
    ``$XDG_CACHE_HOME/cupnet/onnx``, else ``~/.cache/cupnet/onnx``."""
    if os.environ.get("CUPNET_CACHE_DIR"):
        return Path(os.environ["CUPNET_CACHE_DIR"]) / "onnx"
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "cupnet" / "onnx"


def export_key(module: nn.Module) -> str:
    """A digest of what the exported graph of ``module`` depends on: its weights and
    buffers, the source files of the modules defining its layers' classes and their bases
    (constants included; PyTorch's own are covered by its version), and the versions of
    the libraries that build and run the graph."""
    digest = hashlib.sha256(str(_EXPORT_VERSION).encode())
    libraries = ("torch", "onnxruntime", "onnxscript", "segmentation-models-pytorch", "timm",
                 "cupnet")
    versions = library_versions(libraries)
    for library in libraries:
        digest.update(f"{library} {versions.get(library, 'absent')}".encode())
    sources = {inspect.getmodule(base) for layer in module.modules()
               for base in type(layer).__mro__}
    files = sorted({Path(source.__file__) for source in sources
                    if source is not None and getattr(source, "__file__", None)
                    and source.__name__.split(".")[0] not in ("torch", "builtins")})
    for file in files:
        digest.update(file.name.encode())
        digest.update(file.read_bytes())
    for name, value in module.state_dict().items():
        digest.update(name.encode())
        digest.update(value.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()[:32]


def exported_graph(module: nn.Module, side: int | None = None,
                   on_export: Callable[[Path], None] | None = None,
                   fresh: bool = False) -> bytes:
    """The ONNX graph of ``module`` (a :class:`RimNet`, or a U-Net on ``side`` x ``side``
    inputs), from the cache or (``fresh``: in any case) exported now and cached (an
    unwritable cache is skipped with a warning); ``on_export`` is called with the cache
    path before an export (seconds)."""
    strips = isinstance(module, RimNet)
    if not strips and side is None:
        raise ValueError("exported_graph: a U-Net's graph needs its input side")
    kind = "rim" if strips else f"unet{side}"
    path = cache_dir() / f"{kind}-{export_key(module)}.onnx"
    if path.is_file() and not fresh:
        return path.read_bytes()
    if on_export is not None:
        on_export(path)
    target = _StripsAtOnce(module) if strips else module
    example = torch.zeros(_STRIPS_EXAMPLE if strips else (2, 1, side, side))
    dynamic = {d: torch.export.Dim.DYNAMIC for d in ((0, 2, 3) if strips else (0,))}
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the exporter's notes on its own internals
        program = torch.onnx.export(target.eval(), (example,), dynamo=True,
                                    dynamic_shapes=(dynamic,), verbose=False)
    graph = program.model_proto.SerializeToString()
    temporary = path.with_suffix(f".{os.getpid()}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        temporary.write_bytes(graph)
        temporary.replace(path)  # atomic: a concurrent run reads a whole graph or none
    except OSError as error:
        # A cache folder that cannot be made (a file on its path) fails this too, and an
        # error here had passed over the warning and stopped the run.
        with contextlib.suppress(OSError):
            temporary.unlink(missing_ok=True)
        warnings.warn(f"cannot cache the exported network in {path.parent} ({error}); it "
                      "is exported again next time (set CUPNET_CACHE_DIR)", stacklevel=2)
    return graph


def _session(graph: bytes, threads: int) -> onnxruntime.InferenceSession:
    import onnxruntime

    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    # Idle intra-op threads sleep instead of spinning: the cores are shared with the
    # geometry between network calls and with predict's other batch.
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    options.log_severity_level = 3  # errors only
    return onnxruntime.InferenceSession(graph, options, providers=["CPUExecutionProvider"])


class InOnnxRuntime(PassThrough):
    """``module`` (a U-Net or a :class:`RimNet`) run by ONNX Runtime on the CPU.

    Called with CPU float tensors, it gives what ``module`` gives in eval mode (to float
    rounding). A rim network takes CPU strips one at a time, as :meth:`RimNet.forward`
    does. Where ONNX Runtime fails on a call, that call and every later one run in PyTorch
    (with a warning, and :attr:`failure` says why). Attributes the wrapper lacks are the
    module's (``RimNet.columns_seen``). It holds an ONNX Runtime session, which cannot be
    copied or pickled: copy, fold or save the PyTorch model, then wrap it.
    """

    def __init__(self, module: nn.Module, side: int | None = None, threads: int = 1,
                 on_export: Callable[[Path], None] | None = None) -> None:
        """Exports ``module`` (a U-Net for ``side`` x ``side`` inputs, or a rim network) or
        loads its cached graph (:func:`exported_graph`, which calls ``on_export``), and opens
        a session of ``threads`` intra-op threads."""
        super().__init__()
        self.module = module.eval()
        self.strips = isinstance(module, RimNet)
        self.side = side
        try:
            self.session = _session(exported_graph(module, side, on_export), threads)
        except Exception:  # noqa: BLE001 - a cached graph that does not load: export anew
            self.session = _session(exported_graph(module, side, on_export, fresh=True),
                                    threads)
        self.input_name = self.session.get_inputs()[0].name
        self.failure: str | None = None  # why the session failed once, if it did

    def forward(self, inputs: Tensor) -> Tensor | tuple[Tensor, Tensor]:
        """A U-Net's crops or views ``(K, 1, s, s)`` -> logits ``(K, 1, s, s)``; a rim
        network's strips ``(K, 1, S, n)`` -> offset logits ``(K, S, n)`` and ``log sigma``
        ``(K, n)`` px; CPU tensors in the inputs' dtype."""
        if inputs.requires_grad:
            raise RuntimeError("a network run by ONNX Runtime has no gradients: use the "
                               "PyTorch model (cupnet.model.load_model) to train or "
                               "backpropagate")
        if inputs.device.type != "cpu":
            raise ValueError(f"ONNX Runtime runs on the CPU; got inputs on {inputs.device}")
        if inputs.shape[0] == 0 or self.failure is not None:
            return self.module(inputs)
        if not self.strips and inputs.shape[-2:] != (self.side,) * 2:
            # a side the graph was not made for (the config changed since it was made)
            warnings.warn(f"ONNX Runtime's graph takes {self.side} px inputs; PyTorch runs "
                          f"these {tuple(inputs.shape[-2:])}", stacklevel=2)
            return self.module(inputs)
        try:
            if self.strips:
                return strips_one_by_one(self.run, inputs, self)
            return self.run(inputs)
        except Exception as error:  # noqa: BLE001 - whatever ONNX Runtime raises
            # PyTorch gives the same outputs to float rounding: the run goes on there.
            self.failure = error_reason(error)
            warnings.warn(f"ONNX Runtime failed ({self.failure}); this network runs in "
                          "PyTorch from now on", stacklevel=2)
            return self.module(inputs)

    def run(self, inputs: Tensor) -> Any:
        """The graph on the whole CPU batch ``inputs``: its outputs as tensors in the inputs'
        dtype (one, or a tuple)."""
        feed = inputs.detach().to(torch.float32).contiguous().numpy()
        outputs = tuple(torch.from_numpy(x).to(inputs.dtype) for x in
                        self.session.run(None, {self.input_name: feed}))
        return outputs if len(outputs) > 1 else outputs[0]


def onnx_runtime_available() -> str | None:
    """None where ONNX Runtime imports and the exporter's library is installed (found, not
    imported: it takes about 2 s, and only an export needs it), else why not."""
    try:
        import onnxruntime  # noqa: F401
    except ImportError as error:
        return f"ONNX Runtime is not installed ({error})"
    if importlib.util.find_spec("onnxscript") is None:
        return "onnxscript, which torch.onnx.export needs, is not installed"
    return None


def networks_in_onnx_runtime(model: CupNet, threads: int | None = None,
                             on_export: Callable[[Path], None] | None = None) -> CupNet:
    """A copy of ``model`` whose networks ONNX Runtime runs (:class:`InOnnxRuntime`, the
    U-Nets on ``threads`` intra-op threads, None: ``torch.get_num_threads()``), the rest of
    :meth:`~cupnet.model.CupNet.detect` unchanged; ``model`` itself is left as it is.
    ``on_export``: called with the cache path before each network that must be exported.

    For inference on a CPU. Fold the BatchNorms first (:func:`cupnet.fold.fold_batchnorm`),
    as ``cupnet predict`` does: the graph then has one operator fewer per layer. A
    RuntimeError names the problem where ONNX Runtime is missing.
    """
    missing = onnx_runtime_available()
    if missing is not None:
        raise RuntimeError(missing)
    threads = threads or torch.get_num_threads()
    wrapped = copy.deepcopy(model)
    sides = {"locator": model.config.locator_size, "refiner": model.config.crop_size}
    for name in NETWORKS:
        net = getattr(wrapped, name)
        if net is not None:
            # The strips run one per core already (cupnet.parallel): one thread each.
            setattr(wrapped, name, InOnnxRuntime(net, sides.get(name), 1 if name not in sides
                                                 else threads, on_export))
    return wrapped
