"""``cupnet evaluate --pred results.csv --truth truth.csv --out DIR``: the paper's table, figures.

Predicted cups are matched to true cups image by image on their ellipse centres (minimum
total distance; a pair counts when the centres lie within the true ellipse's semi-major
axis). Over the matched cups: MAE, median and 95th percentile of each pose parameter
(inclination errors wrapped to (-90, 90]), of the in-plane translation error
``|(k, l)|`` and of the Hausdorff distance between the predicted and true rim ellipses
(pixels, both curves sampled densely); the detection rate, gross failures (an angle off by
more than 5 degrees), seconds per image, and the orthographic baseline (anteversion
``asin(b / a)`` and inclination from the same predicted ellipse) beside the perspective pose.

The true ellipse comes from truth.csv's ``ellipse_*`` columns, else from the true pose and
the geometry columns of truth.csv or ``--meta``.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment

from cupnet.geometry import Geometry
from cupnet.io.csvfile import csv_text
from cupnet.io.meta import GEOMETRY_KEYS, image_table, row_for_image
from cupnet.io.results import (
    ALT_COLUMNS,
    ELLIPSE_COLUMNS,
    POSE_COLUMNS,
    STATUS_RULE,
    is_status,
)
from cupnet.pose import ellipse_of_pose, orthographic_pose

# The columns results.csv and meta.csv are written with (the three required first).
POSE, ELLIPSE, GEOMETRY = POSE_COLUMNS, ELLIPSE_COLUMNS, GEOMETRY_KEYS
LABELS = {"anteversion_deg": "anteversion (deg)", "inclination_deg": "inclination (deg)",
          "k_mm": "k (mm)", "l_mm": "l (mm)", "kl_mm": "in-plane (k, l) distance (mm)",
          "h_mm": "h (mm)", "hausdorff_px": "Hausdorff (px)"}
# truth.csv of ``cupnet synth`` names the angles by their symbols.
TRUTH_ALIASES = {"theta_deg": "anteversion_deg", "phi_deg": "inclination_deg"}
GROSS_DEG = 5.0
CURVE_SAMPLES = 1440
FOUND = ("ok", "ambiguous")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--pred", required=True, type=Path, help="results.csv of cupnet predict")
    parser.add_argument("--truth", required=True, type=Path, help="truth.csv (e.g. cupnet synth)")
    parser.add_argument("--out", required=True, type=Path, help="folder for report and plots")
    parser.add_argument("--meta", type=Path,
                        help="meta.csv with the geometry, where truth.csv has no ellipse columns")


# -- loading ----------------------------------------------------------------------------------
def _number(value: str | None) -> float:
    try:
        return float(value) if value not in (None, "") else math.nan
    except ValueError:
        return math.nan


def read_rows(path: Path, required: tuple[str, ...],
              aliases: dict[str, str] | None = None) -> list[dict[str, str]]:
    """CSV rows as dicts, columns renamed by ``aliases``; a missing required column raises
    ``ValueError`` naming it."""
    aliases = aliases or {}
    with csv_text(path) as f:
        reader = csv.DictReader(f)
        columns = [aliases.get(c, c) for c in reader.fieldnames or []]
        missing = [c for c in required if c not in columns]
        if missing:
            raise ValueError(f"{path}: missing column(s) {missing}")
        return [{aliases.get(k, k): v for k, v in row.items()} for row in reader]


def _array(rows: list[dict[str, str]], columns: tuple[str, ...]) -> np.ndarray:
    return np.array([[_number(row.get(c)) for c in columns] for row in rows],
                    dtype=np.float64).reshape(len(rows), len(columns))


def true_ellipses(rows: list[dict[str, str]], meta: dict[str, dict[str, str]]) -> np.ndarray:
    """``(N, 5)`` true ellipses: the truth's columns, else projected from pose and geometry."""
    if rows and all(c in rows[0] for c in ELLIPSE):
        return _array(rows, ELLIPSE)
    meta_rows = image_table(meta)
    geometry_rows = [{**(row_for_image(meta_rows, r["image"]) or {}),
                      **{k: v for k, v in r.items() if k in GEOMETRY}} for r in rows]
    missing = [c for c in GEOMETRY[:3] if any(c not in g for g in geometry_rows)]
    if missing:
        raise ValueError(f"truth has no ellipse columns and no geometry {missing} to project the "
                         "true pose (give --meta meta.csv)")
    geo = _array(geometry_rows, GEOMETRY)
    if not np.isfinite(geo[:, 3:]).all():
        raise ValueError("truth needs ellipse columns or principal_u_px / principal_v_px")
    t = torch.as_tensor
    geometry = Geometry(t(geo[:, 0]), t(geo[:, 1]), t(geo[:, 3]), t(geo[:, 4]))
    return ellipse_of_pose(t(_array(rows, POSE)), t(geo[:, 2]), geometry).numpy()


