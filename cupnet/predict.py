"""``cupnet predict IMAGES --out DIR``: cup poses of every image, as CSV, JSON and overlays.

Per image (a DICOM multi-frame run gives one per frame): read it, resolve its geometry
(``--meta`` row > command-line flags > DICOM tags > the landmark file's own values >
``--assume-defaults``; the principal point defaults to the image centre), detect the cups
with the network (or take manual landmarks with ``--landmarks``), solve each pose, and write
one ``results.csv`` row per cup (a status row for images without one). ``results.json`` adds
the geometry used, the assumptions made, the model and the software versions and CPU.

Robustness: a file that cannot be read gets its error row and the run goes on; outputs are
rewritten atomically every few seconds, so an interrupted run (Ctrl-C included) leaves a
valid ``results.csv`` of what finished and ``--resume`` goes on from it; nothing is
overwritten without ``--overwrite``. Images are streamed and processed in batches, so memory
does not grow with the number of images.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import math
import os
import platform
import re
import signal
import sys
import tempfile
import threading
import time
from collections import Counter, deque
from collections.abc import Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING

import numpy as np
import torch
from tqdm import tqdm

from cupnet import __version__
from cupnet.environment import library_versions, processor
from cupnet.errors import error_reason, named_error
from cupnet.geometry import Geometry
from cupnet.io.images import (
    PATIENT_SPACING_SOURCE,
    TURNS,
    Frame,
    ImageSource,
    display_name,
    find_images,
    iter_frames,
    turned_clockwise,
)
from cupnet.io.meta import (
    PRINCIPAL_KEYS,
    GeometryInputs,
    ImageTable,
    ResolvedGeometry,
    add_geometry_arguments,
    assumptions_once,
    frame_file,
    implausible_once,
    row_for_image,
    unmatched_keys,
)
from cupnet.io.results import (
    atomic_write,
    cup_row,
    read_results_csv,
    status_row,
    write_results_csv,
)
from cupnet.io.review import write_review_page
from cupnet.offload import resolve_device
from cupnet.overlay import CupDrawing, draw_overlay, pose_lines, write_png
from cupnet.polarity import METAL_DISPLAYS
from cupnet.runtime import RUNTIMES, onnx_runtime_available

if TYPE_CHECKING:  # the model's libraries load only when a model is
    from cupnet.model import CupNet

# Outputs are rewritten at most every FLUSH_SECONDS, and at least FLUSH_RATIO times as long as
# the last rewrite took, so rewriting stays a small share of the run on huge folders.
FLUSH_SECONDS = 2.0
FLUSH_RATIO = 20.0
# Batches whose detection runs at once, each on --threads PyTorch threads: on 2 cores the
# network of one batch runs while the other core reads images and draws overlays.
BATCHES_IN_FLIGHT = 2


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images", nargs="+",
                        help="folders, image / DICOM files or globs (several may be given)")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--recursive", action="store_true",
                        help="include subfolders (but not earlier runs' output folders, "
                             "those holding results.json and results.csv)")
    add_geometry_arguments(parser)
    parser.add_argument("--checkpoint", type=Path,
                        help="model weights (.safetensors or a weights-only torch file); "
                             "default: the shipped model")
    speed = parser.add_mutually_exclusive_group()
    speed.add_argument("--fast", dest="preset", action="store_const", const="fast",
                       help="skip the model's verification and search of doubtful cups "
                            "(verify_gate): 2-3.5x faster end to end (512 to 1024 px), "
                            "less accurate (docs/training.md, items 12 and 16)")
    speed.add_argument("--fastest", dest="preset", action="store_const", const="fastest",
                       help="also skip the dome-outline refinement (so no doubt, and a "
                            "check flag only for a pose through the detector) and the "
                            "thin-rim hypotheses: segmentation, "
                            "rim stages and solver alone, 7-18x faster than the default, "
                            "several times less accurate (docs/benchmarks.md)")
    parser.add_argument("--check-doubt", type=float, metavar="DOUBT",
                        help="flag a cup check=1 where the model's doubt of its pose reaches "
                             "this (default: the model's check_doubt, 1.4 for the shipped "
                             "one; lower flags more cups, more of them right). The flag "
                             "alone: which cups the model looks at again stays its own "
                             "(look_again_doubt, 1.8 for the shipped one)")
    parser.add_argument("--metal", choices=METAL_DISPLAYS,
                        help="how the images show metal (default: the model's setting, "
                             "auto for the shipped one: judged per image from the cups the "
                             "locator finds, and turned over for the later networks where "
                             "bright): dark (the usual fluoroscopy display, used as given) "
                             "or bright (radiograph-style, metal white: every image turned "
                             "over); docs/training.md, item 20")
    parser.add_argument("--blurred", action="store_true",
                        help="the images are blurrier than a sharp DRR (a rim's edge spread "
                             "over 2 px or more): every rim stage runs the model's rim network "
                             "trained on blurrier images (blur_rim). On images 2 px blurrier "
                             "than the training's it takes the anteversion error at 512 px "
                             "from 4.0 to 1.2 deg; on sharp ones it costs about 0.1 deg "
                             "(docs/training.md, items 75 and 76)")
    parser.add_argument("--denoise-above", type=float, metavar="SIGMA",
                        help="take an image whose noise estimate (the noise column, display "
                             "units [0, 1]) exceeds this through non-local means before the "
                             "networks (default: the model's denoise_above, 0.008 for the "
                             "shipped one; inf: never); docs/training.md, item 55")
    parser.add_argument("--enlarge-below", type=int, metavar="PX",
                        help="enlarge an image (or its round field's square) whose shorter "
                             "side is under this many pixels to the model's enlarge_to (512 "
                             "px for the shipped one) before the networks (default: the "
                             "model's enlarge_below, 496 for the shipped one; 0: never); the "
                             "enlarged column says by how much; docs/training.md, item 56")
    parser.add_argument("--reduce-above", type=int, metavar="PX",
                        help="reduce an image (or its round field's square) whose shorter side "
                             "is over this many pixels to the model's reduce_to (1024 px for "
                             "the shipped one) before the networks, by area averaging "
                             "(default: the model's reduce_above, 1024 for the shipped one; 0: "
                             "never); the reduced column says by how much; docs/training.md, "
                             "item 71")
    parser.add_argument("--min-score", type=float, metavar="PROBABILITY",
                        help="drop a cup whose locator blob's mean probability is below this "
                             "(default: the model's min_score, 0.8 for the shipped one; 0 "
                             "keeps every blob; docs/training.md, item 24)")
    parser.add_argument("--keep-outside-field", action="store_true",
                        help="keep the locator's cups centred outside an image "
                             "intensifier's round field where the image shows one (the "
                             "shipped model drops them, as the surround's dark ends of an "
                             "oblong frame look like cups to it; docs/training.md, item 23), "
                             "and look at a narrow field's whole frame, not its square "
                             "(item 41)")
    parser.add_argument("--rotate", type=int, choices=TURNS, default=0, metavar="DEGREES",
                        help="turn every image clockwise by 90, 180 or 270 degrees before the "
                             "model, to the upright AP display it learnt (the patient's head "
                             "at the top): for files stored turned. Poses, ellipses and "
                             "overlays then refer to the turned image; a principal point "
                             "given is in the file's own pixels and turns with it")
    parser.add_argument("--landmarks", type=Path,
                        help="solve from manual landmarks in this file instead of the network")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace existing results (and remove the overlays and masks "
                             "the previous run's results.json lists)")
    parser.add_argument("--resume", action="store_true",
                        help="keep existing results and process only the images not in "
                             "them (with the same settings: other row-shaping options are "
                             "refused, naming each)")
    parser.add_argument("--save-masks", action="store_true", help="write cup masks as PNG")
    parser.add_argument("--no-overlays", action="store_true", help="skip the overlay PNGs")
    parser.add_argument("--device", default="cpu",
                        help="where the networks run: cpu (default), cuda, cuda:N or mps; "
                             "the geometry between their calls stays on the CPU "
                             "(cupnet.offload)")
    parser.add_argument("--runtime", choices=("auto", *RUNTIMES), default="auto",
                        help="what runs the networks: onnx (ONNX Runtime, on the CPU: about "
                             "5-30 %% faster an image than torch, the same poses to float "
                             "rounding but for a few hard cups; each network is exported "
                             "once, about 30 s in all, and cached; cupnet.runtime), torch, or "
                             "auto (default: onnx on the CPU where it loads, else torch)")
    parser.add_argument("--batch-size", type=int, default=8, help="images per network batch")
    parser.add_argument("--threads", type=int, default=1,
                        help="PyTorch threads per network batch (default 1: two batches, "
                             "reading and writing run side by side, and a busy machine does not "
                             "stall it)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


# -- geometry ---------------------------------------------------------------------------------
def turned_frame(frame: Frame, geometry: ResolvedGeometry, degrees: int) -> None:
    """``frame``'s image turned clockwise by ``degrees`` and ``geometry``'s principal point
    (resolved in the file's pixels) with it, in place."""
    if degrees == 0:
        return
    u_key, v_key = PRINCIPAL_KEYS
    frame.image, geometry.values[u_key], geometry.values[v_key] = turned_clockwise(
        frame.image, geometry.values[u_key], geometry.values[v_key], degrees)
    for key in PRINCIPAL_KEYS:
        geometry.sources[key] += f", turned {degrees} deg clockwise with the image"


def batch_geometry(geometries: list[ResolvedGeometry]) -> tuple[Geometry, torch.Tensor]:
    """``Geometry`` with ``(B,)`` float64 fields and ``(B,)`` cup diameters (mm)."""
    def column(key: str) -> torch.Tensor:
        return torch.tensor([g.values[key] for g in geometries], dtype=torch.float64)

    return (Geometry(column("sdd_mm"), column("pixel_spacing_mm"), column("principal_u_px"),
                     column("principal_v_px")), column("cup_diameter_mm"))


# -- detectors --------------------------------------------------------------------------------
def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _in_onnx_runtime(model: CupNet, strict: bool) -> tuple[CupNet, str]:
    """``model`` with its networks run by ONNX Runtime, and ``"onnx"``; where that fails,
    the error if ``strict``, else ``model`` as it is and ``"torch"``, with a note."""
    from cupnet.runtime import networks_in_onnx_runtime

    def announce(path: Path) -> None:
        print(f"cupnet predict: exporting a network for ONNX Runtime (once, a few seconds; "
              f"cached as {path})", file=sys.stderr)

    try:
        return networks_in_onnx_runtime(model, on_export=announce), "onnx"
    except Exception as exc:  # noqa: BLE001 - any failure to export or load falls back alike
        if strict:
            raise
        print(f"cupnet predict: ONNX Runtime cannot run the networks ({error_reason(exc)}); "
              "they run in PyTorch", file=sys.stderr)
        return model, "torch"


class NetworkDetector:
    """CupNet on a batch of images (weights loaded without running code from the file)."""

    def __init__(self, checkpoint: Path | None, save_masks: bool, preset: str | None = None,
                 settings: dict[str, object] | None = None, device: str = "cpu",
                 runtime: str = "auto") -> None:
        """``settings``: :class:`cupnet.config.CupNetConfig` fields set over the checkpoint's
        (and the preset's), as the command line gives them; ``device``: where the networks
        run (:func:`cupnet.offload.networks_on`); ``runtime`` (on the CPU): ``"onnx"`` runs
        them in ONNX Runtime (:func:`cupnet.runtime.networks_in_onnx_runtime`, the U-Nets on
        ``torch.get_num_threads()`` threads), ``"torch"`` in PyTorch, ``"auto"`` in ONNX
        Runtime where it loads, else in PyTorch. ``info["runtime"]`` says which ran."""
        from cupnet.config import apply_speed_preset
        from cupnet.fold import fold_batchnorm
        from cupnet.model import DEFAULT_CHECKPOINT, load_model
        from cupnet.offload import networks_on  # loads the model's libraries

        self.model = fold_batchnorm(load_model(checkpoint))
        if torch.device(device).type != "cpu":
            self.model, runtime = networks_on(self.model, device), "torch"
        elif runtime != "torch":
            self.model, runtime = _in_onnx_runtime(self.model, strict=runtime == "onnx")
        apply_speed_preset(self.model.config, preset)
        config, settings = self.model.config, settings or {}
        if "check_doubt" in settings:
            # A flag set for the eye alone: the later looks keep the checkpoint's threshold.
            config.look_again_doubt = self.model.look_again_doubt
        if settings.get("blurred") and not config.blur_rim:
            raise ValueError("--blurred needs a model with a rim network trained on blurrier "
                             "images (blur_rim); this checkpoint has none")
        config.update(**settings)  # checked together: --enlarge-below may pass reduce_above
        self.save_masks = save_masks
        path = Path(checkpoint) if checkpoint is not None else DEFAULT_CHECKPOINT
        self.info = {"checkpoint": str(path), "sha256": _sha256(path),
                     "speed_preset": preset, "device": device, "runtime": runtime,
                     "config": dict(vars(self.model.config))}

    def file_values(self, frame: Frame) -> dict[str, float]:
        return {}

    def needs_geometry(self, frame: Frame) -> bool:
        """Whether the image's result needs its geometry: every image may hold a cup."""
        return True

    def cup_numbers(self, frame: Frame, count: int) -> list[int]:
        """results.csv's ``cup`` of each of an image's ``count`` cups: left to right."""
        return list(range(count))

    def input_error(self, frame: Frame) -> str | None:
        """An image too small for the model: its poses would be far off, not just worse."""
        from cupnet.model import MIN_IMAGE_SIDE

        height, width = frame.image.shape[-2:]
        if min(height, width) < MIN_IMAGE_SIDE:
            return (f"error: image too small for the model: {width} x {height} px (at least "
                    f"{MIN_IMAGE_SIDE} px a side)")
        return None

    def __call__(self, frames: list[Frame], geometries: list[ResolvedGeometry]) -> list[list]:
        """Cups of each image, ordered left to right on the image."""
        geometry, diameter = batch_geometry(geometries)
        found = self.model.detect([f.image for f in frames], geometry, diameter,
                                  return_masks=self.save_masks)
        return [sorted(cups, key=lambda c: float(c.ellipse[0]) if np.isfinite(c.ellipse[0])
                       else math.inf) for cups in found]


class LandmarkDetector:
    """Manual landmarks (either CONVENTIONS format) solved with the pose solver, no network.

    An image without landmarks in the file has no cup. The paper's format carries an SDD and
    a radius per row: they count as the file's values, after the user's and the DICOM tags.
    """

    def __init__(self, path: Path) -> None:
        from cupnet.io.landmarks import read_landmarks

        self.sets = ImageTable(read_landmarks(path))
        self.info = {"landmarks": str(path), "sha256": _sha256(path)}

    def cups_of(self, frame: Frame) -> list:
        """The image's :class:`cupnet.io.landmarks.LandmarkSet` s
        (:func:`cupnet.io.meta.row_for_image`, its file's path helping)."""
        return row_for_image(self.sets, frame.name, absolute_path(frame.source)) or []

    def input_error(self, frame: Frame) -> str | None:
        """The landmark file's error for an image all of whose rows are unreadable."""
        cups = self.cups_of(frame)
        if cups and all(c.error is not None for c in cups):
            return f"error: {cups[0].error}"
        return None

    def file_values(self, frame: Frame) -> dict[str, float]:
        cups = [c for c in self.cups_of(frame) if c.error is None]
        return cups[0].geometry_values() if cups else {}

    def needs_geometry(self, frame: Frame) -> bool:
        """Whether the image's result needs its geometry: not where the file holds no
        landmarks for it (no_cup, where a geometry missing had made it an error row)."""
        return bool(self.cups_of(frame))

    def cup_numbers(self, frame: Frame, count: int) -> list[int]:
        """results.csv's ``cup`` of each of an image's cups: the file's own labels, as
        ``cupnet solve`` writes them (numbered by position, a file labelling its cups 1 and
        2 had its cup 2's pose under predict's cup 1)."""
        return [landmarks.cup for landmarks in self.cups_of(frame)][:count]

    def __call__(self, frames: list[Frame], geometries: list[ResolvedGeometry]) -> list[list]:
        from cupnet.detection import CupDetection
        from cupnet.solve_cli import solve_cup

        out: list[list] = []
        for frame, resolved in zip(frames, geometries, strict=True):
            cups = []
            for landmarks in self.cups_of(frame):
                if landmarks.error is not None:
                    nan = np.full(5, math.nan)
                    cups.append(CupDetection(nan, None, False, nan, landmarks.points,
                                             np.ones(len(landmarks.points)), math.nan,
                                             status=f"error: {landmarks.error}"))
                    continue
                # Each cup its own diameter where the file's value is the one in use.
                own = (resolved.sources["cup_diameter_mm"] == "landmark file"
                       and landmarks.cup_diameter_mm is not None)
                diameter = landmarks.cup_diameter_mm if own else resolved.values[
                    "cup_diameter_mm"]
                cups.append(solve_cup(landmarks, resolved.geometry(), diameter, refine=True))
            out.append(cups)
        return out


@dataclass
class Outputs:
    """Everything written under the output folder, kept and flushed together."""

    out: Path
    header: dict
    records: dict[str, dict] = field(default_factory=dict)
    assumptions: dict[str, str] = field(default_factory=dict)
    warnings: dict[str, str] = field(default_factory=dict)  # geometry key -> the first
    last_flush: float = 0.0
    flush_interval: float = FLUSH_SECONDS

    @property
    def csv_path(self) -> Path:
        return self.out / "results.csv"

    @property
    def json_path(self) -> Path:
        return self.out / "results.json"

    def load_previous(self) -> None:
        """For ``--resume``: the records of a previous run (results.csv is the authority)."""
        previous = {}
        if self.json_path.exists():
            try:
                document = json.loads(self.json_path.read_text())
                previous = {r["image"]: r for r in document["images"]}
                self.assumptions.update(document.get("assumptions", {}))
                self.warnings.update(document.get("warnings", {}))
            except (ValueError, KeyError, TypeError):
                previous = {}  # unreadable JSON: rebuild the records from the CSV
        if self.csv_path.exists():
            for name, rows in read_results_csv(self.csv_path).items():
                self.records[name] = previous.get(name) or {"image": name, "rows": rows}

    def remove_previous_images(self) -> None:
        """For ``--overwrite``: the overlays and masks a previous run's ``results.json`` lists
        removed, so none of an image no longer in the run stays beside the new results (only
        those files, and only under ``overlays/`` and ``masks/``)."""
        try:
            records = json.loads(self.json_path.read_text())["images"]
            written = [rel for r in records for rel in [r.get("overlay"), *r.get("masks", [])]
                       if isinstance(rel, str)]
        except (OSError, ValueError, KeyError, TypeError):
            return  # no readable list of what it wrote: nothing is removed
        folders = [(self.out / folder).resolve() for folder in ("overlays", "masks")]
        for rel in written:
            path = (self.out / rel).resolve()
            if any(path.is_relative_to(folder) for folder in folders) and path.is_file():
                path.unlink()

    def add(self, record: dict) -> None:
        self.records[record["image"]] = record

    def flush(self, summary: dict | None = None, force: bool = False) -> None:
        if not force and time.monotonic() - self.last_flush < self.flush_interval:
            return
        start = time.monotonic()
        document = {**self.header, "assumptions": self.assumptions, "warnings": self.warnings,
                    "summary": summary or summarise(self.records.values()),
                    "images": list(self.records.values())}
        atomic_write(self.json_path,
                     lambda f: json.dump(standard_json(document), f, indent=1, allow_nan=False))
        write_results_csv(self.csv_path, self.records.values())
        write_review_page(self.out / "review.html", self.records.values(), document["summary"])
        self.last_flush = time.monotonic()
        self.flush_interval = max(FLUSH_SECONDS, FLUSH_RATIO * (self.last_flush - start))


def standard_json(value: object) -> object:
    """``value`` as standard JSON holds it: numpy scalars as numbers, non-finite numbers as
    null (json.dump wrote ``Infinity`` for ``--denoise-above inf`` and ``NaN`` for a meta
    cell, which strict parsers, JavaScript's among them, reject)."""
    if isinstance(value, dict):
        return {key: standard_json(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [standard_json(item) for item in value]
    if isinstance(value, np.generic):
        value = value.item()
    return None if isinstance(value, float) and not math.isfinite(value) else value


def summarise(records: Iterable[dict]) -> dict:
    """Counts over image records: images, cups found, statuses, failures by reason, and
    the mean of the images' ``seconds`` (each its share of its batch's time: batches run
    two at once, so it exceeds the run's wall time per image)."""
    statuses: Counter[str] = Counter()
    images = cups = check = bright = cleaned = enlarged = reduced = patient_spacing = 0
    seconds = 0.0
    for record in records:
        images += 1
        spacing = record.get("geometry", {}).get("pixel_spacing_mm", {})
        patient_spacing += spacing.get("source") == PATIENT_SPACING_SOURCE
        for row in record["rows"]:
            statuses[row["status"]] += 1
            cups += row["status"] in ("ok", "ambiguous")
            check += str(row.get("check")) == "1"  # rows read back on --resume are strings
        bright += record["rows"][0].get("metal") == "bright"
        cleaned += str(record["rows"][0].get("denoised")) == "1"
        enlarged += record["rows"][0].get("enlarged") not in (None, "")
        reduced += record["rows"][0].get("reduced") not in (None, "")
        seconds += float(record["rows"][0].get("seconds") or 0.0)
    errors = {k: v for k, v in statuses.items() if k.startswith("error")}
    return {"images": images, "cups": cups, "ok": statuses["ok"],
            "ambiguous": statuses["ambiguous"], "check": check, "no_cup": statuses["no_cup"],
            "metal_bright": bright, "denoised": cleaned, "enlarged": enlarged,
            "reduced": reduced,
            "patient_spacing": patient_spacing,
            "errors": sum(errors.values()), "error_reasons": errors,
            "seconds_per_image": seconds / images if images else None}


def writable_folder(out: Path) -> None:
    """Make ``out`` and write (and remove) a file in it, so that one where nothing can be
    written is an OSError naming it before the model loads: it had ended the run in a
    traceback after the first batch, with exit 1 (every row an error, by the README)."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as error:
        raise OSError(f"cannot write to --out {out}: {error.strerror or error}") from error


def absolute_path(source: ImageSource) -> str:
    """An input file's absolute path, links not followed: how inputs are told apart, and
    by which a side file's row given by folder finds it (:func:`cupnet.io.meta.key_for_image`)."""
    return os.path.abspath(source.path)


def output_name(name: str, suffix: str) -> str:
    """File name under overlays/ or masks/ for an image name (a frame's ``#N`` ending ->
    ``_frameN``; a ``#`` elsewhere is the file's own); a name given by its path (two inputs
    of one name, :func:`gather_images`) stays under that folder: a root is dropped and each
    ``..`` becomes ``__``."""
    parts = [("__" if part == ".." else part) for part in PurePosixPath(name).parts
             if part not in ("/", ".")]
    # Every '#' had become '_frame': a file named a#1.png took a_frame1.png's overlay.
    return re.sub(r"#(\d+)$", r"_frame\1", "/".join(parts)) + suffix


# -- the run ----------------------------------------------------------------------------------
def gather_images(specs: list[str], recursive: bool, out: Path) -> list[ImageSource]:
    """The inputs of every spec (folder, file or glob), each file once.

    Names are relative to their spec's folder; where two specs give the same name (a shell
    expanding ``*/a.png``), each of those files is named by its path, so results stay apart
    and a side file's rows given by folder (``d1/a.png``, ``d2/a.png``) find theirs.

    Raises:
        ValueError: ``out`` is a file, or holds an input folder (its contents are skipped).
        FileNotFoundError: a spec names nothing, or no images (:func:`find_images`).
    """
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file; give a folder for the results")
    found: list[ImageSource] = []
    seen: set[str] = set()
    for spec in specs:
        if Path(spec).is_dir() and Path(spec).resolve().is_relative_to(out.resolve()):
            # Everything under --out is skipped as input (the overlays of earlier runs).
            raise ValueError(f"--out {out} holds the input folder {spec}; give a folder "
                             f"beside it or inside it (such as {Path(spec) / 'cupnet'})")
        for source in find_images(spec, recursive, exclude=out):
            # Absolute, links not followed: a file given twice (a folder and a glob in it)
            # runs once, but a link keeps its own row beside its target's (resolving it lost
            # whichever of the two names sorted second, and its side-file row with it).
            path = absolute_path(source)
            if path in seen:
                continue
            seen.add(path)
            found.append(source)
    # The first of a name had kept it, and a meta row of its folder (d1/a.png, beside
    # d2/a.png) then matched neither file by name alone.
    names = Counter(source.name for source in found)
    return [source if names[source.name] == 1
            else ImageSource(source.path, display_name(source.path.as_posix()))
            for source in found]


# The networks learnt images of 512 px and more, and a small image is enlarged to 512
# (CupNetConfig.enlarge_below): a bar under that would reduce sides the model enlarges.
MIN_REDUCED_SIDE = 512


def _check_args(args: argparse.Namespace) -> str | None:
    if args.resume and args.overwrite:
        return "--resume and --overwrite exclude each other"
    if args.batch_size < 1:
        return "--batch-size must be >= 1"
    if args.threads < 1:
        return "--threads must be >= 1"
    if args.min_score is not None and not 0 <= args.min_score <= 1:  # NaN fails too
        return f"--min-score must be a probability in [0, 1], got {args.min_score}"
    for flag, value in (("--check-doubt", args.check_doubt),
                        ("--denoise-above", args.denoise_above),
                        ("--enlarge-below", args.enlarge_below),
                        ("--reduce-above", args.reduce_above)):
        if value is not None and not value >= 0:
            return f"{flag} must be a number >= 0, got {value}"
    if args.reduce_above is not None and 0 < args.reduce_above < MIN_REDUCED_SIDE:
        return (f"--reduce-above must be 0 (never) or at least {MIN_REDUCED_SIDE} px, the "
                "networks' smallest training size")
    if args.rotate and args.landmarks is not None:
        return "--rotate turns the images for the network; --landmarks are solved as given"
    if args.blurred and args.landmarks is not None:
        return "--blurred chooses the network's rim stage; --landmarks are solved as given"
    if args.landmarks is None:
        if args.runtime == "onnx":  # asked for by name: it must run
            if args.device.split(":")[0] != "cpu":  # the device's type, as torch reads it
                return (f"--runtime onnx runs the networks on the CPU, not on --device "
                        f"{args.device}")
            missing = onnx_runtime_available()
            if missing is not None:
                return f"--runtime onnx: {missing}"
        try:
            resolve_device(args.device)
        except ValueError as exc:
            return str(exc)  # it names the device
    existing = [p.name for p in (args.out / "results.csv", args.out / "results.json")
                if p.exists()]
    if existing and not (args.resume or args.overwrite):
        return (f"{args.out} already holds {' and '.join(existing)}: use --resume to go on "
                "with it or --overwrite to replace it")
    return None


def _batches(frames: Iterator[Frame], size: int) -> Iterator[list[Frame]]:
    batch: list[Frame] = []
    for frame in frames:
        batch.append(frame)
        if sum(f.image is not None for f in batch) >= size:
            yield batch
            batch = []
    if batch:
        yield batch


@dataclass
class Batch:
    """A batch between :meth:`Predictor.prepare` and :meth:`Predictor.finish`."""

    size: int
    paths: list[str]  # each frame's file (absolute_path), kept in its record for --resume
    records: dict[int, dict] = field(default_factory=dict)
    ready: list[tuple[int, Frame, ResolvedGeometry]] = field(default_factory=list)


class Predictor:
    """Turns batches of frames into image records (rows, geometry, overlay, masks).

    :meth:`prepare` and :meth:`finish` run in the caller's thread, :meth:`detect` may run in
    a worker, so the network of one batch overlaps the overlays of the previous one.
    """

    def __init__(self, args: argparse.Namespace, detector: NetworkDetector | LandmarkDetector,
                 outputs: Outputs,
                 geometry_inputs: GeometryInputs) -> None:
        self.args, self.detector, self.outputs = args, detector, outputs
        self.geometry_inputs = geometry_inputs

    def _note_assumptions(self, geometry: ResolvedGeometry, width: int) -> None:
        for text in assumptions_once(geometry.sources, self.outputs.assumptions, width):
            tqdm.write(text, file=sys.stderr)

    def _note_implausible(self, name: str, geometry: ResolvedGeometry) -> None:
        """Warn, once per value, of a geometry value outside
        :data:`cupnet.io.meta.PLAUSIBLE_MM`."""
        for text in implausible_once(geometry.values, self.outputs.warnings, name,
                                     geometry.sources):
            tqdm.write(f"warning: {text}", file=sys.stderr)

    def prepare(self, frames: list[Frame]) -> Batch:
        """Read errors and geometry of a batch: records of the images that fail, and the
        images ready for detection."""
        batch = Batch(len(frames), [absolute_path(frame.source) for frame in frames])
        for i, frame in enumerate(frames):
            error = (f"error: {frame.error}" if frame.error is not None
                     else self.detector.input_error(frame))
            if error is not None:
                batch.records[i] = {"image": frame.name, "rows": [
                    status_row(frame.name, error, frame.seconds)]}
                continue
            geometry = self.geometry_inputs.resolve(
                frame.name, frame.image.shape,  # type: ignore[union-attr]
                {"sdd_mm": frame.sdd_mm, "pixel_spacing_mm": frame.pixel_spacing_mm},
                frame.tag_sources, self.detector.file_values(frame), batch.paths[i])
            if not geometry.complete:
                status = (geometry.error(frame.tag_notes)
                          if self.detector.needs_geometry(frame) else "no_cup")
                batch.records[i] = {"image": frame.name, "geometry": geometry.to_json(),
                                    "rows": [status_row(frame.name, status, frame.seconds)]}
                continue
            self._note_assumptions(geometry, frame.image.shape[1])
            self._note_implausible(frame.name, geometry)
            turned_frame(frame, geometry, self.args.rotate)
            batch.ready.append((i, frame, geometry))
        return batch

    def detect(self, batch: Batch) -> tuple[list[list | str], float]:
        """Cups of the batch's ready images and the seconds it took (runs in a worker)."""
        start = time.perf_counter()
        detections = self._detect(batch.ready) if batch.ready else []
        return detections, time.perf_counter() - start

    def finish(self, batch: Batch, detections: list[list | str], seconds: float) -> list[dict]:
        """Image records of a batch in input order: rows, overlays, masks."""
        share = seconds / max(1, len(batch.ready))
        for (i, frame, geo), cups in zip(batch.ready, detections, strict=True):
            if isinstance(cups, str):
                batch.records[i] = {"image": frame.name, "geometry": geo.to_json(), "rows": [
                    status_row(frame.name, cups, frame.seconds + share)]}
            else:
                batch.records[i] = self._record(frame, geo, cups, share)
        for i, path in enumerate(batch.paths):
            batch.records[i]["path"] = path
        return [batch.records[i] for i in range(batch.size)]

    def _detect(self, ready: list[tuple[int, Frame, ResolvedGeometry]]) -> list[list | str]:
        """Cups per image; where the batch fails, image by image, a failure an error status
        (an unforeseen one named by its type: the run goes on past a bug an odd image hits)."""
        try:
            return self.detector([f for _, f, _ in ready], [g for _, _, g in ready])
        except Exception as exc:  # noqa: BLE001 - one image's failure is its row, not the run's
            if len(ready) > 1:
                return [cups for item in ready for cups in self._detect([item])]
            reason = (error_reason(exc) if isinstance(exc, RuntimeError | ValueError)
                      else named_error(exc))
            return [f"error: detection failed ({reason})"]

    def _written(self, rel: str, image: np.ndarray, name: str) -> str | None:
        """``rel`` once ``image`` is written there under ``--out``; None where it cannot be
        (a name too long for the file system, a full disk, no permission): warned of once a
        run, and the image's rows are kept."""
        try:
            write_png(self.outputs.out / rel, image)
        except OSError as exc:
            if "unwritten_images" not in self.outputs.warnings:
                text = (f"cannot write {rel} ({exc.strerror or exc}); the poses are in "
                        f"results.csv, where an overlay or mask could not be written (first: "
                        f"{name})")
                self.outputs.warnings["unwritten_images"] = text
                tqdm.write(f"warning: {text}", file=sys.stderr)
            return None
        return rel

    def _record(self, frame: Frame, geometry: ResolvedGeometry, cups: list,
                compute_seconds: float) -> dict:
        start = time.perf_counter()
        record = {"image": frame.name, "geometry": geometry.to_json()}
        numbers = self.detector.cup_numbers(frame, len(cups))  # results.csv's cup
        if not self.args.no_overlays:
            drawings = [CupDrawing(c.ellipse, c.landmarks, c.weights,
                                   pose_lines(j, c.status, c.pose, c.residual_px, c.alt_pose,
                                              c.doubt, c.check, c.pose_sd),
                                   c.status, c.outline, c.check, j)
                        for j, c in zip(numbers, cups, strict=True)]
            title = f"{frame.name}: " + (f"{len(cups)} cup(s)" if cups else "no_cup")
            if self.args.rotate:
                title += f", turned {self.args.rotate} deg clockwise (--rotate)"
            if cups and cups[0].metal_bright:
                title += ", metal shown bright"
            if cups and cups[0].denoised:
                title += f", denoised (noise {cups[0].noise:.3f})"
            if cups and cups[0].enlarged:
                title += f", enlarged {cups[0].enlarged:.2f} times"
            if cups and cups[0].reduced:
                title += f", reduced to {cups[0].reduced:.2f} of its size"
            record["overlay"] = self._written(f"overlays/{output_name(frame.name, '.png')}",
                                              draw_overlay(frame.image, drawings, title),
                                              frame.name)
        if self.args.save_masks:
            masks = [self._written(f"masks/{output_name(frame.name, f'_cup{j}.png')}",
                                   np.round(np.clip(cup.mask, 0, 1) * 255).astype(np.uint8),
                                   frame.name)
                     for j, cup in zip(numbers, cups, strict=True) if cup.mask is not None]
            record["masks"] = [rel for rel in masks if rel is not None]
        seconds = frame.seconds + compute_seconds + time.perf_counter() - start
        record["rows"] = ([cup_row(frame.name, j, c, seconds)
                           for j, c in zip(numbers, cups, strict=True)]
                          or [status_row(frame.name, "no_cup", seconds)])
        return record


# Signals that end a run as Ctrl-C does, what finished written and the summary saying how to
# go on: a scheduler's time limit, `timeout`, `docker stop` (SIGTERM), a closed terminal
# (SIGHUP). Uncaught, they had ended it without the last rows or the summary.
STOPPING_SIGNALS = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP")
                         if hasattr(signal, name))


@contextlib.contextmanager
def signals_interrupt(received: list[int]) -> Iterator[None]:
    """Within it, :data:`STOPPING_SIGNALS` raise KeyboardInterrupt in the main thread, their
    number appended to ``received``; elsewhere (a thread) it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(number: int, _frame: object) -> None:
        received.append(number)
        raise KeyboardInterrupt

    previous = {number: signal.signal(number, stop) for number in STOPPING_SIGNALS}
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)


def _note_unmatched(outputs: Outputs, meta: dict, detector: object, names: list[str],
                    paths: dict[str, str]) -> None:
    """Warn of ``--meta`` rows and ``--landmarks`` sets that no image of the run found (frames
    find their file's; ``paths``: the files' absolute paths by name): each was left unused
    without a word."""
    tables = [("meta.csv", meta)]
    if isinstance(detector, LandmarkDetector):
        tables.append(("landmark", detector.sets))
    for what, table in tables:
        unused = unmatched_keys(table, names, paths)
        if unused:
            outputs.warnings[f"unmatched_{what}"] = (
                f"{len(unused)} {what} row(s) matched no image of the run (first: "
                f"{unused[0]}); check their names against the images'")
        else:  # a resumed run's images may have found the rows an earlier part left unused
            outputs.warnings.pop(f"unmatched_{what}", None)


def in_input_order(records: dict[str, dict], names: list[str]) -> dict[str, dict]:
    """``records`` (by image name) in the order of the run's input ``names`` (a file's
    frames in theirs), then those of no input of the run as they were: a resumed run had put
    its new images after the earlier part's, where a whole run sorts them in."""
    place = {name: i for i, name in enumerate(names)}

    def key(item: tuple[int, str]) -> tuple[int, int, int]:
        index, name = item
        file, frame = frame_file(name)
        if frame is not None and file in place:
            return (0, place[file], frame)
        return (0, place[name], 0) if name in place else (1, index, 0)

    order = sorted(enumerate(records), key=key)
    return {name: records[name] for _, name in order}


def renamed_moved(records: dict[str, dict], sources: list[ImageSource]) -> None:
    """An earlier run's record (in ``records``, by name, in place) of a file this run names
    otherwise (a second input folder with a file of its name, its folder spelt otherwise)
    takes the new name, found by its file's path: the file had been run again and counted
    twice under both names."""
    by_path: dict[str, list[str]] = {}
    for name, record in records.items():
        if isinstance(record.get("path"), str):
            by_path.setdefault(record["path"], []).append(name)
    for source in sources:
        for old in by_path.get(absolute_path(source), []):
            frame = frame_file(old)[1]
            new = source.name + ("" if frame is None else f"#{frame}")
            if new != old and new not in records:
                record = records.pop(old)
                record["image"] = new
                for row in record["rows"]:
                    row["image"] = new
                records[new] = record


def _software() -> dict:
    """The versions and CPU the poses rest on: the same weights find a few hard cups
    otherwise with another CPU or release of the numeric libraries (:mod:`cupnet.environment`)."""
    return {"cupnet": __version__, "python": platform.python_version(),
            "torch": torch.__version__, **library_versions(), "platform": platform.platform(),
            "cpu": processor()}


# The commonest error reasons the summary prints, each with its count.
SUMMARY_REASONS = 5


def _print_summary(summary: dict, out: Path, overlays: bool, elapsed: float,
                   interrupted: bool, warnings: dict[str, str]) -> None:
    lines = [
        f"{'interrupted' if interrupted else 'done'}: {summary['images']} images, "
        f"{summary['cups']} cups found ({summary['ok']} ok, {summary['ambiguous']} ambiguous), "
        f"{summary['no_cup']} without a cup, {summary['errors']} error rows",
    ]
    reasons = sorted(summary["error_reasons"].items(), key=lambda kv: -kv[1])
    lines += [f"  {n} x {reason}" for reason, n in reasons[:SUMMARY_REASONS]]
    if len(reasons) > SUMMARY_REASONS:
        rest = reasons[SUMMARY_REASONS:]
        lines.append(f"  {sum(n for _, n in rest)} error row(s) more, for {len(rest)} other "
                     "reason(s): the status column of results.csv")
    if summary["check"]:
        lines.append(f"  {summary['check']} cup(s) flagged (the model doubts them, or their given "
                     "landmarks lie off the rim): check=1 in results.csv, drawn in magenta on "
                     "the overlays; look before trusting them")
    if summary.get("patient_spacing"):
        lines.append(f"  {summary['patient_spacing']} image(s) with the detector's pixel spacing "
                     "taken from DICOM PixelSpacing, without a magnification factor (by the "
                     "standard the patient's spacing, smaller by the magnification: on the "
                     "benchmark's DRRs at 1.25, h came out about 160 mm small, a sixth of the "
                     "cups behind the detector (error rows) and the angles 1-3 deg worse; "
                     "docs/benchmarks.md); check, or give --pixel-spacing")
    if summary["metal_bright"]:
        lines.append(f"  {summary['metal_bright']} image(s) taken to show metal bright "
                     "(metal=bright in results.csv)")
    if summary.get("denoised"):
        lines.append(f"  {summary['denoised']} image(s) noisier than the networks' training, "
                     "denoised first: denoised=1 and their noise in results.csv")
    if summary.get("enlarged"):
        lines.append(f"  {summary['enlarged']} image(s) smaller than the networks' training, "
                     "enlarged first: the factor in results.csv's enlarged column")
    if summary.get("reduced"):
        lines.append(f"  {summary['reduced']} image(s) much larger than the networks' "
                     "training, reduced first: the factor in results.csv's reduced column")
    lines += [f"  warning: {text}" for text in warnings.values()]
    lines.append(f"results: {out / 'results.csv'}, results.json and review.html"
                 + (f"; overlays: {out / 'overlays'}" if overlays else "")
                 + f" ({elapsed:.1f} s this run)")
    if interrupted:
        lines.append("rerun the same command with --resume to process the rest")
    print("\n".join(lines))


def run(args: argparse.Namespace) -> int:
    # One intra-op thread by default: measured on the 2-core machine, 2 threads made the
    # network ~15x slower whenever another process used a core (OpenMP threads wait on each
    # other); parallelism comes from BATCHES_IN_FLIGHT batches and the reader threads instead.
    threads = torch.get_num_threads()
    torch.set_num_threads(max(1, args.threads))  # _check_args reports a bad value
    try:
        return _run(args)
    finally:
        torch.set_num_threads(threads)


def _model_settings(args: argparse.Namespace) -> dict[str, object]:
    """The model settings the command line overrides (flags not given keep the model's)."""
    given = {"check_doubt": args.check_doubt, "metal": args.metal,
             "min_score": args.min_score, "denoise_above": args.denoise_above,
             "enlarge_below": args.enlarge_below, "reduce_above": args.reduce_above,
             "round_field": False if args.keep_outside_field else None,
             "blurred": True if args.blurred else None}
    settings = {name: value for name, value in given.items() if value is not None}
    if settings.get("reduce_above") == 0:  # 0: never, as for --enlarge-below
        settings["reduce_above"] = None
    return settings


# The options that shape results.csv's rows (as argparse names them), with how to name each
# to the user: a resume with any of them changed would mix two runs' rows under the later
# run's settings alone. (Batch size, threads, device and runtime change no row.)
RESULT_OPTIONS = {"preset": "--fast / --fastest", "rotate": "--rotate", "metal": "--metal",
                  "check_doubt": "--check-doubt", "min_score": "--min-score",
                  "denoise_above": "--denoise-above", "enlarge_below": "--enlarge-below",
                  "reduce_above": "--reduce-above", "blurred": "--blurred",
                  "keep_outside_field": "--keep-outside-field", "meta": "--meta",
                  "sdd": "--sdd", "pixel_spacing": "--pixel-spacing",
                  "cup_diameter": "--cup-diameter", "principal_point": "--principal-point",
                  "assume_defaults": "--assume-defaults"}


def _changed_since(json_path: Path, header: dict) -> list[str]:
    """:func:`changed_settings` of the run whose results.json is ``json_path``; none where
    it is missing or unreadable (results.csv alone is resumed as it is)."""
    try:
        earlier = json.loads(json_path.read_text())
    except (OSError, ValueError):
        return []
    return changed_settings(earlier, header) if isinstance(earlier, dict) else []


def changed_settings(earlier: dict, header: dict) -> list[str]:
    """What differs between an earlier run's results.json ``earlier`` and this run's
    ``header`` among :data:`RESULT_OPTIONS`, and the model (or landmark file) and meta file
    by content, each as ``option: before -> now``."""
    before, now = earlier.get("arguments", {}), standard_json(header["arguments"])

    def same(key: str) -> bool:
        if key == "meta" and before.get(key) and now.get(key):  # spelt otherwise, one file
            return Path(before[key]).resolve() == Path(now[key]).resolve()
        return before.get(key) == now.get(key)

    def shown(value: object) -> object:
        return "not given" if value is None or value is False else value

    changed = [f"{option}: {shown(before.get(key))} -> {shown(now.get(key))}"
               for key, option in RESULT_OPTIONS.items() if not same(key)]
    if earlier.get("model", {}).get("sha256") != header["model"].get("sha256"):
        changed.append("the model's weights or the landmark file: other contents")
    # A meta file edited in place: the same path, other geometry for the images still to run.
    if same("meta") and earlier.get("meta_sha256", header["meta_sha256"]) != header["meta_sha256"]:
        changed.append("--meta: other contents")
    return changed


def _run(args: argparse.Namespace) -> int:
    problem = _check_args(args)
    if problem is None:
        try:
            sources = gather_images(args.images, args.recursive, args.out)
            geometry_inputs = GeometryInputs.from_args(args)
            writable_folder(args.out)
        except (OSError, ValueError) as exc:  # as cupnet solve: an unreadable --meta too
            problem = str(exc)
    if problem is not None:
        print(f"cupnet predict: error: {problem}", file=sys.stderr)
        return 2
    try:
        detector = (LandmarkDetector(args.landmarks) if args.landmarks is not None
                    else NetworkDetector(args.checkpoint, args.save_masks, args.preset,
                                         _model_settings(args), args.device, args.runtime))
    except Exception as exc:  # any unreadable model or landmark file stops the run here
        print(f"cupnet predict: error: cannot load {args.landmarks or 'the model'}: "
              f"{error_reason(exc)}",
              file=sys.stderr)
        return 2
    arguments = {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}
    header = {"software": _software(), "model": detector.info, "arguments": arguments,
              "meta_sha256": _sha256(args.meta) if args.meta is not None else None}
    outputs = Outputs(args.out, header)
    if args.resume:
        changed = _changed_since(outputs.json_path, header)
        if changed:
            print(f"cupnet predict: --resume with other settings than the run in {args.out} "
                  f"({'; '.join(changed)}): its rows would mix the two runs'; give the same "
                  "options, or --overwrite, or another --out", file=sys.stderr)
            return 2
        try:
            outputs.load_previous()
        except ValueError as exc:  # a results.csv cut short mid-row: no row is added to it
            print(f"cupnet predict: error: cannot resume: {exc}", file=sys.stderr)
            return 2
        renamed_moved(outputs.records, sources)
    elif args.overwrite:
        outputs.remove_previous_images()
    done = set(outputs.records)
    predictor = Predictor(args, detector, outputs, geometry_inputs)
    todo = [s for s in sources if s.name not in done]
    start = time.perf_counter()
    interrupted = False
    bar = tqdm(total=len(todo), unit="file", disable=args.quiet, desc="cupnet predict")
    frames = iter_frames(todo, skip=done)
    pool = ThreadPoolExecutor(BATCHES_IN_FLIGHT, thread_name_prefix="cupnet-detect")
    in_flight: deque[tuple[list[Frame], Batch, Future]] = deque()

    def complete() -> None:
        files, batch, future = in_flight.popleft()
        for record in predictor.finish(batch, *future.result()):
            outputs.add(record)
        bar.update(sum(f.last_of_source for f in files))
        outputs.flush()

    def run_all() -> None:
        for files in _batches(frames, args.batch_size):
            batch = predictor.prepare([f for f in files if not f.skipped])
            in_flight.append((files, batch, pool.submit(predictor.detect, batch)))
            while len(in_flight) >= BATCHES_IN_FLIGHT:
                complete()
        while in_flight:
            complete()
        # Only a run that went through every image can tell which rows no image found.
        _note_unmatched(outputs, geometry_inputs.meta, detector, list(outputs.records),
                        {source.name: absolute_path(source) for source in sources})

    stopped_by: list[int] = []  # the signal that ended the run as Ctrl-C does, if one did
    try:
        with signals_interrupt(stopped_by):
            run_all()
    except KeyboardInterrupt:
        interrupted = True
    finally:
        # Also on an unexpected error: what finished is written before it propagates.
        pool.shutdown(wait=False, cancel_futures=True)
        frames.close()
        bar.close()
        outputs.records = in_input_order(outputs.records, [source.name for source in sources])
        summary = summarise(outputs.records.values())
        outputs.flush(summary, force=True)
    _print_summary(summary, args.out, not args.no_overlays, time.perf_counter() - start,
                   interrupted, outputs.warnings)
    if interrupted:
        return 128 + (stopped_by[0] if stopped_by else signal.SIGINT)  # the shell's way
    # A script's `&&` should stop where nothing came of the run (a wrong --meta, no geometry).
    return 1 if summary["images"] and summary["cups"] + summary["no_cup"] == 0 else 0

