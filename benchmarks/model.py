"""CupNet speed and accuracy: segmentation + pose per 512x512 image, and pose MAE on fresh DRRs.

Run: ``python benchmarks/model.py [--checkpoint PATH] [--presets NAME ...] [--ablation NAME=PATH
...] [--images N] [--runtimes torch onnx] [--parts speed accuracy oblong fresh newer blind
unseen against small large captures degraded hardware geometry] [--against JSON]``. Writes the
``model`` (speed), ``model_accuracy`` (accuracy, ablation), ``model_oblong`` (oblong images),
``model_small`` and ``model_large`` (small and large images), ``model_captures``
(screenshots), ``model_degraded`` (JPEG, halved, noisier and blurrier images),
``model_hardware`` (screws and the cup's inserter in the image) and ``model_geometry`` (the
geometry given wrong; these seven not by default),
``model_fresh_seed`` (seeds no setting was chosen on), ``model_newer_seeds``,
``model_blind_seeds`` and ``model_unseen_seeds`` (seeds nobody had looked at when a rule was
made; not by default) and
``model_against`` (other inference settings, timed in one process) sections of
docs/benchmarks.md, and docs/model_failures.png (the shipped model's worst cases); for another
``--checkpoint``, benchmarks.md and model_failures.png beside it instead.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from unittest import mock

import cv2
import numpy as np
import torch
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import cupnet.field  # noqa: E402
from benchmarks.report import DOC, HEADER, machine, markdown_table, write_section  # noqa: E402
from cupnet.config import SPEED_PRESETS, apply_speed_preset  # noqa: E402
from cupnet.detection import CupDetection  # noqa: E402
from cupnet.evaluate import GROSS_DEG  # noqa: E402
from cupnet.fold import fold_batchnorm  # noqa: E402
from cupnet.geometry import Geometry  # noqa: E402
from cupnet.io.meta import (  # noqa: E402
    ASSUMED_CUP_DIAMETER_MM,
    ASSUMED_DETECTOR_WIDTH_MM,
    ASSUMED_SDD_MM,
)
from cupnet.model import DEFAULT_CHECKPOINT, MIN_IMAGE_SIDE, CupNet, load_model  # noqa: E402
from cupnet.offload import PassThrough  # noqa: E402
from cupnet.runtime import RUNTIMES, networks_in_onnx_runtime  # noqa: E402
from train.data import synth_config  # noqa: E402
from train.losses import POSE_NAMES as NAMES  # noqa: E402
from train.losses import POSE_SCALE as TARGETS  # noqa: E402  (the issue's target MAEs)
from train.losses import pose_errors  # noqa: E402
from train.module import cup_errors  # noqa: E402

# cupnet predict's --blurred (the blur-trained rim network in every rim stage), scored and
# timed as the speed presets are, under its option's name.
BLURRED = "blurred"
OPTIONS = [*SPEED_PRESETS, BLURRED]
# Seeds of fresh DRRs no inference setting was chosen on, and those that chose them (with the
# accuracy table's --seed) since the sixth session.
FRESH_SEEDS = [20_262_123, 20_263_123, 20_264_123, 20_265_123]
SELECTION_SEEDS = (777, 31337, 4242)
# Seed sets whose images no session had looked at when a rule was made; a session then
# looked at their missed cups and made the next rule (docs/training.md, item by item), so
# each set after the first tests the rule before it blind.
NEWER_SEEDS = [20_266_123, 20_267_123, 20_268_123, 20_269_123]
BLIND_SEEDS = [20_270_123, 20_271_123, 20_272_123, 20_273_123]
UNSEEN_SEEDS = [20_274_123, 20_275_123, 20_276_123, 20_277_123]
# docs/training.md's item -> the seeds whose missed cups it looked at.
LOOKED_AT = {42: FRESH_SEEDS, 43: NEWER_SEEDS, 44: BLIND_SEEDS}
# The --parts name of the seeds nobody has looked at yet.
UNLOOKED_PART = "unseen"
# accuracy()'s counts of the flagged cups, the gross failures and the ambiguous cups: the
# seed-set sections sum them over a part's seeds.
FLAG_COUNTS = ("flagged", "gross", "gross_flagged", "gross_alt_right", "gross_silent",
               "ambiguous", "ambiguous_gross")
# --parts name -> its section in the doc, its title and its seeds (None: --fresh-seeds).
SEED_SECTIONS = {"fresh": ("model_fresh_seed", "CupNet on fresh seeds", None),
                 "newer": ("model_newer_seeds", "CupNet on newer fresh seeds", NEWER_SEEDS),
                 "blind": ("model_blind_seeds", "CupNet on blind seeds", BLIND_SEEDS),
                 "unseen": ("model_unseen_seeds", "CupNet on unseen seeds", UNSEEN_SEEDS)}


def part_seeds(part: str, args: argparse.Namespace) -> list[int]:
    """The seeds of the fresh-seed ``part`` (one of :data:`SEED_SECTIONS`)."""
    seeds = SEED_SECTIONS[part][2]
    return args.fresh_seeds if seeds is None else seeds


def output_paths(checkpoint: str, doc: str | None = None,
                 gallery: str | None = None) -> tuple[Path, Path, str]:
    """Where the sections and the failure gallery go, and the header a new file starts with:
    the project's docs/ for the shipped checkpoint, else beside ``checkpoint``, so another
    model's figures never overwrite the shipped model's; ``doc`` and ``gallery`` override."""
    path = Path(checkpoint).resolve()
    if path == DEFAULT_CHECKPOINT.resolve():
        folder, header = DOC.parent, HEADER
    else:
        folder = path.parent
        header = (f"# Benchmarks of {checkpoint}\n\nWritten by `python benchmarks/model.py "
                  f"--checkpoint {checkpoint}`; \"the shipped model\" in its sections is this "
                  "checkpoint, with the inference settings of the JSON beside it.\n")
    return (Path(doc) if doc else folder / DOC.name,
            Path(gallery) if gallery else folder / "model_failures.png", header)


def write(name: str, body: str, args: argparse.Namespace) -> None:
    """Write section ``name`` to the file :func:`output_paths` chose for ``args``."""
    write_section(name, body, args.doc, args.header)


def samples(config: str | dict, seed: int, count: int,
            sizes: list[int] | list[tuple[int, int]] | None = None) -> list[dict]:
    """``count`` fresh samples of ``config`` (a YAML path or a dict of fields), split evenly
    over image ``sizes``: square sides, or ``(width, height)`` (None: the config's)."""
    from data_synth import SynthDataset

    sizes = sizes or [None]
    out = []
    for i, size in enumerate(sizes):
        share = count // len(sizes) + (i < count % len(sizes))
        out += list(SynthDataset(synth_config(config, size), seed=seed + i, length=share))
    return out


def shape(text: str) -> tuple[int, int]:
    """``"WxH"`` -> ``(W, H)`` pixels (an argparse type)."""
    width, _, height = text.partition("x")
    try:
        return int(width), int(height)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, got {text!r}") from None


def geometry_of(sample: dict) -> Geometry:
    return Geometry.from_row(sample["geometry"])


def detect_sample(model: CupNet, sample: dict) -> list[CupDetection]:
    """The cups ``model`` detects in one synthetic sample, with its geometry and cup size."""
    return model.detect(sample["image"][None], geometry_of(sample),
                        float(sample["cup_diameter"][0]), return_masks=False)[0]


def latency(model: CupNet, images: list[dict], repeats: int = 1) -> dict[str, float]:
    """Mean and median wall seconds per image of detect() (segmentation + landmarks + pose),
    batch of one, and the mean CPU seconds (all threads) per image: the steadier figure on a
    shared machine, where other work and the hypervisor take turns on the cores."""
    detect_sample(model, images[0])  # warm-up
    times = []
    cpu_start = time.process_time()
    for _ in range(repeats):
        for s in images:
            start = time.perf_counter()
            detect_sample(model, s)
            times.append(time.perf_counter() - start)
    return {"mean_s": float(np.mean(times)), "median_s": float(np.median(times)),
            "cpu_s": (time.process_time() - cpu_start) / len(times)}


def failure_gallery(cases: list[tuple[dict, int, CupDetection | None, np.ndarray | None]],
                    path: Path, count: int = 6, tile: int = 240) -> None:
    """The ``count`` true cups with the largest theta errors (unsolved cups first): a crop
    around each, the true rim in green, the landmarks in red, the errors as text.

    Args: cases: ``(sample, cup index, detection, errors)`` per true cup, from :func:`accuracy`.
    """
    from cupnet.overlay import display_image

    worst = sorted(cases, key=lambda case: -np.inf if case[3] is None else -case[3][0])
    tiles = []
    for s, c, det, err in worst[:count]:
        image = cv2.cvtColor(display_image(s["image"][0].numpy()), cv2.COLOR_GRAY2BGR)
        cx, cy, a, b, alpha = (float(v) for v in s["ellipse"][c])
        cv2.ellipse(image, ((cx, cy), (2 * a, 2 * b), alpha), (80, 220, 80), 1)
        for u, v in [] if det is None else det.landmarks:
            cv2.circle(image, (round(float(u)), round(float(v))), 1, (60, 60, 255), -1)
        half = int(1.5 * a) + 4
        x0, y0 = max(int(cx) - half, 0), max(int(cy) - half, 0)
        crop = cv2.resize(image[y0:int(cy) + half, x0:int(cx) + half], (tile, tile))
        text = ("missed" if det is None else det.status[:24]) if err is None else (
            f"d theta {err[0]:.1f}, d phi {err[1]:.1f}, d h {err[4]:.0f}")
        cv2.rectangle(crop, (0, tile - 18), (tile, tile), (0, 0, 0), -1)
        cv2.putText(crop, text, (4, tile - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1)
        tiles.append(crop)
    if tiles:
        cv2.imwrite(str(path), np.hstack(tiles))


def accuracy(model: CupNet, data: list[dict], cases: list | None = None) -> dict[str, float]:
    """Pose MAE (and median, 90th percentile) of matched cups and the fraction of true
    cups detected with a pose, the false positives (of them flagged), and the counts of
    :data:`FLAG_COUNTS` with the cups not flagged's MAE; appends ``(sample, cup index,
    detection, errors)`` of each true cup to ``cases`` when given."""
    errors, check, alt_right, ambiguous = [], [], [], []
    found, total, false_pos, false_flagged = 0, 0, 0, 0
    for s in data:
        dets = detect_sample(model, s)
        truth = s["pose"].double()
        cups, fp = cup_errors(dets, truth.numpy(), s["ellipse"].numpy(),
                              s["cup_valid"].numpy().astype(bool))
        if cases is not None:
            cases += [(s, c, det, err) for c, det, err in cups]
        errors += [err for _, _, err in cups if err is not None]
        check += [det.check for _, det, err in cups if err is not None]
        # An ambiguous pair reported in the wrong order: its second pose is right.
        alt_right += [det.alt_pose is not None and bool(
            (pose_errors(torch.from_numpy(det.alt_pose)[None], truth[c:c + 1])[0, :2].abs()
             <= GROSS_DEG).all()) for c, det, err in cups if err is not None]
        ambiguous += [det.alt_pose is not None for _, det, err in cups if err is not None]
        found += sum(err is not None for _, _, err in cups)
        total += len(cups)
        false_pos += fp
        matched = {id(det) for _, det, _ in cups if det is not None}
        false_flagged += sum(bool(det.check) for det in dets if id(det) not in matched)
    errors = np.array(errors) if errors else np.full((1, 5), np.nan)
    out = {}
    for stat, values in (("mae", errors.mean(0)), ("median", np.median(errors, 0)),
                         ("p90", np.percentile(errors, 90, 0))):
        out.update({f"{stat}_{n}": float(v) for n, v in zip(NAMES, values, strict=True)})
    out.update(detected=found / max(total, 1), cups=total, false_positives=false_pos,
               false_positives_flagged=false_flagged)
    # The cups the model flags to check by eye, and what is left once they are set apart.
    check = np.array(check or [False] * len(errors), dtype=bool)
    gross = errors[:, :2].max(1) > GROSS_DEG
    alt_right = np.array(alt_right or [False] * len(errors), dtype=bool)
    ambiguous = np.array(ambiguous or [False] * len(errors), dtype=bool)
    out.update(flagged=int(check.sum()), gross=int(gross.sum()),
               gross_flagged=int((gross & check).sum()),
               gross_alt_right=int((gross & alt_right).sum()),
               # Gross failures nothing warns of: neither flagged nor a pair in the wrong order.
               gross_silent=int((gross & ~check & ~alt_right).sum()),
               ambiguous=int(ambiguous.sum()), ambiguous_gross=int((ambiguous & gross).sum()),
               **{f"unflagged_mae_{n}": float(v) for n, v in zip(
                   NAMES, unflagged_mae(errors, check), strict=True)})
    return out


def false_detections(model: CupNet, data: list[dict]) -> tuple[int, int]:
    """Detections (any status) in images that hold no cup, and how many are flagged
    ``check``."""
    dets = [det for s in data for det in detect_sample(model, s)]
    return len(dets), sum(bool(det.check) for det in dets)


def with_flagged(count: int, flagged: int) -> str:
    """A table cell of ``count`` detections or failures and how many of them are flagged
    ``check``: ``"3 (1 flagged)"``."""
    return f"{count} ({flagged} flagged)"


def scored(res: dict[str, float]) -> list:
    """A table row's scores from :func:`accuracy`'s ``res``: the MAEs, cups found, false
    positives."""
    return [*[res[f"mae_{n}"] for n in NAMES], f"{100 * res['detected']:.1f} % of {res['cups']}",
            with_flagged(res["false_positives"], res["false_positives_flagged"])]


def resized_rows(model: CupNet, sizes: list[int], seed: int, count: int,
                 args: argparse.Namespace, setting: str, off: int | None, way: str,
                 flag: str) -> list[list]:
    """Rows of ``model`` on ``count`` fresh DRRs of each side in ``sizes`` (one ``seed``):
    as ``model`` takes them, and where it resizes them (its config's ``setting``: enlarge or
    reduce, said by ``way``), also as given (``setting`` set to ``off``, ``flag 0`` on
    ``cupnet predict``'s command line)."""
    shipped, rows = getattr(model.config, setting), []
    for size in sizes:
        setattr(model.config, setting, shipped)  # the row before may have turned it off
        data = samples(args.eval_config, seed, count, [size])
        ways = ([("as given", shipped)] if model.resize_factor(size, size) == 1
                else [(way, shipped), (f"as given (`{flag} 0`)", off)])
        for name, value in ways:
            setattr(model.config, setting, value)
            res = accuracy(model, data)
            print(size, name, res)
            rows.append([size, count, name, *scored(res), f"{res['median_theta']:.2f}",
                         f"{res['median_phi']:.2f}", res["gross"]])
    setattr(model.config, setting, shipped)
    return rows


SIZE_COLUMNS = ["side (px)", "images", "image", *[f"MAE {n}" for n in NAMES], "detected",
                "false positives", "median theta", "median phi", "gross failures"]


def small_section(model: CupNet, args: argparse.Namespace) -> str:
    """The shipped model on images of ``args.small`` sides, each size's DRRs from one seed:
    where :data:`cupnet.model.MIN_IMAGE_SIDE` comes from; the ``model_small`` section."""
    rows = resized_rows(model, args.small, args.seed + 21, args.small_images, args,
                        "enlarge_below", 0, "enlarged", "--enlarge-below")
    return ("## CupNet on small images\n\n"
            f"`python benchmarks/model.py --parts small --runtimes {args.runtimes[0]}`: "
            f"{args.small_images} fresh DRRs a size from `{args.eval_config}` (seed "
            f"{args.seed + 21}), the shipped model, MAE over detected true cups (deg, deg, mm, "
            "mm, mm) and the angles' medians (deg), false positives as in the accuracy table, "
            "gross failures (anteversion or inclination off by more than 5 deg). The model "
            f"enlarges an image under {model.config.enlarge_below} px to "
            f"{model.config.enlarge_to} px first (Lanczos; "
            "`enlarge_below`, docs/training.md, item 56); each such size is scored as given "
            "too. Below some side the poses are far off, not a little worse: `cupnet predict` "
            f"gives an image under {MIN_IMAGE_SIDE} px a side an error row "
            "(`cupnet.model.MIN_IMAGE_SIDE`).\n\n" + markdown_table(SIZE_COLUMNS, rows))


def large_section(model: CupNet, args: argparse.Namespace) -> str:
    """The shipped model on images of ``args.large`` sides, reduced as it reduces them and
    as given; the ``model_large`` section."""
    rows = resized_rows(model, args.large, args.seed + 61, args.large_images, args,
                        "reduce_above", None, "reduced", "--reduce-above")
    return ("## CupNet on large images\n\n"
            f"`python benchmarks/model.py --parts large --runtimes {args.runtimes[0]}`: "
            f"{args.large_images} fresh DRRs a size from `{args.eval_config}` (seed "
            f"{args.seed + 61}; the same scenes at each size, the detector's width drawn as "
            "for every size, so the pixels are finer), the shipped model, columns as for small "
            "images. Radiographs and many detectors give 1,500-3,000 px; the networks learnt "
            f"512 and 768 px. The model reduces an image over {model.config.reduce_above} px "
            f"to {model.config.reduce_to} px first (area averaging; `reduce_above`, "
            "docs/training.md, item 71), and each such size is scored as given too.\n\n"
            + markdown_table(SIZE_COLUMNS, rows))


def as_8_bit(sample: dict) -> np.ndarray:
    """``sample``'s image as an 8-bit export holds it: ``(H, W)`` uint8."""
    return np.round(sample["image"][0].numpy().clip(0, 1) * 255).astype(np.uint8)


def with_image(sample: dict, image: np.ndarray) -> dict:
    """``sample`` holding the 8-bit ``image`` ``(H, W)`` (as a reader gives it, in [0, 1])."""
    return dict(sample, image=torch.from_numpy(image.astype(np.float32) / 255)[None])


def in_a_disc(sample: dict, radius: float = 0.49) -> dict:
    """``sample`` with its image masked to a centred disc of ``radius`` of its width (a flat
    black surround), as an intensifier frame shows it, quantised to 8 bits."""
    image = sample["image"][0].numpy()
    height, width = image.shape
    v, u = np.mgrid[:height, :width]
    disc = np.hypot(u - (width - 1) / 2, v - (height - 1) / 2) <= radius * width
    return dict(sample, image=torch.from_numpy(np.round(np.where(disc, image, 0) * 255) / 255)
                .float()[None])


def captured(sample: dict) -> dict:
    """:func:`in_a_disc`'s frame as a screenshot shows it: in a capture 40 % wider and 16 %
    higher, its flat margins holding patient text, a side marker on the disc's corner; the
    geometry and true ellipses moved with it."""
    frame = as_8_bit(in_a_disc(sample))
    height, width = frame.shape
    left, top = int(0.2 * width), int(0.08 * height)
    capture = np.zeros((height + 2 * top, width + 2 * left), np.uint8)
    capture[top:top + height, left:left + width] = frame
    scale = width / 768
    for text, corner, size in (("PATIENT 0421  L HIP  2026-11-03", (10, int(0.05 * height)), 1.0),
                               ("kV 72 mA 3.1", (width, height + 2 * top - 10), 0.8),
                               ("R", (left + 20, top + int(0.1 * height)), 2.0)):
        cv2.putText(capture, text, corner, cv2.FONT_HERSHEY_SIMPLEX, size * scale, 255,
                    round(2 * size))
    geometry, ellipse = sample["geometry"].clone(), sample["ellipse"].clone()
    geometry[2:] += torch.tensor([left, top], dtype=geometry.dtype)
    ellipse[:, :2] += torch.tensor([left, top], dtype=ellipse.dtype)
    return dict(sample, image=torch.from_numpy(capture.astype(np.float32) / 255)[None],
                geometry=geometry, ellipse=ellipse)


def jpeg_exported(sample: dict, quality: int) -> dict:
    """``sample`` exported as an 8-bit JPEG of ``quality`` (OpenCV's libjpeg) and read back."""
    ok, data = cv2.imencode(".jpg", as_8_bit(sample), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError(f"OpenCV could not encode a JPEG of quality {quality}")
    return with_image(sample, cv2.imdecode(data, cv2.IMREAD_GRAYSCALE))


def halved(sample: dict) -> dict:
    """``sample`` exported at half its size (area-averaged, 8 bits): the pixel spacing
    doubles, and pixel centres at integers put the old ``u`` at ``(u + 0.5) / 2 - 0.5``, so
    the principal point and the true ellipses' centres move so and their axes halve."""
    image = cv2.resize(as_8_bit(sample), None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    geometry, ellipse = sample["geometry"].clone(), sample["ellipse"].clone()
    geometry[1] *= 2
    geometry[2:] = (geometry[2:] + 0.5) / 2 - 0.5
    ellipse[:, :2] = (ellipse[:, :2] + 0.5) / 2 - 0.5
    ellipse[:, 2:4] /= 2
    return dict(with_image(sample, image), geometry=geometry, ellipse=ellipse)


def noisier(sample: dict, sigma: float, rng: np.random.Generator) -> dict:
    """``sample`` with white Gaussian noise of standard deviation ``sigma`` (of the display
    range [0, 1]) added, clipped and exported at 8 bits."""
    image = sample["image"][0].numpy() + rng.normal(0.0, sigma, sample["image"].shape[1:])
    return with_image(sample, as_8_bit(dict(sample, image=torch.from_numpy(image)[None])))


def blurrier(sample: dict, sigma: float) -> dict:
    """``sample`` blurred by a Gaussian of ``sigma`` px on top of its own blur, at 8 bits."""
    return with_image(sample, cv2.GaussianBlur(as_8_bit(sample), (0, 0), sigma))


# --parts degraded: each row's label and what it does to a sample (with its own noise).
DEGRADATIONS: dict[str, Callable[[dict, np.random.Generator], dict]] = {
    "as rendered": lambda s, _: s,
    "8-bit PNG": lambda s, _: with_image(s, as_8_bit(s)),
    "JPEG, quality 90": lambda s, _: jpeg_exported(s, 90),
    "JPEG, quality 75": lambda s, _: jpeg_exported(s, 75),
    "JPEG, quality 50": lambda s, _: jpeg_exported(s, 50),
    "half the size (spacing doubled)": lambda s, _: halved(s),
    "noise, sigma 0.01 more": lambda s, rng: noisier(s, 0.01, rng),
    "noise, sigma 0.03 more": lambda s, rng: noisier(s, 0.03, rng),
    "blur, sigma 1 px more": lambda s, _: blurrier(s, 1.0),
    "blur, sigma 2 px more": lambda s, _: blurrier(s, 2.0),
}


def robustness_rows(part: str, label: str, models: dict[str, CupNet], images: list[dict]
                    ) -> list[list[object]]:
    """One table row for each of ``models``, scored on ``images``: ``label`` (the row
    group; printed with ``part``), the model's name, its :func:`scored` figures, the
    angles' medians and its gross failures (of them flagged)."""
    rows = []
    for name, model in models.items():
        res = accuracy(model, images)
        print(part, label, name, res)
        rows.append([label, name, *scored(res), f"{res['median_theta']:.2f}",
                     f"{res['median_phi']:.2f}", f"{res['gross']} ({res['gross_flagged']})"])
    return rows


def preset_flags(args: argparse.Namespace) -> str:
    """``--presets`` as the command line gave them where not the default (the speed
    presets), for a section's command; else nothing."""
    return "" if args.presets == list(SPEED_PRESETS) else f" --presets {' '.join(args.presets)}"


def runtime_flags(args: argparse.Namespace) -> str:
    """``--runtimes`` as the command line gave them, for a section's command (the default
    runtime's alone would replace a section of both runtimes' rows with its own)."""
    return f" --runtimes {' '.join(args.runtimes)}"


def seed_preset_flags(args: argparse.Namespace) -> str:
    """``--seed-presets`` as the command line gave them, one flag (argparse keeps the last of
    several), for a section's command; nothing where none were given."""
    return f" --seed-presets {' '.join(args.seed_presets)}" if args.seed_presets else ""


def robustness_intro(part: str, count: int, seed: int, args: argparse.Namespace) -> str:
    """A robustness section's command (``--parts part``) and the ``count`` fresh DRRs it
    scores, from seed ``seed`` on."""
    return (f"`python benchmarks/model.py --parts {part}{runtime_flags(args)}"
            + seed_preset_flags(args)
            + f"`: {count} fresh DRRs from `{args.eval_config}` at "
            f"{', '.join(map(str, args.sizes))} px in equal shares (seeds {seed} on)")


ROBUSTNESS_COLUMNS = ["images", "settings", *[f"MAE {n}" for n in NAMES], "detected",
                      "false positives", "median theta", "median phi", "gross (flagged)"]
# Surgical hardware in the image (docs/synth.md): SynthConfig fields set on the eval config.
HARDWARE = {
    "none": {},
    "screws (1-3 through the dome)": {"p_screws": 1.0},
    "inserter (a rod along the cup's axis)": {"p_impactor": 1.0},
    "screws and inserter": {"p_screws": 1.0, "p_impactor": 1.0},
}


def hardware_section(models: dict[str, CupNet], args: argparse.Namespace) -> str:
    """The ``model_hardware`` section: each of ``models`` (the shipped model and its presets)
    on the same fresh DRRs without surgical hardware and with each kind of it (screws, the
    cup's inserter), as the shipped weights' last stage was trained on (other seeds)."""
    rows, eval_fields = [], yaml.safe_load(Path(args.eval_config).read_text()) or {}
    for label, fields in HARDWARE.items():
        images = samples({**eval_fields, **fields}, args.seed + 51, args.hardware_images,
                         args.sizes)
        rows += robustness_rows("hardware", label, models, images)
    return ("## CupNet with surgical hardware in the image\n\n"
            + robustness_intro("hardware", args.hardware_images, args.seed + 51, args)
            + ", each row the same scenes and noise with the hardware added (`SynthConfig`'s "
            "`p_screws` and `p_impactor`, docs/synth.md): 1-3 titanium screws 20-45 mm long "
            "through each cup's dome, or the inserter the first cup is held on during "
            "impaction, a steel rod 8-16 mm across along the cup's axis, out through the "
            "opening and the field (the cup on it without liner, head or stem yet). The "
            "shipped weights' last stage trained on images with both (docs/training.md, "
            "item 64; other seeds), and a cup still doubted after the other looks is looked "
            "at once more with a rod found across the image painted over (`rod_look`, item "
            "70). Columns as in the degraded table.\n\n"
            + markdown_table(ROBUSTNESS_COLUMNS, rows))


def misgiven(sample: dict, sdd: float = 1.0, spacing: float = 1.0, centred: bool = False,
             diameter_mm: float = 0.0, assumed: bool = False) -> dict:
    """``sample`` with its geometry given as a user unsure of it may give it: the SDD and
    pixel spacing times ``sdd`` and ``spacing``, the principal point at the image's centre
    where ``centred``, each cup's diameter ``diameter_mm`` larger; with ``assumed`` all of
    them as ``cupnet predict --assume-defaults`` fills them (:mod:`cupnet.io.meta`'s SDD, cup
    diameter and detector width over the image's), the principal point at the centre. Its
    image and truth (pose, ellipses) as they are."""
    height, width = sample["image"].shape[-2:]
    geometry, diameter = sample["geometry"].clone(), sample["cup_diameter"]
    if assumed:
        geometry[:2] = torch.tensor([ASSUMED_SDD_MM, ASSUMED_DETECTOR_WIDTH_MM / width],
                                    dtype=geometry.dtype)
        diameter = torch.full_like(diameter, ASSUMED_CUP_DIAMETER_MM)
    geometry[0] *= sdd
    geometry[1] *= spacing
    if centred or assumed:
        geometry[2:] = torch.tensor([(width - 1) / 2, (height - 1) / 2], dtype=geometry.dtype)
    return dict(sample, geometry=geometry, cup_diameter=diameter + diameter_mm)


# --parts geometry: each row's label and the geometry it gives the model (misgiven's).
MISGIVEN: dict[str, dict[str, float | bool]] = {
    "as drawn (the truth)": {},
    "SDD 10 % short": {"sdd": 0.9},
    "SDD 5 % short": {"sdd": 0.95},
    "SDD 5 % long": {"sdd": 1.05},
    "SDD 10 % long": {"sdd": 1.1},
    "pixel spacing 2 % small": {"spacing": 0.98},
    "pixel spacing 2 % large": {"spacing": 1.02},
    "pixel spacing at the patient (the detector's / 1.25)": {"spacing": 0.8},
    "principal point at the image's centre": {"centred": True},
    "cup diameter 2 mm small": {"diameter_mm": -2.0},
    "cup diameter 2 mm large": {"diameter_mm": 2.0},
    "all as --assume-defaults fills them": {"assumed": True},
}


def geometry_section(models: dict[str, CupNet], args: argparse.Namespace) -> str:
    """The ``model_geometry`` section: each of ``models`` on the same fresh DRRs, told their
    geometry rightly and each way of :data:`MISGIVEN`, scored against the truth."""
    data = samples(args.eval_config, args.seed + 71, args.geometry_images, args.sizes)
    drawn = synth_config(args.eval_config)
    rows = []
    for label, given in MISGIVEN.items():
        rows += robustness_rows("geometry", label, models, [misgiven(s, **given) for s in data])
    return ("## CupNet with the geometry given wrong\n\n"
            + robustness_intro("geometry", args.geometry_images, args.seed + 71, args)
            + ", each row the same images with the geometry given otherwise than drawn "
            "(`benchmarks/model.py`, `MISGIVEN`): the source-to-detector distance (SDD) or "
            "the detector's pixel spacing off by a share, the pixel spacing given at the "
            "patient rather than at the detector (DICOM PixelSpacing for "
            "ImagerPixelSpacing, at a magnification of 1.25), the principal point left at "
            f"the image's centre (drawn within {100 * drawn.principal_offset_frac:g} % of "
            "the side from it), the cup's "
            "diameter off by 2 mm, or all of them as `cupnet predict --assume-defaults` "
            f"fills them (SDD {ASSUMED_SDD_MM:g} mm, pixel spacing "
            f"{ASSUMED_DETECTOR_WIDTH_MM:g} mm over the image's width, cup diameter "
            f"{ASSUMED_CUP_DIAMETER_MM:g} mm, the principal point at the centre; drawn: SDD "
            f"{drawn.sdd_mm[0]:g}-{drawn.sdd_mm[1]:g} mm, detector "
            f"{drawn.detector_width_mm[0]:g}-{drawn.detector_width_mm[1]:g} mm wide, cups "
            f"{drawn.cup_diameter_mm[0]:g}-{drawn.cup_diameter_mm[1]:g} mm). Scored against "
            "the drawn truth, in the drawn geometry's millimetres. Columns as in the "
            "degraded table.\n\n"
            + markdown_table(ROBUSTNESS_COLUMNS, rows))


def degraded_section(models: dict[str, CupNet], args: argparse.Namespace) -> str:
    """The shipped model (and ``models``' presets) on the same fresh DRRs as exported,
    compressed, shrunk, noisier and blurrier than any training image: the
    ``model_degraded`` section."""
    data = samples(args.eval_config, args.seed + 41, args.degraded_images, args.sizes)
    shipped = next(iter(models.values())).config
    rows = []
    for label, degrade in DEGRADATIONS.items():
        rng = np.random.default_rng(args.seed + 41)  # each row's noise, the same for each model
        images = [degrade(s, rng) for s in data]
        rows += robustness_rows("degraded", label, models, images)
    return ("## CupNet on degraded images\n\n"
            + robustness_intro("degraded", args.degraded_images, args.seed + 41, args)
            + ", each row the same images degraded as a user's export may be "
            "(`benchmarks/model.py`, `DEGRADATIONS`): 8-bit, JPEG (OpenCV), halved in size "
            "(area-averaged, the pixel spacing and principal point given accordingly; the "
            f"model enlarges those under {shipped.enlarge_below} px to {shipped.enlarge_to} "
            "first, docs/training.md, item 56), "
            "more white noise (standard deviation of the display range [0, 1]) or more "
            "Gaussian blur. Training saw a focal-spot blur of sigma 0.2-1.0 px, quantum and "
            "electronic noise at 300-20,000 photons a pixel, 8 or 16 bits, and no JPEG "
            "(docs/synth.md). MAE over detected true cups (deg, deg, mm, mm, mm), false "
            "positives as in the accuracy table, the angles' medians (deg: the typical cup, "
            "where a few gross failures move the MAE); gross: cups whose theta or phi is off by "
            f"more than {GROSS_DEG:g} deg (of them flagged `check`).\n\n"
            + markdown_table(ROBUSTNESS_COLUMNS, rows))


def captures_section(model: CupNet, args: argparse.Namespace) -> str:
    """The shipped model on intensifier frames and on screenshots of them, the latter with
    and without its cut of a narrow field to its square: the ``model_captures`` section."""
    data = samples(args.eval_config, args.seed + 31, args.capture_images, [512, 768])
    rows = []
    for label, images, crop_below in (
            ("the frames (a disc of radius 0.49 of the width)", [in_a_disc(s) for s in data],
             cupnet.field.CROP_BELOW),
            ("the captures, whole (as before `field_crop`)", [captured(s) for s in data], 0.0),
            ("the captures, the field cut out (`detect`)", [captured(s) for s in data],
             cupnet.field.CROP_BELOW)):
        with mock.patch.object(cupnet.field, "CROP_BELOW", crop_below):
            res = accuracy(model, images)
        print("captures", label, res)
        rows.append([label, len(images), *scored(res)])
    return ("## CupNet on screenshots\n\n"
            f"`python benchmarks/model.py --parts captures --runtimes {args.runtimes[0]}`: "
            f"{args.capture_images} fresh DRRs at 512 and 768 px from `{args.eval_config}` "
            f"(seed {args.seed + 31}), each masked to an intensifier's disc, and the same "
            "frames as a screenshot or secondary capture holds them: in flat margins 40 % "
            "wider and 16 % higher with burnt-in text (`benchmarks/model.py`, `captured`). "
            "The disc then spans about 0.85 of the capture's height, narrower than any training "
            "frame's; `CupNet.detect` cuts such a field to its square first "
            "(`cupnet.field.field_crop`, below `CROP_BELOW` of the short side). MAE over "
            "detected true cups (deg, deg, mm, mm, mm), false positives as in the accuracy "
            "table; cups cut by the disc's edge count too.\n\n"
            + markdown_table(["images", "count", *[f"MAE {n}" for n in NAMES], "detected",
                              "false positives"], rows))


def oblong_section(models: dict[str, CupNet], args: argparse.Namespace) -> str:
    """The shipped model's accuracy on oblong images (their field of view as wide as their
    short side), per shape and pooled over the shapes' cups, with the networks in each
    runtime ``models`` holds (by name): the ``model_oblong`` section."""
    rows = []
    for runtime, model in models.items():
        maes, found, cups, false, gross = [], [], [], [], []
        for i, size in enumerate(args.oblong):
            count = (args.oblong_images // len(args.oblong)
                     + (i < args.oblong_images % len(args.oblong)))
            res = accuracy(model, samples(args.eval_config, args.seed + 11 + i, count, [size]))
            print("oblong", runtime, size, res)
            maes.append([res[f"mae_{n}"] for n in NAMES])
            found.append(res["detected"] * res["cups"])
            cups.append(res["cups"])
            false.append((res["false_positives"], res["false_positives_flagged"]))
            gross.append((res["gross"], res["gross_flagged"]))
            rows.append([runtime, f"{size[0]}x{size[1]}", count, *scored(res),
                         with_flagged(*gross[-1])])
        pooled = np.average(maes, axis=0, weights=found)  # each shape's MAE: its found cups
        rows.append([runtime, "all", args.oblong_images, *pooled,
                     f"{100 * sum(found) / sum(cups):.1f} % of {sum(cups)}",
                     with_flagged(*np.sum(false, 0)), with_flagged(*np.sum(gross, 0))])
    return ("## CupNet on oblong images\n\n"
            f"`python benchmarks/model.py --parts oblong --runtimes {' '.join(models)}`: "
            f"{args.oblong_images} fresh DRRs from `{args.eval_config}` (seeds "
            f"{args.seed + 11} on), the shipped model with its networks in each runtime, MAE "
            "over detected true cups (deg, deg, mm, mm, mm), false positives as in the "
            "accuracy table. The locator sees an oblong image through square windows of its "
            "short side (`cupnet.crops.square_windows`); it was trained on square images "
            "only. Its blobs centred outside an intensifier's round field are dropped "
            "(`cupnet.field.round_field`). Gross: cups whose theta or phi is off by more "
            f"than {GROSS_DEG:g} deg (of them flagged `check`): with "
            f"{args.oblong_images // max(len(args.oblong), 1)} images a shape, one such cup "
            "can move a shape's MAE by a degree.\n\n"
            + markdown_table(["runtime", "shape (W x H px)", "images",
                              *[f"MAE {n}" for n in NAMES], "detected", "false positives",
                              "gross failures"], rows))


def unflagged_mae(errors: np.ndarray, check: np.ndarray) -> np.ndarray:
    """MAE ``(5,)`` (deg, deg, mm, mm, mm) of the cups of ``errors`` ``(N, 5)`` whose
    ``check`` ``(N,)`` is False; NaN where every cup is flagged."""
    return errors[~check].mean(0) if (~check).any() else np.full(5, np.nan)


def flag_summary(res: dict[str, float], detected: int, model: CupNet) -> str:
    """What ``model``'s ``check`` flag marks among its ``detected`` cups (``res``:
    :func:`accuracy`'s counts, or their sums over sets), as a clause."""
    share = 100 * res["flagged"] / max(detected, 1)
    return (f"flags {res['flagged']} of the {detected} detected cups ({share:.1f} %) `check` "
            f"(its doubt >= `check_doubt` {model.config.check_doubt}), "
            f"{res['gross_flagged']} of the {res['gross']} gross failures (anteversion or "
            f"inclination off by more than {GROSS_DEG:g} deg) among them; "
            f"{res['gross_alt_right']} of those {res['gross']} are ambiguous pairs reported "
            "in the wrong order (status `ambiguous`, the second pose right), whose two poses "
            f"the doubt can rarely tell apart; with no warning at all: {res['gross_silent']} "
            f"of the {res['gross']}")


def interval(values: np.ndarray, draws: int = 1000) -> np.ndarray:
    """95 % bootstrap interval ``(2, ...)`` of the mean of ``values`` ``(N, ...)`` over its
    first axis (seeded: the same values give the same interval)."""
    rng = np.random.default_rng(0)
    means = [values[rng.integers(0, len(values), len(values))].mean(0) for _ in range(draws)]
    return np.percentile(means, [2.5, 97.5], 0)


def fresh_seed_intro(args: argparse.Namespace, runtimes: list[str], part: str = "fresh"
                     ) -> str:
    """The fresh-seed section's title and prose (``part``: one of :data:`SEED_SECTIONS`):
    the command that measures it, and whether its seeds are fresh (an honest estimate),
    include seeds that chose settings, or seeds whose missed cups a later rule was made on."""
    seeds = part_seeds(part, args)
    command = f"python benchmarks/model.py --parts {part} --runtimes {' '.join(runtimes)}"
    if args.checkpoint != str(DEFAULT_CHECKPOINT):
        command += f" --checkpoint {args.checkpoint}"
    if part == "fresh" and seeds != FRESH_SEEDS:
        command += f" --fresh-seeds {' '.join(map(str, seeds))}"
    command += seed_preset_flags(args)
    chosen_on = sorted(set(seeds) & {args.seed, *SELECTION_SEEDS})
    honesty = (f"of these seeds {', '.join(map(str, chosen_on))} chose inference settings, "
               "so these figures flatter the model" if chosen_on else
               "seeds no inference setting was chosen on (the accuracy table's seed, and "
               f"seeds {', '.join(map(str, SELECTION_SEEDS))}, chose them since the sixth "
               "session): the honest estimate of the shipped model's accuracy")
    looked = [(item, sorted(set(seeds) & set(looked_at)))
              for item, looked_at in LOOKED_AT.items() if set(seeds) & set(looked_at)]
    if looked:
        honesty += (" (but a session made a rule after looking at the missed cups of seeds "
                    + "; of seeds ".join(f"{', '.join(map(str, found))} (docs/training.md, "
                                         f"item {item})" for item, found in looked)
                    + f"; `--parts {UNLOOKED_PART}` measures seeds nobody had looked at)")
    return (f"## {SEED_SECTIONS[part][1]}\n\n"
            f"`{command}`: {args.fresh_images} DRRs a seed from `{args.eval_config}` at "
            f"{', '.join(map(str, args.sizes))} px, {honesty}, seed by seed and pooled, with "
            "95 % bootstrap intervals over the cups. A few gross failures a seed move its "
            f"means. MAE over detected true cups (deg, deg, mm, mm, mm); targets {TARGETS}."
            "\n\n")


def fresh_seed_section(models: dict[str, CupNet], args: argparse.Namespace,
                       part: str = "fresh") -> str:
    """The shipped model's accuracy on fresh DRRs of ``part``'s seeds (:func:`part_seeds`:
    "fresh", by default seeds no setting was chosen on, "newer", "blind" or "unseen"), each
    and pooled (with 95 % bootstrap intervals over the cups), with the networks in each runtime
    and under each speed preset ``models`` holds (by name): that part's section
    (:data:`SEED_SECTIONS`), with a line a model pooling over the seeds what its ``check``
    flag marks and its ambiguous cups (:data:`FLAG_COUNTS`)."""
    rows, flags = [], []
    for name, model in models.items():
        per_cup: list[np.ndarray | None] = []  # each true cup's, None where missed
        checked: list[bool] = []  # each found cup's check flag
        counts = dict.fromkeys(FLAG_COUNTS, 0)
        for seed in part_seeds(part, args):
            cases: list = []
            res = accuracy(model, samples(args.eval_config, seed, args.fresh_images,
                                          args.sizes), cases)
            per_cup += [err for *_, err in cases]  # not the samples: their images are big
            checked += [bool(det.check) for _, _, det, err in cases if err is not None]
            counts = {key: counts[key] + res[key] for key in FLAG_COUNTS}
            print("fresh seed", seed, name, res)
            rows.append([name, seed, *[f"{res[f'mae_{n}']:.3g}" for n in NAMES],
                         f"{100 * res['detected']:.1f} % of {res['cups']}",
                         with_flagged(res["false_positives"], res["false_positives_flagged"])])
        errors = np.array([err for err in per_cup if err is not None])
        found = np.array([err is not None for err in per_cup], dtype=np.float64)
        low, high = interval(errors)
        found_low, found_high = 100 * interval(found)
        rows.append([name, "all, 95 % interval",
                     *[f"{m:.3g} [{lo:.3g}, {hi:.3g}]" for m, lo, hi in
                       zip(errors.mean(0), low, high, strict=True)],
                     # The count and two decimals: at 99 % a cup is 0.13 points, and one
                     # decimal rounded 755 of 763 (98.95 %) up to the target.
                     f"{int(found.sum())} of {len(found)}, {100 * found.mean():.2f} % "
                     f"[{found_low:.1f}, {found_high:.1f}]", ""])
        # The README's advice to look at flagged cups rests on these pooled counts.
        unflagged = unflagged_mae(errors, np.array(checked, dtype=bool))
        flags.append(f"Pooled, {name} {flag_summary(counts, len(errors), model)}; the cups "
                     f"not flagged have MAE theta {unflagged[0]:.3g} deg, phi "
                     f"{unflagged[1]:.3g} deg, h {unflagged[4]:.3g} mm. Found cups "
                     f"`ambiguous`: {counts['ambiguous']}; the pose reported first lies "
                     f"within {GROSS_DEG:g} deg for "
                     f"{counts['ambiguous'] - counts['ambiguous_gross']} of them, the second "
                     f"for {counts['gross_alt_right']} of the other {counts['ambiguous_gross']}.")
    return (fresh_seed_intro(args, args.runtimes, part)
            + markdown_table(["runtime", "seed", *[f"MAE {n}" for n in NAMES], "detected",
                              "false positives"], rows)
            + "".join(f"\n\n{line}" for line in flags))


class StripCounter(PassThrough):
    """A rim network that counts the strips it is asked for (``count``): the work of
    :meth:`CupNet.detect` that does not drift with the machine's load (strips are about 60 %
    of its time)."""

    def __init__(self, module: torch.nn.Module) -> None:
        super().__init__()
        self.module = module
        self.count = 0

    def forward(self, strips: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        self.count += strips.shape[0]
        return self.module(strips)


@contextlib.contextmanager
def counting_strips(model: CupNet) -> Iterator[list[StripCounter]]:
    """``model`` with its rim networks counting the strips they are asked for, within the
    block, which is given their counters; put back as they were after it."""
    names = [name for name in ("rim", "coarse_rim", "blur_rim")
             if getattr(model, name) is not None]
    counters = {name: StripCounter(getattr(model, name)) for name in names}
    for name, counter in counters.items():
        setattr(model, name, counter)
    try:
        yield list(counters.values())
    finally:
        for name, counter in counters.items():
            setattr(model, name, counter.module)


def against_section(model: CupNet, other: CupNet, args: argparse.Namespace) -> str:
    """The shipped model against itself with the inference settings ``args.against``, in one
    process, alternating image by image on the speed set and 90 images of the accuracy set's
    seeds, and on 30 of the images without a cup (where a look at images with no cup found
    costs most): the ``model_against`` section. A change's speed is measured so, not across
    runs: this shared machine's speed drifts by a third between them."""
    sets = {"speed set (20 x 512 px)": samples(args.speed_config, args.seed + 1, 20),
            "90 of the accuracy set's seeds": samples(args.eval_config, args.seed, 90, args.sizes),
            "30 of the no-cup set's": samples(args.no_cup_config, args.seed + 7, 30, args.sizes)}
    models = {"shipped": model, f"with {args.against}": other}
    rows = []
    for set_name, data in sets.items():
        times: dict[str, list[float]] = {name: [] for name in models}
        for net in models.values():
            detect_sample(net, data[0])  # warm-up
        with contextlib.ExitStack() as stack:
            counters = {name: stack.enter_context(counting_strips(net))
                        for name, net in models.items()}
            for sample in data:
                for name, net in models.items():
                    start = time.process_time()
                    detect_sample(net, sample)
                    times[name].append(time.process_time() - start)
        rows += [[set_name, name, 1000 * np.mean(t), 1000 * np.median(t),
                  sum(counter.count for counter in counters[name]) / len(data)]
                 for name, t in times.items()]
    return ("## CupNet against other inference settings, in one process\n\n"
            f"`python benchmarks/model.py --parts against --runtimes {args.runtimes[0]} "
            f"--against '{args.against}'` on "
            f"{machine()}: the shipped model and the same weights with those settings, "
            "alternating image by image, CPU time of `detect` (one thread"
            f"{', networks in ONNX Runtime' if args.runtimes[0] == 'onnx' else ''}), and the "
            "rim-network strips asked for an image, counted in the same run: the work, which "
            "does not drift with the machine's load.\n\n"
            + markdown_table(["images", "model", "mean CPU ms / image",
                              "median CPU ms / image", "strips / image"], rows))


def speed_section(models: dict[str, CupNet], args: argparse.Namespace) -> None:
    """Time ``models`` end to end on 20 synthetic 512x512 images; writes the ``model`` section."""
    speed_set = samples(args.speed_config, args.seed + 1, 20)
    rows = []
    for name, net in models.items():
        for threads in args.threads:
            torch.set_num_threads(threads)
            timing = latency(net, speed_set)
            rows.append([f"{name}: segmentation + pose, 512x512, batch 1, {threads} thread(s)",
                         f"{1000 * timing['mean_s']:.1f}", f"{1000 * timing['median_s']:.1f}",
                         f"{1 / timing['mean_s']:.1f}", f"{1000 * timing['cpu_s']:.1f}"])
    torch.set_num_threads(args.threads[0])
    speed = markdown_table(["model, pipeline", "mean ms / image", "median ms / image",
                            "images / s", "CPU ms / image"], rows)
    print(speed)
    write("model", "## CupNet speed\n\n"
          f"`python benchmarks/model.py --parts speed{runtime_flags(args)}{preset_flags(args)}` "
          f"on {machine()}; checkpoint "
          f"`{Path(args.checkpoint).name}`, as it is and with its speed presets "
          f"({', '.join(f'`--{p}`' for p in args.presets) or 'none'}, as `cupnet "
          "predict` takes them); 20 synthetic 512x512 images, "
          "`CupNet.detect` end to end (locator, 2 refiner passes, rim stages, pose "
          "with ML refinement; BatchNorm folded, as `cupnet predict` runs it), "
          "machine load at the start: "
          f"{os.getloadavg()[0]:.1f} (other agents share the CPU). GPU figures: "
          "`CupNet throughput on <device>` (`benchmarks/throughput.py`). With 2 "
          "threads the rim networks' "
          "strips run one per core (`cupnet.parallel`), with the same results as on "
          "one. 'ONNX Runtime': the networks run by ONNX Runtime "
          "(`cupnet predict --runtime onnx`, `cupnet.runtime`; its U-Nets on one "
          "thread), the geometry as in PyTorch's rows.\n\n" + speed, args)


def accuracy_section(models: dict[str, CupNet], args: argparse.Namespace) -> None:
    """Score ``models`` (the first the shipped one) on fresh DRRs and images without a cup;
    writes the ``model_accuracy`` section and the shipped model's failure gallery."""
    model = next(iter(models.values()))
    eval_set = samples(args.eval_config, args.seed, args.images, args.sizes)
    no_cup_set = samples(args.no_cup_config, args.seed + 7, args.no_cup_images, args.sizes)
    header = ["model", *[f"MAE {n}" for n in NAMES], "detected", "false positives",
              f"cups found in {len(no_cup_set)} no-cup images"]
    table, spread = [], ""
    for name, net in models.items():
        cases: list = []
        res = accuracy(net, eval_set, cases)
        if net is model:
            failure_gallery(cases, args.gallery)
            spread = markdown_table(
                ["shipped model", *NAMES],
                [[stat, *[res[f"{key}_{n}"] for n in NAMES]]
                 for stat, key in (("mean", "mae"), ("median", "median"),
                                   ("90th percentile", "p90"), ("MAE of the cups not flagged "
                                                                "`check`", "unflagged_mae"))])
            spread += (f"\n\nThe shipped model "
                       f"{flag_summary(res, round(res['detected'] * res['cups']), net)}.")
        no_cup, no_cup_flagged = false_detections(net, no_cup_set)
        table.append([name, *[res[f"mae_{n}"] for n in NAMES], f"{100 * res['detected']:.1f} %",
                      with_flagged(res["false_positives"], res["false_positives_flagged"]),
                      with_flagged(no_cup, no_cup_flagged)])
        print(name, res)
    text = markdown_table(header, table)
    text += ("\n\nAbsolute errors of the shipped model's detected cups: a few gross failures "
             "dominate the means.\n\n" + spread)
    print(text)
    write("model_accuracy", "## CupNet accuracy\n\n"
          f"`python benchmarks/model.py --parts accuracy{runtime_flags(args)}"
          f"{preset_flags(args)}`: {args.images} fresh DRRs from "
          f"`{args.eval_config}` (CT background on every image) at "
          f"{', '.join(map(str, args.sizes))} px (seed {args.seed}), MAE over detected "
          "true cups "
          f"(deg, deg, mm, mm, mm); targets {TARGETS}; false positives: detections "
          "matching no true cup in those images; and the detections in "
          f"{len(no_cup_set)} images without a cup (`{args.no_cup_config}`), where "
          "each should say `no_cup` (of both, how many the model flags `check`; "
          "the others are mostly `error` rows, without a pose to doubt). The "
          "ablation (segmentation "
          "alone vs end to end, same set) and the training record are in "
          f"docs/training.md; the worst cases in {args.gallery.name}.\n\n" + text, args)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", default=str(DEFAULT_CHECKPOINT))
    parser.add_argument("--presets", nargs="*", default=list(SPEED_PRESETS),
                        choices=OPTIONS,
                        help="the shipped model's speed presets (and --blurred) to time and "
                             "score beside it")
    parser.add_argument("--ablation", nargs="*", default=[],
                        help="more checkpoints to compare on the same set, as NAME=PATH")
    parser.add_argument("--eval-config", default="configs/synth_eval.yaml")
    parser.add_argument("--speed-config", default="configs/synth_speed.yaml")
    parser.add_argument("--images", type=int, default=270)
    parser.add_argument("--no-cup-config", default="configs/synth_nocup.yaml")
    parser.add_argument("--no-cup-images", type=int, default=60)
    parser.add_argument("--sizes", type=int, nargs="+", default=[512, 768, 1024],
                        help="square sizes (px) of the accuracy images, in equal shares")
    parser.add_argument("--oblong", type=shape, nargs="*",
                        default=[(768, 512), (512, 768), (1024, 640), (1024, 768)],
                        help="oblong image shapes (WxH) to score the shipped model on too")
    parser.add_argument("--oblong-images", type=int, default=240)
    parser.add_argument("--small", type=int, nargs="*", default=[512, 384, 256, 192, 128],
                        help="square sides (px) to score the shipped model on (--parts small)")
    parser.add_argument("--small-images", type=int, default=30, help="images a small side")
    parser.add_argument("--large", type=int, nargs="*", default=[1536, 2048, 3072],
                        help="square sides (px) to score the shipped model on (--parts large)")
    parser.add_argument("--large-images", type=int, default=60, help="images a large side")
    parser.add_argument("--capture-images", type=int, default=60,
                        help="frames shown as screenshots (--parts captures)")
    parser.add_argument("--degraded-images", type=int, default=180,
                        help="images a degradation (--parts degraded)")
    parser.add_argument("--hardware-images", type=int, default=120,
                        help="images a kind of surgical hardware (--parts hardware)")
    parser.add_argument("--geometry-images", type=int, default=90,
                        help="images a way of giving the geometry (--parts geometry)")
    parser.add_argument("--seed", type=int, default=20_261_123)
    parser.add_argument("--fresh-seeds", type=int, nargs="+",
                        default=FRESH_SEEDS,
                        help="seeds of the fresh sets (default: seeds no setting was chosen "
                             "on; the section says which given seeds chose settings)")
    parser.add_argument("--fresh-images", type=int, default=180, help="images a fresh seed")
    parser.add_argument("--seed-presets", nargs="*", default=[], choices=OPTIONS,
                        help="speed presets (and --blurred) to score on the seed sets too, "
                             "beside the shipped model as it is (in each runtime)")
    parser.add_argument("--against", default='{"verify_gate": 1.0, "outline_settled": 0.05, '
                        '"search_screen": null}',
                        help="inference settings (JSON) to time the shipped model against, "
                             "in one process (--parts against); default: the nineteenth "
                             "session's")
    parser.add_argument("--gallery", help="where to write the model's worst cases "
                        "(default: docs/model_failures.png, or beside another checkpoint)")
    parser.add_argument("--doc", help="the markdown file the sections go to (default: "
                        "docs/benchmarks.md, or benchmarks.md beside another checkpoint)")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2],
                        help="torch intra-op threads to time with (accuracy uses the first)")
    parser.add_argument("--runtimes", nargs="+", default=["torch"], choices=RUNTIMES,
                        help="what runs the networks (cupnet predict --runtime); the first "
                             "model of the first is the shipped one of the gallery")
    parser.add_argument("--parts", nargs="+", default=["speed", "accuracy", "oblong", "fresh"],
                        choices=["speed", "accuracy", "oblong", *SEED_SECTIONS, "against",
                                 "small", "large", "captures", "degraded", "hardware",
                                 "geometry"],
                        help="the sections to measure; the others are left as they are "
                             "(speed alone: for a change that keeps every pose)")
    args = parser.parse_args()
    args.doc, args.gallery, args.header = output_paths(args.checkpoint, args.doc, args.gallery)

    def loaded(path: str, preset: str | None = None, runtime: str = "torch") -> CupNet:
        net = fold_batchnorm(load_model(path))  # as cupnet predict runs it
        if preset == BLURRED:
            net.config.blurred = True
        else:
            apply_speed_preset(net.config, preset)
        # one thread a U-Net call, as predict's default (the strips take the timed threads)
        return networks_in_onnx_runtime(net, threads=1) if runtime == "onnx" else net

    model = loaded(args.checkpoint)
    models = {}
    shipped_names = {runtime: ", ONNX Runtime" if runtime == "onnx" else ""
                     for runtime in args.runtimes}
    for runtime, suffix in shipped_names.items():
        models[f"shipped (end to end){suffix}"] = (model if runtime == "torch"
                                                   else loaded(args.checkpoint, None, runtime))
        models.update({f"shipped, --{preset}{suffix}": loaded(args.checkpoint, preset, runtime)
                       for preset in args.presets})
    timed = dict(models)  # the shipped model and its presets; the ablations are scored only
    for item in args.ablation:
        name, path = item.split("=", 1)
        models[name] = loaded(path)
    if "speed" in args.parts:
        speed_section(timed, args)
    torch.set_num_threads(args.threads[0])  # what accuracy is scored with
    if "accuracy" in args.parts:
        accuracy_section(models, args)
    shipped = {runtime: models[f"shipped (end to end){suffix}"]
               for runtime, suffix in shipped_names.items()}
    if "oblong" in args.parts and args.oblong and args.oblong_images:
        text = oblong_section(shipped, args)
        print(text)
        write("model_oblong", text, args)
    if "captures" in args.parts and args.capture_images:
        text = captures_section(next(iter(shipped.values())), args)
        print(text)
        write("model_captures", text, args)
    if "small" in args.parts and args.small:
        text = small_section(next(iter(shipped.values())), args)
        print(text)
        write("model_small", text, args)
    if "large" in args.parts and args.large:
        text = large_section(next(iter(shipped.values())), args)
        print(text)
        write("model_large", text, args)
    # By row name: the runtime, then ", --PRESET" where one applies (loaded above where
    # --presets timed it too).
    seed_models = dict(shipped)
    for runtime, suffix in shipped_names.items():
        for preset in args.seed_presets:
            name = f"shipped, --{preset}{suffix}"
            seed_models[f"{runtime}, --{preset}"] = (
                models[name] if name in models else loaded(args.checkpoint, preset, runtime))
    for part, (section, *_) in SEED_SECTIONS.items():
        if part in args.parts and args.fresh_images:
            text = fresh_seed_section(seed_models, args, part)
            print(text)
            write(section, text, args)
    if "degraded" in args.parts and args.degraded_images:
        text = degraded_section(seed_models, args)
        print(text)
        write("model_degraded", text, args)
    if "hardware" in args.parts and args.hardware_images:
        text = hardware_section(seed_models, args)
        print(text)
        write("model_hardware", text, args)
    if "geometry" in args.parts and args.geometry_images:
        text = geometry_section(seed_models, args)
        print(text)
        write("model_geometry", text, args)
    if "against" in args.parts:
        other = loaded(args.checkpoint, None, args.runtimes[0])
        for key, value in json.loads(args.against).items():
            setattr(other.config, key, value)
        text = against_section(next(iter(shipped.values())), other, args)
        print(text)
        write("model_against", text, args)


if __name__ == "__main__":
    main()