# -- matching ---------------------------------------------------------------------------------
@dataclass
class Matched:
    """Matched cups (``M`` rows) and the counts around them.

    Attributes:
        images: ``M`` image names.
        pred, true: ``(M, 5)`` poses (deg, deg, mm, mm, mm).
        pred_ellipse, true_ellipse: ``(M, 5)`` (cx, cy, a, b, alpha_deg) px.
        n_true: true cups; n_pred: predicted cups (less those that stand for truth rows
            left out); n_images: predicted images.
        seconds: seconds per predicted image (its first row).
        errors: images whose prediction is an error row.
        ambiguous: matched cups the solver flagged ambiguous.
        unpredicted: truth images without any prediction row (left out).
        check: ``(M,)`` matched cups the model flagged to check by eye (``check`` = 1).
        alt_pred: ``(M, 5)`` the second pose of each matched ambiguous cup, NaN for others.
        untrue: predicted images without a truth row (scored as images with no cup).
        incomplete_truth: truth rows without a whole pose and ellipse (left out).
    """

    images: list[str]
    pred: np.ndarray
    true: np.ndarray
    pred_ellipse: np.ndarray
    true_ellipse: np.ndarray
    n_true: int
    n_pred: int
    n_images: int
    seconds: np.ndarray
    errors: int
    ambiguous: int
    unpredicted: int
    check: np.ndarray
    alt_pred: np.ndarray
    untrue: int
    incomplete_truth: int


def _duplicates(rows: list[dict[str, str]], columns: tuple[str, ...], what: str) -> None:
    """A ValueError naming the first row of ``rows`` that repeats another on ``columns``
    (two runs' results appended, a truth file pasted twice): each would count again."""
    seen: set[tuple[str, ...]] = set()
    for row in rows:
        key = tuple(row.get(c) or "" for c in columns)
        if key in seen:
            cells = ", ".join(f"{c} {v}" for c, v in zip(columns[1:], key[1:], strict=True))
            raise ValueError(f"two {what} rows alike for image {row['image']} ({cells}): "
                             "two files appended? Give each cup once")
        seen.add(key)


def _truth_names(pred_rows: list[dict[str, str]], truth_names: set[str]
                 ) -> list[dict[str, str]]:
    """``pred_rows`` named as the truth names their images: a prediction of a run on the
    parent folder (``images/a.png``) or a truth keyed by paths finds its image by file name
    where that name is one image's alone (:meth:`cupnet.io.meta.ImageTable.key_for`)."""
    named, truth = {}, image_table(truth_names)
    for image in {row["image"] for row in pred_rows}:
        named[image] = truth.key_for(image) or image
    # Two predicted images that find one truth image keep their own names.
    found = Counter(named.values())
    return [row if found[named[row["image"]]] > 1 else {**row, "image": named[row["image"]]}
            for row in pred_rows]


# Cost of a pair too far apart to match: above any sum of real distances in pixels.
_UNMATCHABLE = 1e12


def match_cups(pred_rows: list[dict[str, str]], truth_rows: list[dict[str, str]],
               truth_ellipse: np.ndarray) -> Matched:
    """Pairs of predicted and true cups per image by ellipse centre (Hungarian assignment).

    Only images with a prediction row count; truth images without one are counted apart
    (``unpredicted``), so evaluating part of a set does not read as missed cups.
    """
    # The centre too: a results.csv of another tool may have no cup column.
    _duplicates(pred_rows, ("image", "cup", *ELLIPSE[:2]), "prediction")
    _duplicates(truth_rows, ("image", *POSE), "truth")
    pred_rows = _truth_names(pred_rows, {r["image"] for r in truth_rows})
    pred_by_image: dict[str, list[dict[str, str]]] = {}
    first_rows: dict[str, dict[str, str]] = {}
    for row in pred_rows:
        first_rows.setdefault(row["image"], row)
    predicted = np.array([r["image"] in first_rows for r in truth_rows], dtype=bool)
    complete = np.isfinite(_array(truth_rows, POSE)).all(1) & np.isfinite(truth_ellipse).all(1)
    usable = complete & predicted
    truth_rows_ok = np.flatnonzero(usable).tolist()
    for row in pred_rows:
        if row["status"] in FOUND and np.isfinite(_array([row], ELLIPSE[:2])).all():
            pred_by_image.setdefault(row["image"], []).append(row)
    truth_by_image: dict[str, list[int]] = {}
    for i in truth_rows_ok:
        truth_by_image.setdefault(truth_rows[i]["image"], []).append(i)
    pairs: list[tuple[dict[str, str], int]] = []
    for image, indices in truth_by_image.items():
        candidates = pred_by_image.get(image, [])
        if not candidates:
            continue
        centres = _array(candidates, ELLIPSE[:2])
        true_centres = truth_ellipse[indices, :2]
        distance = np.linalg.norm(centres[:, None] - true_centres[None], axis=-1)
        # Pairs farther apart than the true semi-major axis are no match, so they must not
        # take part in the assignment: a false cup far off had outbid a found one, whose
        # sum of distances came out higher, and both pairs were then dropped.
        within = distance <= truth_ellipse[indices, 2][None]
        cost = np.where(within, distance, _UNMATCHABLE)
        for p, t in zip(*linear_sum_assignment(cost), strict=True):
            if within[p, t]:
                pairs.append((candidates[p], indices[t]))
    # A cup whose truth row is left out (no whole pose) is no false positive when found: an
    # image's predictions left unpaired are discounted up to its left-out truth rows.
    left_out = Counter(truth_rows[i]["image"] for i in np.flatnonzero(~complete & predicted))
    paired = Counter(p["image"] for p, _ in pairs)
    unscored = sum(min(count, len(pred_by_image.get(image, [])) - paired[image])
                   for image, count in left_out.items())
    # Images: those predicted (a truth without rows for an image means it has no cup).
    evaluated = list(first_rows.values())
    seconds = np.array([_number(r.get("seconds")) for r in evaluated])
    return Matched(
        images=[truth_rows[t]["image"] for _, t in pairs],
        pred=_array([p for p, _ in pairs], POSE),
        true=_array([truth_rows[t] for _, t in pairs], POSE),
        pred_ellipse=_array([p for p, _ in pairs], ELLIPSE),
        true_ellipse=truth_ellipse[[t for _, t in pairs]].reshape(len(pairs), 5),
        n_true=len(truth_rows_ok),
        n_pred=sum(len(v) for v in pred_by_image.values()) - unscored,
        n_images=len(evaluated),
        seconds=seconds[np.isfinite(seconds)],
        errors=sum(r["status"].startswith("error") for r in evaluated),
        unpredicted=len({r["image"] for r in truth_rows} - set(first_rows)),
        ambiguous=sum(p["status"] == "ambiguous" for p, _ in pairs),
        check=np.array([p.get("check") == "1" for p, _ in pairs], dtype=bool),
        alt_pred=_array([p if p["status"] == "ambiguous" else {} for p, _ in pairs],
                        ALT_COLUMNS),
        untrue=len(set(first_rows) - {r["image"] for r in truth_rows}),
        incomplete_truth=int(np.sum(~complete & predicted)),
    )


# -- metrics ----------------------------------------------------------------------------------
def wrap_inclination(diff: np.ndarray) -> np.ndarray:
    """Inclination differences into (-90, 90] degrees (phi is defined modulo 180)."""
    return 90.0 - np.mod(90.0 - diff, 180.0)


def pose_errors(pred: np.ndarray, true: np.ndarray) -> dict[str, np.ndarray]:
    """Signed errors per parameter ``(M,)`` plus the in-plane distance ``kl_mm``."""
    diff = pred - true
    diff[:, 1] = wrap_inclination(diff[:, 1])
    errors = {name: diff[:, i] for i, name in enumerate(POSE)}
    errors["kl_mm"] = np.hypot(diff[:, 2], diff[:, 3])
    return errors


def hausdorff_ellipses(first: np.ndarray, second: np.ndarray,
                       samples: int = CURVE_SAMPLES) -> np.ndarray:
    """Symmetric Hausdorff distance between ellipse curves, ``(M, 5)`` each -> ``(M,)`` px.

    Both curves are sampled at ``samples`` points; each point's distance to the other curve
    is the distance to its polyline (segments), so the result is exact to ``O(1/samples^2)``.
    """
    from cupnet.ellipse import ellipse_points

    t = torch.linspace(0, 2 * math.pi, samples + 1, dtype=torch.float64)
    curves = [ellipse_points(torch.as_tensor(e, dtype=torch.float64), t) for e in (first, second)]

    def directed(points: torch.Tensor, polyline: torch.Tensor) -> torch.Tensor:
        start, seg = polyline[:, :-1], polyline[:, 1:] - polyline[:, :-1]  # (M, S, 2)
        rel = points[:, :, None] - start[:, None]  # (M, P, S, 2)
        along = ((rel * seg[:, None]).sum(-1) / (seg**2).sum(-1).clamp_min(1e-300)[:, None])
        foot = start[:, None] + along.clamp(0, 1)[..., None] * seg[:, None]
        dist = torch.linalg.vector_norm(points[:, :, None] - foot, dim=-1).amin(-1)
        return dist.amax(-1)

    a, b = curves
    chunks = [torch.maximum(directed(a[i:i + 8, :-1], b[i:i + 8]),
                            directed(b[i:i + 8, :-1], a[i:i + 8]))
              for i in range(0, len(a), 8)]
    return torch.cat(chunks).numpy() if chunks else np.zeros(0)


def _stats(values: np.ndarray) -> dict[str, float | None]:
    values = np.abs(values[np.isfinite(values)])
    if values.size == 0:
        return {"mae": None, "median": None, "p95": None}
    return {"mae": float(values.mean()), "median": float(np.median(values)),
            "p95": float(np.percentile(values, 95))}


def compute_metrics(matched: Matched) -> dict:
    """The report's numbers as a JSON-ready dict."""
    errors = pose_errors(matched.pred, matched.true)
    ortho = orthographic_pose(torch.as_tensor(matched.pred_ellipse)).numpy().reshape(-1, 2)
    ortho_errors = {"anteversion_deg": ortho[:, 0] - matched.true[:, 0],
                    "inclination_deg": wrap_inclination(ortho[:, 1] - matched.true[:, 1])}
    hausdorff = hausdorff_ellipses(matched.pred_ellipse, matched.true_ellipse)
    angle_error = np.maximum(np.abs(errors["anteversion_deg"]), np.abs(errors["inclination_deg"]))
    gross = int(np.sum(~(angle_error <= GROSS_DEG)))  # NaN counts as a failure
    n = len(matched.images)
    rest = ~matched.check
    # The first pose of an ambiguous cup is scored; what its second pose would have given.
    alt_errors = pose_errors(matched.alt_pred, matched.true)
    alt_angle = np.maximum(np.abs(alt_errors["anteversion_deg"]),
                           np.abs(alt_errors["inclination_deg"]))
    return {
        "images": matched.n_images,
        "true_cups": matched.n_true,
        "predicted_cups": matched.n_pred,
        "matched_cups": n,
        "detection_rate": n / matched.n_true if matched.n_true else None,
        "false_positives": matched.n_pred - n,
        "error_images": matched.errors,
        "ambiguous_matched": matched.ambiguous,
        "ambiguous_second_nearer": int(np.sum(alt_angle < angle_error)),
        "gross_second_right": int(np.sum((alt_angle <= GROSS_DEG) & ~(angle_error <= GROSS_DEG))),
        "predicted_images_without_truth": matched.untrue,
        "truth_rows_incomplete": matched.incomplete_truth,
        "truth_images_not_predicted": matched.unpredicted,
        "gross_failures": gross,
        "gross_failure_rate": gross / n if n else None,
        "seconds_per_image": float(matched.seconds.mean()) if matched.seconds.size else None,
        "perspective": {name: _stats(values) for name, values in errors.items()}
        | {"hausdorff_px": _stats(hausdorff)},
        "orthographic": {name: _stats(values) for name, values in ortho_errors.items()},
        # What a user who checks the flagged cups by eye is left with.
        "check": {"flagged": int(matched.check.sum()),
                  "gross_flagged": int(np.sum(~(angle_error[matched.check] <= GROSS_DEG))),
                  "unflagged": {name: _stats(values[rest]) for name, values in errors.items()}},
    }


def evaluate_results(pred_csv: str | Path, truth_csv: str | Path,
                     meta_csv: str | Path | None = None) -> dict:
    """Metrics of a results.csv against a truth.csv (see :func:`compute_metrics`)."""
    return compute_metrics(_load(Path(pred_csv), Path(truth_csv),
                                 None if meta_csv is None else Path(meta_csv)))


def _load(pred_csv: Path, truth_csv: Path, meta_csv: Path | None) -> Matched:
    pred_rows = read_rows(pred_csv, ("image", "status", *POSE, *ELLIPSE[:2]))
    # Any other status had read as a missed cup without a word ('OK' from a spreadsheet).
    unknown = sorted({repr(r["status"]) for r in pred_rows if not is_status(r["status"])})
    if unknown:
        raise ValueError(f"{pred_csv}: unknown status value(s) {', '.join(unknown[:5])}: "
                         f"results.csv's status is {STATUS_RULE}")
    # A found cup without a whole pose had counted as matched and been left out of that
    # angle's MAE without a word.
    posed = [r for r in pred_rows if r["status"] in FOUND]
    partial = [r["image"] for r, finite in zip(posed, np.isfinite(_array(posed, POSE)).all(1),
                                               strict=True) if not finite]
    if partial:
        raise ValueError(f"{pred_csv}: {len(partial)} row(s) of status ok or ambiguous without "
                         f"a whole pose (first: {partial[0]}): each such row gives "
                         f"{', '.join(POSE)}")
    truth_rows = read_rows(truth_csv, ("image", *POSE), TRUTH_ALIASES)
    meta = ({r["image"]: r for r in read_rows(meta_csv, ("image",))}
            if meta_csv is not None else {})
    return match_cups(pred_rows, truth_rows, true_ellipses(truth_rows, meta))


# -- report -----------------------------------------------------------------------------------
def _fmt(value: float | None, digits: int = 3) -> str:
    return "-" if value is None else f"{value:.{digits}g}"


def metrics_table(metrics: dict) -> str:
    """The paper's table (markdown): error statistics beside the orthographic baseline."""
    lines = ["| parameter | MAE | median | p95 | orthographic MAE |", "|---|---|---|---|---|"]
    for name, label in LABELS.items():
        stats = metrics["perspective"][name]
        ortho = metrics["orthographic"].get(name, {}).get("mae")
        lines.append(f"| {label} | {_fmt(stats['mae'])} | {_fmt(stats['median'])} | "
                     f"{_fmt(stats['p95'])} | {_fmt(ortho)} |")
    rate = metrics["detection_rate"]
    gross = metrics["gross_failure_rate"]
    lines += [
        "",
        "| images | true cups | detection rate | false positives | gross failures (> 5 deg) "
        "| error images | seconds / image |",
        "|---|---|---|---|---|---|---|",
        f"| {metrics['images']} | {metrics['true_cups']} | "
        f"{'-' if rate is None else f'{100 * rate:.1f} %'} | {metrics['false_positives']} | "
        f"{metrics['gross_failures']} ({'-' if gross is None else f'{100 * gross:.1f} %'}) | "
        f"{metrics['error_images']} | {_fmt(metrics['seconds_per_image'])} |",
        "",
        "Seconds / image: the mean of results.csv's `seconds`, each image's share of its "
        "batch's time; `cupnet predict` runs two batches at once, so this exceeds its run's "
        "wall time per image, which its summary prints.",
    ]
    check = metrics["check"]
    if check["flagged"]:
        rest = check["unflagged"]
        lines.append(
            f"\n{check['flagged']} matched cup(s) flagged `check` by the model, "
            f"{check['gross_flagged']} of them gross failures; MAE of the others: "
            + ", ".join(f"{label} {_fmt(rest[name]['mae'])}" for name, label in LABELS.items()
                        if name in rest) + ".")
    if metrics["ambiguous_matched"]:
        lines.append(f"\n{metrics['ambiguous_matched']} matched cup(s) ambiguous (both circle "
                     "poses in range): their first pose is scored; the second lies nearer the "
                     f"truth for {metrics['ambiguous_second_nearer']}, and is right for "
                     f"{metrics['gross_second_right']} of the gross failures.")
    if metrics["truth_images_not_predicted"]:
        lines.append(f"\n{metrics['truth_images_not_predicted']} truth image(s) without a "
                     "prediction row were left out.")
    untrue = metrics["predicted_images_without_truth"]
    if untrue > metrics["images"] / 2:  # a truth omits the images without a cup, not most
        lines.append(f"\n{untrue} of the {metrics['images']} predicted images have no truth "
                     "row, so count as images without a cup (their cups as false positives): "
                     "do the two files name the images alike?")
    elif untrue:
        lines.append(f"\n{untrue} predicted image(s) have no truth row and count as images "
                     "without a cup (a cup found there, as a false positive).")
    if metrics["truth_rows_incomplete"]:
        lines.append(f"\n{metrics['truth_rows_incomplete']} truth row(s) without a whole pose "
                     "(or ellipse) were left out.")
    return "\n".join(lines)


def plot_figures(matched: Matched, out: Path) -> list[Path]:
    """Error vs distance from the image centre (perspective vs orthographic) and predicted vs
    true scatter per parameter, as PNG files under ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    errors = pose_errors(matched.pred, matched.true)
    ortho = orthographic_pose(torch.as_tensor(matched.pred_ellipse)).numpy().reshape(-1, 2)
    distance = np.hypot(matched.true[:, 2], matched.true[:, 3])
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), constrained_layout=True)
    for ax, index, name in ((axes[0], 0, "anteversion"), (axes[1], 1, "inclination")):
        ortho_error = ortho[:, index] - matched.true[:, index]
        if index == 1:
            ortho_error = wrap_inclination(ortho_error)
        ax.scatter(distance, np.abs(ortho_error), s=10, c="tab:red", alpha=0.6,
                   label="orthographic")
        ax.scatter(distance, np.abs(errors[POSE[index]]), s=10, c="tab:blue", alpha=0.8,
                   label="perspective (cupnet)")
        ax.set(xlabel="distance of the cup from the image centre |(k, l)| (mm)",
               ylabel=f"|{name} error| (deg)", title=name)
        ax.set_ylim(bottom=0)
        ax.legend()
    distance_plot = out / "error_vs_distance.png"
    fig.savefig(distance_plot, dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, 5, figsize=(18, 3.8), constrained_layout=True)
    for ax, i, name in zip(axes, range(5), POSE, strict=True):
        true, pred = matched.true[:, i], matched.pred[:, i]
        ax.scatter(true, pred, s=10, alpha=0.7)
        finite = np.concatenate([true, pred])
        finite = finite[np.isfinite(finite)]
        if finite.size:
            lo, hi = finite.min(), finite.max()
            ax.plot([lo, hi], [lo, hi], "k--", lw=1)
        ax.set(xlabel=f"true {LABELS[name]}", ylabel=f"predicted {LABELS[name]}")
    scatter_plot = out / "predicted_vs_true.png"
    fig.savefig(scatter_plot, dpi=110)
    plt.close(fig)
    return [distance_plot, scatter_plot]


def write_report(metrics: dict, plots: list[Path], out: Path, pred: Path, truth: Path) -> Path:
    body = [
        "# cupnet evaluation",
        "",
        f"Predictions `{pred}` against truth `{truth}`; cups matched by ellipse centre. Errors "
        "over matched cups; orthographic baseline: anteversion asin(b/a) and inclination from "
        f"the same predicted ellipse. Gross failure: an angle off by more than {GROSS_DEG:g} deg.",
        "",
        metrics_table(metrics),
        "",
    ]
    body += [f"![{p.stem}]({p.relative_to(out).as_posix()})\n" for p in plots]
    report = out / "report.md"
    report.write_text("\n".join(body))
    return report


def run(args: argparse.Namespace) -> int:
    try:
        matched = _load(args.pred, args.truth, args.meta)
    except (FileNotFoundError, ValueError, KeyError) as exc:
        print(f"cupnet evaluate: error: {exc}", file=sys.stderr)
        return 2
    if args.out.exists() and not args.out.is_dir():
        print(f"cupnet evaluate: error: --out {args.out} is a file; give a folder",
              file=sys.stderr)
        return 2
    metrics = compute_metrics(matched)
    args.out.mkdir(parents=True, exist_ok=True)
    plots = plot_figures(matched, args.out / "plots")
    (args.out / "metrics.json").write_text(json.dumps(metrics, indent=1) + "\n")
    report = write_report(metrics, plots, args.out, args.pred, args.truth)
    print(metrics_table(metrics))
    print(f"\nreport: {report}\nplots: {', '.join(str(p) for p in plots)}")
    return 0
