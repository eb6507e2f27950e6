"""cupnet predict: every image gets its row, geometry precedence, resume, no overwrite."""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import signal
import subprocess
import sys
from collections.abc import Callable
from dataclasses import replace
from importlib import metadata
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from dicom_factory import write_dicom

import cupnet.predict as predict
from cupnet.cli import main
from cupnet.config import CupNetConfig
from cupnet.environment import processor
from cupnet.geometry import Geometry, pose_to_radians, project_rim
from cupnet.io.images import PATIENT_SPACING_SOURCE, Frame, ImageSource
from cupnet.io.meta import ASSUMED_DETECTOR_WIDTH_MM, resolve_geometry
from cupnet.io.results import POSE_COLUMNS, RESULT_COLUMNS, SD_COLUMNS, status_row
from cupnet.model import CupNet, save_model


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An untrained CupNet: the pipeline's bookkeeping does not depend on what it detects."""
    torch.manual_seed(0)
    return save_model(CupNet(), tmp_path_factory.mktemp("model") / "untrained.safetensors")


def noise_png(path: Path, dtype: type = np.uint16, size: int = 256) -> Path:
    rng = np.random.default_rng(len(path.name))
    cv2.imwrite(str(path), (rng.random((size, size)) * np.iinfo(dtype).max).astype(dtype))
    return path


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        assert reader.fieldnames == list(RESULT_COLUMNS)
        return list(reader)


def rows_by_image(rows: list[dict[str, str]]) -> dict[str, list[dict[str, str]]]:
    out: dict[str, list[dict[str, str]]] = {}
    for row in rows:
        out.setdefault(row["image"], []).append(row)
    return out


def test_every_image_gets_a_row_and_geometry_is_recorded(tmp_path: Path,
                                                         checkpoint: Path) -> None:
    images = tmp_path / "images"
    images.mkdir()
    noise_png(images / "a16.png")
    noise_png(images / "b8.png", np.uint8)
    write_dicom(images / "c.dcm", (np.random.default_rng(1).random((256, 256)) * 4000)
                .astype(np.uint16), DistanceSourceToDetector=1100.0,
                ImagerPixelSpacing=[0.2, 0.2])
    (images / "empty.png").write_bytes(b"")
    (images / "text.png").write_text("not an image")
    cv2.imwrite(str(images / "thumb.png"), np.full((200, 300), 128, np.uint8))
    data = (images / "a16.png").read_bytes()
    (images / "cut.png").write_bytes(data[: len(data) // 3])
    meta = tmp_path / "meta.csv"
    meta.write_text("image,sdd_mm,pixel_spacing_mm\na16.png,1000,0.25\nc.dcm,,0.3\n")
    out = tmp_path / "out"
    code = main(["predict", str(images), "--out", str(out), "--checkpoint", str(checkpoint),
                 "--meta", str(meta), "--cup-diameter", "52", "--sdd", "990", "--quiet",
                 "--save-masks"])
    assert code == 0
    # As readable as any file the user makes there (they were 0600: tempfile's own mode).
    (out / "mine.txt").write_text("")
    assert {(out / name).stat().st_mode & 0o777 for name in (
        "results.csv", "results.json", "review.html", "mine.txt")} == {
        (out / "mine.txt").stat().st_mode & 0o777}
    by_image = rows_by_image(read_csv(out / "results.csv"))
    assert set(by_image) == {"a16.png", "b8.png", "c.dcm", "empty.png", "text.png", "cut.png",
                             "thumb.png"}
    # Poses from a thumbnail would be far off (docs/training.md, item 41): an error, not cups.
    assert by_image["thumb.png"][0]["status"] == (
        "error: image too small for the model: 300 x 200 px (at least 256 px a side)")
    assert by_image["empty.png"][0]["status"] == "error: empty file (0 bytes)"
    assert "not a readable PNG" in by_image["text.png"][0]["status"]
    assert "corrupt or truncated PNG" in by_image["cut.png"][0]["status"]
    # b8.png has an SDD (flag) and a diameter but no pixel spacing anywhere: its row says so.
    (b8,) = by_image["b8.png"]
    assert b8["status"].startswith("error: missing pixel spacing (--pixel-spacing")
    assert "source-to-detector" not in b8["status"]
    # Read, and their geometry whole: the network's rows alone (an untrained network's cup
    # may have no pose), not a reading, geometry or detection error (no cup number).
    for name in ("a16.png", "c.dcm"):
        assert all(r["status"] in ("ok", "ambiguous", "no_cup") or (
            r["status"].startswith("error: no pose from the rim found: ") and r["cup"] != "")
            for r in by_image[name])
        assert float(by_image[name][0]["seconds"]) > 0
    document = json.loads((out / "results.json").read_text())
    records = {r["image"]: r for r in document["images"]}
    geometry = records["c.dcm"]["geometry"]
    # meta.csv wins over the flag and the tags; the flag wins over the tag.
    assert geometry["pixel_spacing_mm"] == {"value": 0.3, "source": "meta.csv"}
    assert geometry["sdd_mm"] == {"value": 990.0, "source": "command line"}
    assert geometry["principal_u_px"] == {"value": 127.5, "source": "image centre"}
    assert records["a16.png"]["geometry"]["sdd_mm"]["source"] == "meta.csv"
    assert document["model"]["checkpoint"] == str(checkpoint)
    software = document["software"]
    assert software["cupnet"] and software["cpu"] == processor()
    # The libraries whose kernels decide a few hard cups (docs/training.md, item 69).
    for library in ("onnxruntime", "opencv-python-headless", "numpy"):
        assert software[library] == metadata.version(library)
    assert document["summary"]["images"] == 7
    assert document["summary"]["errors"] == sum(
        row["status"].startswith("error: ") for rows in by_image.values() for row in rows)
    for name in ("a16.png", "c.dcm"):
        overlay = out / records[name]["overlay"]
        assert cv2.imread(str(overlay)).shape == (768, 768, 3)  # enlarged to stay readable
        for mask in records[name].get("masks", []):
            assert cv2.imread(str(out / mask), cv2.IMREAD_UNCHANGED).shape == (256, 256)


def test_the_summary_counts_rows_and_the_flags_read_back_on_resume() -> None:
    """Error rows are counted as rows, not as reasons (two files failing alike are two); a
    cup flagged in a row read back from results.csv (--resume where results.json is gone:
    every cell a string) stays flagged, as one just run (an int)."""
    empty = "error: empty file (0 bytes)"
    records = [{"image": f"e{i}.png", "rows": [{"status": empty}]} for i in range(2)]
    records += [{"image": "read_back.png", "rows": [
                    {"status": "ok", "check": "1", "seconds": "0.5"},
                    {"status": "ambiguous", "check": "0", "seconds": "0.5"}]},
                {"image": "run.png", "rows": [{"status": "ok", "check": 1, "seconds": 1.5}]}]
    summary = predict.summarise(records)
    assert summary["errors"] == 2 and summary["error_reasons"] == {empty: 2}
    assert (summary["cups"], summary["ok"], summary["ambiguous"], summary["check"]) == (3, 2, 1, 2)
    assert summary["images"] == 4 and summary["seconds_per_image"] == pytest.approx(0.5)


def test_the_printed_summary_counts_the_error_rows_past_its_commonest_reasons(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Reasons past the fifth had been left out without a word (8 error rows, 5 listed)."""
    records = [{"image": f"e{i}.png", "rows": [{"status": f"error: reason {i}"}]}
               for i in range(8)]
    records.append({"image": "e8.png", "rows": [{"status": "error: reason 0"}]})
    predict._print_summary(predict.summarise(records), tmp_path, False, 1.0, False, {})
    lines = capsys.readouterr().out.splitlines()
    assert lines[1] == "  2 x error: reason 0"
    assert len([line for line in lines if " x error: " in line]) == predict.SUMMARY_REASONS
    assert ("  3 error row(s) more, for 3 other reason(s): the status column of results.csv"
            in lines)


def test_geometry_precedence_and_assumptions() -> None:
    tags = {"sdd_mm": 1200.0, "pixel_spacing_mm": 0.15}
    tags_only = resolve_geometry((100, 200), {}, {}, tags=tags)
    assert tags_only.missing == ["cup_diameter_mm"]
    assert tags_only.values["sdd_mm"] == 1200.0 and tags_only.sources["sdd_mm"] == "DICOM tags"
    assert (tags_only.values["principal_u_px"], tags_only.values["principal_v_px"]) == (99.5, 49.5)
    flags = {"sdd_mm": 1000.0, "cup_diameter_mm": 50.0, "principal_u_px": 10.0,
             "principal_v_px": 20.0}
    explicit = resolve_geometry((100, 200), {"sdd_mm": 900.0}, flags, tags=tags,
                                file_values={"pixel_spacing_mm": 0.3})
    assert explicit.missing == []
    assert explicit.values["sdd_mm"] == 900.0 and explicit.sources["sdd_mm"] == "meta.csv"
    assert explicit.values["pixel_spacing_mm"] == 0.15  # the tags before the landmark file
    assert explicit.values["principal_u_px"] == 10.0
    assumed = resolve_geometry((100, 200), {}, {}, assume_defaults=True)
    assert assumed.missing == []
    assert assumed.values["pixel_spacing_mm"] == pytest.approx(ASSUMED_DETECTOR_WIDTH_MM / 200)
    assert set(assumed.sources.values()) == {"assumed", "image centre"}
    missing = resolve_geometry((100, 200), {}, {})
    message = missing.error({"pixel_spacing_mm": "DICOM PixelSpacing is not square"})
    assert "source-to-detector distance (--sdd" in message and "not square" in message
    assert message.endswith("; or use --assume-defaults")
    # No image size (a landmark file without it): no centre, no spacing to assume, no hint.
    sizeless = resolve_geometry(None, {}, {}, assume_defaults=True)
    assert sizeless.missing == ["pixel_spacing_mm", "principal_u_px", "principal_v_px"]
    assert sizeless.error() == (
        "error: missing pixel spacing (--pixel-spacing or meta.csv pixel_spacing_mm), "
        "principal point (--principal-point or meta.csv principal_u_px, principal_v_px; no "
        "image size to take its centre from: give --image-size W H)")
    # A value no geometry has is its image's error row before the networks run (the
    # solver had said so after them, as "no pose from the rim found").
    bad = resolve_geometry((100, 200), {"sdd_mm": 0.0, "cup_diameter_mm": math.nan,
                                        "principal_u_px": math.inf}, flags)
    assert not bad.complete and bad.missing == ["pixel_spacing_mm"]  # unusable said first
    assert bad.error() == ("error: sdd_mm from meta.csv must be a positive number, got 0.0; "
                           "cup_diameter_mm from meta.csv must be a positive number, got nan; "
                           "principal_u_px from meta.csv must be a number, got inf")
    assert explicit.complete and assumed.complete and not missing.complete
    # Only the principal point missing: --assume-defaults would not give it, so no hint.
    centreless = resolve_geometry(None, {}, {"sdd_mm": 1000.0, "cup_diameter_mm": 50.0,
                                             "pixel_spacing_mm": 0.3})
    assert centreless.missing == ["principal_u_px", "principal_v_px"]
    assert not centreless.error().endswith("--assume-defaults")


def test_no_overwrite_without_flag(tmp_path: Path, blind_checkpoint: Path,
                                   capsys: pytest.CaptureFixture) -> None:
    image = noise_png(tmp_path / "a.png")
    out = tmp_path / "out"
    common = [str(image), "--out", str(out), "--checkpoint", str(blind_checkpoint), "--sdd", "1000",
              "--pixel-spacing", "0.3", "--cup-diameter", "52", "--quiet", "--no-overlays"]
    assert main(["predict", *common]) == 0
    # A user's note in it, which no run writes: a refused run leaves it, --overwrite not.
    edited = (out / "results.csv").read_bytes() + b"a user's note\n"
    (out / "results.csv").write_bytes(edited)
    assert main(["predict", *common, "--sdd", "900"]) == 2
    assert "already holds results.csv" in capsys.readouterr().err
    assert (out / "results.csv").read_bytes() == edited
    assert main(["predict", *common, "--resume", "--overwrite"]) == 2
    assert (out / "results.csv").read_bytes() == edited
    assert main(["predict", *common, "--overwrite"]) == 0
    assert b"a user's note" not in (out / "results.csv").read_bytes()
    assert not (out / "overlays").exists()


def test_overwrite_removes_the_overlays_of_the_run_it_replaces(tmp_path: Path,
                                                              blind_checkpoint: Path) -> None:
    """Only the files the previous results.json lists, under overlays/ (they had stayed)."""
    images = tmp_path / "images"
    images.mkdir()
    for name in ("a.png", "b.png"):
        noise_png(images / name)
    out = tmp_path / "out"
    common = ["--out", str(out), "--checkpoint", str(blind_checkpoint), "--assume-defaults",
              "--quiet"]
    assert main(["predict", str(images), *common]) == 0
    (out / "overlays" / "mine.png").write_bytes(b"a user's file")
    (images / "b.png").unlink()
    assert main(["predict", str(images), *common, "--overwrite"]) == 0
    assert sorted(p.name for p in (out / "overlays").iterdir()) == ["a.png.png", "mine.png"]


def five_images_in_batches_of_two(tmp_path: Path, checkpoint: Path) -> tuple[Path, list[str]]:
    """``cupnet predict``'s arguments for five noise images, two a batch; and its --out."""
    images = tmp_path / "images"
    images.mkdir()
    for i in range(5):
        noise_png(images / f"im{i}.png")
    out = tmp_path / "out"
    return out, ["predict", str(images), "--out", str(out), "--checkpoint", str(checkpoint),
                 "--sdd", "1000", "--pixel-spacing", "0.3", "--cup-diameter", "52", "--quiet",
                 "--batch-size", "2", "--no-overlays"]


def interrupt_the_batch_of(name: str, monkeypatch: pytest.MonkeyPatch) -> Callable[[], None]:
    """Ctrl-C while the network runs on the batch holding image ``name``, from now until the
    returned function is called. (By name, not by call: two batches run at once, so the
    second call may be either.)"""
    real = predict.NetworkDetector.__call__

    def interrupted(self, frames, *args):
        if any(frame.name == name for frame in frames):
            raise KeyboardInterrupt
        return real(self, frames, *args)

    monkeypatch.setattr(predict.NetworkDetector, "__call__", interrupted)
    return lambda: monkeypatch.setattr(predict.NetworkDetector, "__call__", real)


def test_resume_after_interrupted_run(tmp_path: Path, blind_checkpoint: Path,
                                      monkeypatch: pytest.MonkeyPatch) -> None:
    out, args = five_images_in_batches_of_two(tmp_path, blind_checkpoint)
    restore = interrupt_the_batch_of("im2.png", monkeypatch)
    assert main(args) == 130
    first = rows_by_image(read_csv(out / "results.csv"))
    assert set(first) == {"im0.png", "im1.png"}
    restore()
    assert main(args) == 2  # existing results: neither resumed nor overwritten silently
    assert main([*args, "--resume"]) == 0
    final = rows_by_image(read_csv(out / "results.csv"))
    assert set(final) == {f"im{i}.png" for i in range(5)}
    assert final["im0.png"] == first["im0.png"]  # kept, not recomputed
    document = json.loads((out / "results.json").read_text())
    assert [r["image"] for r in document["images"]] == [f"im{i}.png" for i in range(5)]


# Settings a resume refuses to change, and how it names each change. Each geometry flag
# alone: a resume with another had mixed two geometries' poses.
REFUSED_CHANGES = [
    (["--fastest", "--rotate", "90"],
     "--fast / --fastest: not given -> fastest; --rotate: 0 -> 90"),
    (["--pixel-spacing", "0.25"], "--pixel-spacing: 0.3 -> 0.25"),
    (["--sdd", "900"], "--sdd: 1000.0 -> 900.0"),
    (["--cup-diameter", "50"], "--cup-diameter: 52.0 -> 50.0"),
    (["--principal-point", "100", "120"], "--principal-point: not given -> [100.0, 120.0]"),
    (["--assume-defaults"], "--assume-defaults: not given -> True"),
    (["--check-doubt", "0.5"], "--check-doubt: not given -> 0.5"),
    (["--reduce-above", "0"], "--reduce-above: not given -> 0"),
]


def test_resume_refuses_other_settings_than_the_run_it_resumes(
        tmp_path: Path, blind_checkpoint: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture) -> None:
    """A resume with --fastest of a default run had mixed the two runs' rows under the later
    settings alone; settings that change no row (batch size, threads) may change, and a
    meta file spelt otherwise is the same file."""
    out, args = five_images_in_batches_of_two(tmp_path, blind_checkpoint)
    restore = interrupt_the_batch_of("im2.png", monkeypatch)
    (tmp_path / "meta.csv").write_text("image,sdd_mm\nim0.png,1000\n")
    assert main([*args, "--meta", str(tmp_path / "meta.csv")]) == 130
    restore()
    for changes, named in REFUSED_CHANGES:
        capsys.readouterr()
        assert main([*args, "--meta", str(tmp_path / "meta.csv"), "--resume", *changes]) == 2
        err = capsys.readouterr().err
        assert f"--resume with other settings than the run in {out} ({named}): " in err
        assert len(rows_by_image(read_csv(out / "results.csv"))) == 2  # left as it was
    # The meta file edited in place: the images still to run would take other geometry.
    (tmp_path / "meta.csv").write_text("image,sdd_mm\nim0.png,1000\nim3.png,900\n")
    assert main([*args, "--meta", str(tmp_path / "meta.csv"), "--resume"]) == 2
    assert f"the run in {out} (--meta: other contents)" in capsys.readouterr().err
    (tmp_path / "meta.csv").write_text("image,sdd_mm\nim0.png,1000\n")
    monkeypatch.chdir(tmp_path)
    assert main([*args, "--meta", "./meta.csv", "--resume", "--batch-size", "3"]) == 0
    assert len(rows_by_image(read_csv(out / "results.csv"))) == 5


@pytest.mark.parametrize("cut", [",1", ",1,n"])
def test_resume_refuses_a_results_csv_cut_short_mid_row(
        tmp_path: Path, blind_checkpoint: Path, capsys: pytest.CaptureFixture,
        cut: str) -> None:
    """A copy cut short mid-row (results.json not copied) had been resumed from: a status
    cut to 'n' was kept and written back, and a row without one ended the run in a
    traceback with the new images' rows lost. It is refused before any image, naming the
    line, and the file is left as it was."""
    (tmp_path / "in").mkdir()
    for name in ("a.png", "b.png"):
        noise_png(tmp_path / "in" / name)
    out = tmp_path / "out"
    args = ["predict", str(tmp_path / "in"), "--out", str(out), "--checkpoint",
            str(blind_checkpoint), "--assume-defaults", "--quiet", "--no-overlays"]
    assert main(args) == 0
    text = (out / "results.csv").read_text()
    cut_short = text[:text.index("b.png") + len("b.png")] + cut
    (out / "results.csv").write_text(cut_short)
    (out / "results.json").unlink()
    noise_png(tmp_path / "in" / "c.png")
    assert main([*args, "--resume"]) == 2
    assert (f"cannot resume: {out / 'results.csv'}, line 3: status "
            f"{'n' if cut.endswith('n') else None!r} is none of ok, ambiguous, no_cup or "
            "error: <reason> (a row cut short?)") in capsys.readouterr().err
    assert (out / "results.csv").read_text() == cut_short


def test_resume_takes_a_renamed_file_as_done(tmp_path: Path, blind_checkpoint: Path) -> None:
    """A second folder with a file of the first's name, added on --resume: both are then
    named by their paths, and the first's earlier record takes its new name (found by its
    file's path), where the file had been run again and counted twice, under both names."""
    for folder in ("d1", "d2"):
        (tmp_path / folder).mkdir()
        noise_png(tmp_path / folder / "a.png", size=256)
    noise_png(tmp_path / "d1" / "b.png", size=256)
    out = tmp_path / "out"
    args = ["predict", str(tmp_path / "d1"), "--out", str(out), "--checkpoint",
            str(blind_checkpoint), "--assume-defaults", "--quiet", "--no-overlays"]
    assert main(args) == 0
    before = rows_by_image(read_csv(out / "results.csv"))
    assert main([*args[:2], str(tmp_path / "d2"), *args[2:], "--resume"]) == 0
    after = rows_by_image(read_csv(out / "results.csv"))
    first, second = (f"{tmp_path.as_posix()}/{d}/a.png" for d in ("d1", "d2"))
    assert list(after) == [first, "b.png", second]  # in input order, as a whole run's
    assert [{**row, "image": "a.png"} for row in after[first]] == before["a.png"]  # not rerun
    document = json.loads((out / "results.json").read_text())
    assert document["summary"]["images"] == 3


def test_sigterm_ends_a_run_as_ctrl_c_does(tmp_path: Path, blind_checkpoint: Path,
                                           monkeypatch: pytest.MonkeyPatch,
                                           capsys: pytest.CaptureFixture) -> None:
    """A scheduler's time limit (SIGTERM) had ended the run without its last rows, its
    summary or the hint to resume."""
    assert signal.SIGTERM in predict.STOPPING_SIGNALS  # (else the signal below ends pytest)
    out, args = five_images_in_batches_of_two(tmp_path, blind_checkpoint)
    real = predict.NetworkDetector.__call__
    calls = []

    def terminated_on_third_batch(self, *args):  # the first is written by then
        calls.append(args)
        if len(calls) == 3:
            os.kill(os.getpid(), signal.SIGTERM)
        return real(self, *args)

    monkeypatch.setattr(predict.NetworkDetector, "__call__", terminated_on_third_batch)
    assert main(args) == 128 + signal.SIGTERM
    printed = capsys.readouterr()
    assert "interrupted" in printed.out and "--resume" in printed.out + printed.err
    assert {"im0.png", "im1.png"} <= set(rows_by_image(read_csv(out / "results.csv")))
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # restored after the run


@pytest.mark.parametrize("status", [0, 128 + signal.SIGTERM])
def test_the_command_exits_at_once_when_stopped(status: int) -> None:
    """A stopped run's detection threads, still on the batches in flight, had held the
    installed command's exit for seconds (past `docker stop`'s grace): a thread that never
    ends stands in for them. A run that finished waits for its threads as before."""
    script = (
        "import threading, cupnet.cli as cli\n"
        "stop = threading.Event()\n"
        "threading.Thread(target=stop.wait, daemon=False).start()\n"
        "def main():\n    print('written before the stop')\n"
        f"    if {status} == 0: stop.set()\n    return {status}\n"
        "cli.main = main\n"
        "cli.console()\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == status, done.stderr
    assert done.stdout == "written before the stop\n"  # flushed before the exit


@pytest.mark.parametrize(("error", "status"), [
    (IndexError("an odd image's bug"), "IndexError: an odd image's bug"),  # unforeseen: typed
    # Foreseen (a check's own message), one line of it: torch's add a C++ trace below.
    (RuntimeError("the rim is empty\nException raised from ... (most recent call first)"),
     "the rim is empty"),
])
def test_a_detection_that_fails_on_one_image_is_its_row_alone(
        tmp_path: Path, blind_checkpoint: Path, monkeypatch: pytest.MonkeyPatch,
        error: Exception, status: str) -> None:
    images = tmp_path / "images"
    images.mkdir()
    for i in range(3):
        noise_png(images / f"im{i}.png")
    real = predict.NetworkDetector.__call__

    def failing_on_im1(self, frames, geometries):
        if any(frame.name == "im1.png" for frame in frames):
            raise error
        return real(self, frames, geometries)

    monkeypatch.setattr(predict.NetworkDetector, "__call__", failing_on_im1)
    out = tmp_path / "out"
    assert main(["predict", str(images), "--out", str(out), "--checkpoint",
                 str(blind_checkpoint), "--sdd", "1000", "--pixel-spacing", "0.3",
                 "--cup-diameter", "52", "--quiet", "--no-overlays"]) == 0
    by_image = rows_by_image(read_csv(out / "results.csv"))
    assert [row["status"] for row in by_image["im1.png"]] == [
        f"error: detection failed ({status})"]
    for name in ("im0.png", "im2.png"):
        assert not by_image[name][0]["status"].startswith("error"), by_image[name]


def test_a_batch_shares_its_network_time_among_the_images_it_ran() -> None:
    """Each image's seconds add its share of its batch's detection time: the batch's over
    the images the network ran on, not over those that failed before it (a read error's row
    keeps its reading time alone)."""
    geometry = resolve_geometry((256, 256), {}, {"sdd_mm": 1000.0, "pixel_spacing_mm": 0.3,
                                                 "cup_diameter_mm": 52.0})
    frames = [Frame(f"im{i}.png", ImageSource(Path(f"im{i}.png"), f"im{i}.png"),
                    seconds=0.25) for i in range(3)]
    batch = predict.Batch(3, ["/im0.png", "/im1.png", "/im2.png"], records={0: {
        "image": "im0.png", "rows": [status_row("im0.png", "error: empty file (0 bytes)", 0.25)]}},
        ready=[(1, frames[1], geometry), (2, frames[2], geometry)])
    predictor = predict.Predictor(argparse.Namespace(), None, None, None)
    failed = "error: detection failed (the rim is empty)"
    records = predictor.finish(batch, [failed, failed], 6.0)
    assert [record["rows"][0]["seconds"] for record in records] == [0.25, 3.25, 3.25]


def test_rotate_turns_a_stored_turned_image_back_with_its_principal_point(
        tmp_path: Path) -> None:
    """An oblong DRR stored turned a quarter counterclockwise, with its principal point in
    the file's pixels: ``--rotate 90`` gives the upright file's poses and ellipses exactly."""
    from data_synth.config import SynthConfig
    from data_synth.dataset import synthesize

    config = SynthConfig(image_size=(640, 512), p_bilateral=0.0, p_no_cup=0.0)
    sample = synthesize(config, 5, 0)
    pixels = np.round(sample["image"][0].numpy() * 65535).astype(np.uint16)  # (512, 640)
    sdd, spacing = sample["geometry"][:2].tolist()
    u0, v0 = 300.0, 200.0  # off the centre, so a wrong turn of it shows
    width = pixels.shape[1]
    runs = {"upright": (pixels, [u0, v0], []),
            "stored": (np.rot90(pixels), [v0, width - 1 - u0], ["--rotate", "90"])}
    rows = {}
    for name, (image, principal, flags) in runs.items():
        (tmp_path / name).mkdir()
        cv2.imwrite(str(tmp_path / name / "hip.png"), np.ascontiguousarray(image))
        out = tmp_path / f"out_{name}"
        assert main(["predict", str(tmp_path / name), "--out", str(out), "--sdd", str(sdd),
                     "--pixel-spacing", str(spacing), "--principal-point",
                     *map(str, principal), "--cup-diameter",
                     str(float(sample["cup_diameter"][0])), "--quiet", *flags]) == 0
        rows[name] = read_csv(out / "results.csv")
    # One cup found, the same way in both (nearly edge-on, inclination near 90: its rim's
    # second pose lies in range too).
    assert [r["status"] for r in rows["upright"]] == [r["status"] for r in rows["stored"]]
    assert rows["upright"][0]["status"] in ("ok", "ambiguous") and len(rows["upright"]) == 1
    columns = [*POSE_COLUMNS, "ellipse_cx_px", "ellipse_cy_px", "ellipse_angle_deg"]
    assert ([[float(r[c]) for c in columns] for r in rows["stored"]]
            == [[float(r[c]) for c in columns] for r in rows["upright"]])
    assert abs(float(rows["upright"][0]["anteversion_deg"])
               - float(sample["pose"][0, 0])) < 2.0
    overlay = cv2.imread(str(tmp_path / "out_stored" / "overlays" / "hip.png.png"))
    assert overlay.shape[1] > overlay.shape[0]  # drawn on the upright, wide image
    document = json.loads((tmp_path / "out_stored" / "results.json").read_text())
    (record,) = document["images"]
    assert record["geometry"]["principal_u_px"]["source"].endswith(
        "turned 90 deg clockwise with the image")


def test_multiframe_dicom_gives_a_row_per_frame(tmp_path: Path, blind_checkpoint: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """Each frame its own row, from its own pixels; a run stopped after the first frame
    resumes with the others alone: the file is not done, but its first frame is (it had
    been read and run again, its row replaced)."""
    frames = (np.random.default_rng(2).random((3, 256, 256)) * 4000).astype(np.uint16)
    path = write_dicom(tmp_path / "run.dcm", frames, DistanceSourceToDetector=1000.0,
                       ImagerPixelSpacing=[0.3, 0.3])
    out = tmp_path / "out"
    args = ["predict", str(path), "--out", str(out), "--checkpoint", str(blind_checkpoint),
            "--cup-diameter", "52", "--quiet", "--batch-size", "1"]
    restore = interrupt_the_batch_of("run.dcm#2", monkeypatch)
    assert main(args) == 130
    first = rows_by_image(read_csv(out / "results.csv"))
    assert list(first) == ["run.dcm#1"]
    restore()
    seen: dict[str, np.ndarray] = {}
    real = predict.NetworkDetector.__call__

    def seeing(self, frames, geometries):
        seen.update((frame.name, frame.image) for frame in frames)
        return real(self, frames, geometries)

    monkeypatch.setattr(predict.NetworkDetector, "__call__", seeing)
    assert main([*args, "--resume"]) == 0
    assert sorted(seen) == ["run.dcm#2", "run.dcm#3"]
    for name, stored in zip(("run.dcm#2", "run.dcm#3"), frames[1:], strict=True):
        np.testing.assert_allclose(seen[name], (stored - stored.min()) / np.ptp(stored),
                                   atol=1e-6)
    by_image = rows_by_image(read_csv(out / "results.csv"))
    assert list(by_image) == ["run.dcm#1", "run.dcm#2", "run.dcm#3"]
    assert by_image["run.dcm#1"] == first["run.dcm#1"]  # kept, not recomputed
    assert (out / "overlays" / "run.dcm_frame2.png").exists()


def test_folder_without_images_and_bad_checkpoint(tmp_path: Path, capsys: pytest.CaptureFixture,
                                                  checkpoint: Path) -> None:
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("no images here")
    assert main(["predict", str(tmp_path / "empty"), "--out", str(tmp_path / "out")]) == 2
    assert "no images found in" in capsys.readouterr().err
    noise_png(tmp_path / "a.png")
    missing = tmp_path / "missing.safetensors"
    assert main(["predict", str(tmp_path / "a.png"), "--out", str(tmp_path / "o2"),
                 "--checkpoint", str(missing)]) == 2
    assert "checkpoint not found" in capsys.readouterr().err
    assert main(["predict", str(tmp_path / "a.png"), "--out", str(tmp_path / "o3"),
                 "--sdd", "0"]) == 2
    assert "--sdd must be a positive number of mm, got 0.0" in capsys.readouterr().err
    assert main(["predict", str(tmp_path / "a.png"), "--out", str(tmp_path / "o5"),
                 "--reduce-above", "300"]) == 2
    assert "--reduce-above must be 0 (never) or at least 512 px" in capsys.readouterr().err
    # Settings outside their ranges, NaN among them, had run (every image no_cup at a
    # --min-score of 2, a --check-doubt of nan never flagging).
    for flags, message in ((["--min-score", "2"], "--min-score must be a probability in "
                            "[0, 1], got 2.0"),
                           (["--min-score", "nan"], "--min-score must be a probability"),
                           (["--check-doubt", "nan"], "--check-doubt must be a number >= 0, "
                            "got nan"),
                           (["--denoise-above", "-0.01"], "--denoise-above must be a number"),
                           (["--enlarge-below", "-5"], "--enlarge-below must be a number"),
                           (["--reduce-above", "-5"], "--reduce-above must be a number"),
                           (["--principal-point", "inf", "250"],
                            "--principal-point must be two finite pixel positions")):
        assert main(["predict", str(tmp_path / "a.png"), "--out", str(tmp_path / "o6"),
                     *flags]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "o6").exists()
    assert not (tmp_path / "o3" / "results.csv").exists()
    # A --meta that cannot be read (here a folder) is named, not a traceback.
    assert main(["predict", str(tmp_path / "a.png"), "--out", str(tmp_path / "o4"),
                 "--meta", str(tmp_path / "empty")]) == 2
    assert "Is a directory" in capsys.readouterr().err


# Overlays over 768 px draw 2 px wide lines: the tolerance is half the width + 1 px.
@pytest.mark.parametrize(("shape", "scale", "tol"), [((600, 900), 1.0, 2.0),
                                                     ((1024, 2048), 0.5, 2.0),
                                                     ((200, 256), 3.0, 2.0)])
def test_overlay_ellipse_follows_the_conventions(shape: tuple[int, int], scale: float,
                                                 tol: float) -> None:
    """OpenCV draws the rim where cupnet.ellipse.ellipse_points puts it (alpha from +u to +v)."""
    from cupnet.ellipse import ellipse_points
    from cupnet.overlay import CupDrawing, draw_overlay

    # The same place on the overlay in both cases: original pixels scaled by 1 / scale.
    ellipse = np.array([370.0, 220.0, 60.0, 25.0, 30.0])
    ellipse[:2] = (ellipse[:2] + 0.5) / scale - 0.5
    ellipse[2:4] /= scale
    canvas = draw_overlay(np.zeros(shape), [CupDrawing(ellipse, None, None, [])], "",
                          max_side=1024).astype(int)
    assert canvas.shape[:2] == (round(shape[0] * scale), round(shape[1] * scale))
    green = (canvas[..., 1] > 100) & (canvas[..., 1] > canvas[..., 2] + 50)
    drawn = np.argwhere(green)[:, ::-1].astype(float)  # (u, v)
    drawn = drawn[np.linalg.norm(drawn - [370, 220], axis=1) > 24]  # not the cup's label
    curve = ellipse_points(torch.tensor(ellipse), torch.linspace(0, 2 * np.pi, 2000,
                                                                 dtype=torch.float64)).numpy()
    curve = (curve + 0.5) * scale - 0.5  # original pixels -> overlay pixels
    dist = np.linalg.norm(drawn[:, None] - curve[None], axis=-1)
    assert len(drawn) > 100
    assert dist.min(1).max() < tol  # every drawn pixel on the curve
    assert dist.min(0).max() < tol  # the whole curve drawn


def rim_landmarks(pose_deg: list[float], diameter: float, geometry: Geometry,
                  n: int = 24) -> np.ndarray:
    """``(n, 2)`` pixels of the projected rim of a cup pose (public units)."""
    t = torch.linspace(0, 2 * np.pi, n + 1, dtype=torch.float64)[:-1]
    pose = pose_to_radians(torch.tensor([pose_deg], dtype=torch.float64))
    return project_rim(pose, diameter / 2, geometry, t)[0].numpy()


def test_landmarks_bilateral_two_rows_blank_no_cup(tmp_path: Path) -> None:
    images = tmp_path / "images"
    images.mkdir()
    noise_png(images / "pelvis.png", size=512)
    cv2.imwrite(str(images / "blank.png"), np.zeros((512, 512), np.uint16))
    geometry = Geometry.for_image(512, 512, sdd=1000.0, pixel_spacing=0.4)
    right, left = [25.0, 40.0, -60.0, 10.0, 300.0], [20.0, -35.0, 55.0, 15.0, 280.0]
    lines = ["image,cup,u,v"]
    for cup, pose in enumerate((right, left), start=1):  # the file's own labels, 1 and 2
        points = rim_landmarks(pose, 52.0, geometry)
        lines += [f"pelvis.png,{cup},{u:.9f},{v:.9f}" for u, v in points]
    (tmp_path / "landmarks.csv").write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    geometry_flags = ["--sdd", "1000", "--pixel-spacing", "0.4", "--cup-diameter", "52"]
    assert main(["predict", str(images), "--out", str(out), "--landmarks",
                 str(tmp_path / "landmarks.csv"), *geometry_flags, "--quiet"]) == 0
    by_image = rows_by_image(read_csv(out / "results.csv"))
    assert [r["status"] for r in by_image["blank.png"]] == ["no_cup"]
    # Without the geometry too: it had been an error row naming the geometry missing, which
    # an image without landmarks does not need.
    assert main(["predict", str(images), "--out", str(tmp_path / "bare"), "--landmarks",
                 str(tmp_path / "landmarks.csv"), "--quiet"]) == 0
    bare = rows_by_image(read_csv(tmp_path / "bare" / "results.csv"))
    assert [r["status"] for r in bare["blank.png"]] == ["no_cup"]
    assert bare["pelvis.png"][0]["status"].startswith("error: missing source-to-detector")
    rows = by_image["pelvis.png"]
    # The file's labels, as cupnet solve writes them (predict had numbered them 0, 1).
    assert [r["cup"] for r in rows] == ["1", "2"]
    assert main(["solve", str(tmp_path / "landmarks.csv"), "--out", str(tmp_path / "s.csv"),
                 *geometry_flags, "--image-size", "512", "512"]) == 0
    solved = read_csv(tmp_path / "s.csv")
    assert [(r["cup"], r["anteversion_deg"]) for r in solved] == [
        (r["cup"], r["anteversion_deg"]) for r in rows]
    for row, truth in zip(rows, (right, left), strict=True):
        assert row["status"] == "ok"
        got = [float(row[c]) for c in POSE_COLUMNS]
        np.testing.assert_allclose(got, truth, atol=1e-3)
        assert row["doubt"] == ""  # no network measured it
        assert row["check"] == "0"  # the landmarks lie on the solved rim
        # Standard errors from their scatter about it: none to speak of, exact as they are.
        assert all(0 <= float(row[c]) < 1e-3 for c in SD_COLUMNS)
    overlay = cv2.imread(str(out / "overlays" / "pelvis.png.png"))
    assert overlay.shape == (768, 768, 3)
    document = json.loads((out / "results.json").read_text())
    assert document["model"]["landmarks"] == str(tmp_path / "landmarks.csv")


def test_landmarks_in_the_paper_format_carry_geometry(tmp_path: Path) -> None:
    # The paper's label.csv: pixels are millimetres, SDD and radius per row.
    cv2.imwrite(str(tmp_path / "x.png"), np.zeros((300, 400), np.uint8))
    geometry = Geometry.for_image(400, 300, sdd=1040.0, pixel_spacing=1.0)
    pose = [30.0, 25.0, 20.0, -15.0, 400.0]
    points = rim_landmarks(pose, 48.0, geometry, n=16)
    header = "image_name,image_width,image_height,source_to_detection_distance,radius," \
             "n_landmarks," + ",".join(f"landmark_{i}_x,landmark_{i}_y" for i in range(1, 17))
    row = ",".join(["x.png", "400", "300", "1040", "24", "16",
                    *(repr(float(c)) for c in points.reshape(-1))])
    (tmp_path / "label.csv").write_text(f"{header}\n{row}\nbad.png,400,300,1040,24,16,1,2\n")
    out = tmp_path / "out"
    cv2.imwrite(str(tmp_path / "bad.png"), np.zeros((300, 400), np.uint8))
    assert main(["predict", str(tmp_path), "--out", str(out), "--landmarks",
                 str(tmp_path / "label.csv"), "--quiet", "--no-overlays"]) == 0
    by_image = rows_by_image(read_csv(out / "results.csv"))
    (row,) = by_image["x.png"]
    np.testing.assert_allclose([float(row[c]) for c in POSE_COLUMNS], pose, atol=1e-3)
    assert "n_landmarks = 16 but 1 landmarks given" in by_image["bad.png"][0]["status"]
    geometry_used = {r["image"]: r for r in json.loads(
        (out / "results.json").read_text())["images"]}["x.png"]["geometry"]
    assert geometry_used["sdd_mm"] == {"value": 1040.0, "source": "landmark file"}
    assert geometry_used["cup_diameter_mm"] == {"value": 48.0, "source": "landmark file"}


class _RunsCode:
    """Pickles to a call of ``Path.touch``: loading it unsafely would create the marker."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_checkpoint_cannot_run_code(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    marker = tmp_path / "code_ran"
    torch.save({"weight": _RunsCode(marker)}, tmp_path / "evil.pt")
    noise_png(tmp_path / "a.png")
    assert main(["predict", str(tmp_path / "a.png"), "--out", str(tmp_path / "out"),
                 "--checkpoint", str(tmp_path / "evil.pt"), "--cup-diameter", "52"]) == 2
    assert not marker.exists()
    assert "cannot load" in capsys.readouterr().err


def test_shipped_model_bilateral_two_rows_blank_no_cup(tmp_path: Path,
                                                      capsys: pytest.CaptureFixture) -> None:
    """The shipped checkpoint on a synthetic bilateral image (two rows), the same image
    turned over (metal bright: taken so, turned back, the same poses) and a blank one."""
    from data_synth.config import SynthConfig
    from data_synth.dataset import synthesize

    # 512 px, the networks' smallest training size: no enlargement (tested below).
    config = SynthConfig(p_bilateral=1.0, p_no_cup=0.0, photons=(5000.0, 20000.0),
                         image_size=(512, 512))
    sample = next(s for s in (synthesize(config, 11, i) for i in range(20))
                  if bool(s["cup_valid"].all()))
    images = tmp_path / "images"
    images.mkdir()
    pixels = np.round(sample["image"][0].numpy() * 65535).astype(np.uint16)
    cv2.imwrite(str(images / "bilateral.png"), pixels)
    cv2.imwrite(str(images / "bilateral_bright.png"), 65535 - pixels)
    # The same image with three times the noise of the noisiest training images.
    noise = np.random.default_rng(3).normal(0, 0.03 * 65535, pixels.shape)
    cv2.imwrite(str(images / "bilateral_noisy.png"),
                np.round(np.clip(pixels + noise, 0, 65535)).astype(np.uint16))
    cv2.imwrite(str(images / "blank.png"), np.zeros(config.image_size[::-1], np.uint16))
    sdd, spacing, u0, v0 = sample["geometry"].tolist()
    out = tmp_path / "out"
    assert main(["predict", str(images), "--out", str(out), "--sdd", str(sdd),
                 "--pixel-spacing", str(spacing), "--principal-point", str(u0), str(v0),
                 "--cup-diameter", str(float(sample["cup_diameter"][0])), "--quiet"]) == 0
    by_image = rows_by_image(read_csv(out / "results.csv"))
    assert [r["status"] for r in by_image["blank.png"]] == ["no_cup"]
    blank = by_image["blank.png"][0]
    assert blank["doubt"] == blank["check"] == blank["metal"] == ""
    rows = by_image["bilateral.png"]
    assert [r["cup"] for r in rows] == ["0", "1"]
    # Left to right: each row's ellipse centre near the true cup on its side, and each pose
    # one the network believes (not flagged for checking).
    true_u = sorted(sample["ellipse"][:, 0].tolist())
    for row, u in zip(rows, true_u, strict=True):
        assert abs(float(row["ellipse_cx_px"]) - u) < 10
        assert float(row["doubt"]) < 1.8 and row["check"] == "0" and row["metal"] == "dark"
        assert all(row[c] == "" for c in SD_COLUMNS)  # not for the network's landmarks
    turned = by_image["bilateral_bright.png"]
    assert [r["metal"] for r in turned] == ["bright", "bright"]
    # Not the same run as the dark image's: the locator saw the bright image, so the rims
    # start from other rough ellipses (tests/test_polarity.py checks the turning exactly).
    for row, dark in zip(turned, rows, strict=True):
        difference = np.abs([float(row[c]) - float(dark[c]) for c in POSE_COLUMNS])
        assert (difference < [1.5, 1.5, 1.0, 1.0, 5.0]).all()
    # The noisy image is measured as such and denoised first; its poses stay near the truth
    # (the clean image's are off by up to 0.9 deg and 3.4 mm in h, the noisy one's by up to
    # 2.1 deg, 1.8 mm in k and 12.4 mm in h: the outline refinement, which had brought h
    # within 9.4 mm, left one cup's pose more doubted, so it keeps its rim's pose;
    # docs/training.md, item 67).
    # The others carry no noise: under the model's denoise_above only the decision is taken.
    noisy = by_image["bilateral_noisy.png"]
    assert [r["denoised"] for r in noisy] == ["1", "1"]
    assert all(abs(float(r["noise"]) - 0.03) < 0.003 for r in noisy)
    assert all(r["denoised"] == "0" and r["noise"] == "" for r in rows + turned)
    truth = sorted(sample["pose"].tolist(), key=lambda pose: pose[2])  # left to right
    for row, pose in zip(noisy, truth, strict=True):
        error = np.abs([float(row[c]) for c in POSE_COLUMNS] - np.array(pose))
        assert (error < [3.5, 3.5, 2.0, 2.0, 15.0]).all()
    printed = capsys.readouterr().out
    assert "1 image(s) taken to show metal bright" in printed
    assert "1 image(s) noisier than the networks' training, denoised first" in printed


@pytest.mark.parametrize(
    ("render", "export", "photons", "column", "factor", "said", "near_px", "bound"),
    [(512, 0.5, (5000.0, 20000.0), "enlarged", 2.0,
      "smaller than the networks' training, enlarged first", 0.5, [1.5, 1.0, 1.0, 1.0, 8.0]),
     (2048, 1.0, None, "reduced", 0.5,
      "much larger than the networks' training, reduced first", 1.0, [1.0, 1.0, 1.0, 1.0, 8.0])])
def test_an_image_off_the_training_sizes_is_resized_first_and_reported_in_its_pixels(
        tmp_path: Path, capsys: pytest.CaptureFixture, render: int, export: float,
        photons: tuple[float, float] | None, column: str, factor: float, said: str,
        near_px: float, bound: list[float]) -> None:
    """A DRR of ``render`` px, exported at ``export`` of its size (area-averaged; spacing
    and principal point moved with it): a 512 px DRR at half its size, which the shipped
    model enlarges twice to its smallest training side, and a 2048 px one as rendered,
    which it reduces to half. Each says so, and reports the cup in the image's own pixels
    near the truth; the flag at 0 runs the image as it is."""
    from data_synth.config import SynthConfig
    from data_synth.dataset import synthesize

    config = SynthConfig(p_no_cup=0.0, image_size=(render, render),
                         **({} if photons is None else {"photons": photons}))
    sample = synthesize(config, 5, 2)
    pixels = np.round(sample["image"][0].numpy() * 65535).astype(np.uint16)
    if export != 1:
        pixels = cv2.resize(pixels, None, fx=export, fy=export, interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(tmp_path / "image.png"), pixels)
    sdd, spacing, u0, v0 = sample["geometry"].tolist()
    args = ["predict", str(tmp_path / "image.png"), "--sdd", str(sdd), "--pixel-spacing",
            str(spacing / export), "--principal-point", str((u0 + 0.5) * export - 0.5),
            str((v0 + 0.5) * export - 0.5), "--cup-diameter",
            str(float(sample["cup_diameter"][0])), "--quiet", "--no-overlays"]
    flag = {"enlarged": "--enlarge-below", "reduced": "--reduce-above"}[column]
    other = {"enlarged": "reduced", "reduced": "enlarged"}[column]
    assert main([*args, "--out", str(tmp_path / "out")]) == 0
    [row] = read_csv(tmp_path / "out" / "results.csv")
    assert row["status"] == "ok" and float(row[column]) == factor and row[other] == ""
    centre = (sample["ellipse"][0, :2].numpy() + 0.5) * export - 0.5
    found = np.array([float(row["ellipse_cx_px"]), float(row["ellipse_cy_px"])])
    assert np.abs(found - centre).max() < near_px
    error = np.abs([float(row[c]) for c in POSE_COLUMNS] - sample["pose"][0].numpy())
    assert (error < bound).all()
    assert f"1 image(s) {said}" in capsys.readouterr().out
    assert main([*args, "--out", str(tmp_path / "as_is"), flag, "0"]) == 0
    [row] = read_csv(tmp_path / "as_is" / "results.csv")
    assert row["status"] == "ok" and row[column] == ""
    assert said.split(", ")[-1] not in capsys.readouterr().out  # "enlarged first" and so on


def test_spacing_from_patient_plane_pixel_spacing_is_recorded_and_reported(
        tmp_path: Path, blind_checkpoint: Path, capsys: pytest.CaptureFixture) -> None:
    stored = np.zeros((256, 320), np.uint16)
    write_dicom(tmp_path / "plain.dcm", stored, PixelSpacing=[0.2, 0.2],
                DistanceSourceToDetector=1000.0)
    write_dicom(tmp_path / "imager.dcm", stored, ImagerPixelSpacing=[0.2, 0.2],
                DistanceSourceToDetector=1000.0)
    write_dicom(tmp_path / "skewed.dcm", stored, ImagerPixelSpacing=[0.1, 0.2],
                DistanceSourceToDetector=1000.0)
    out = tmp_path / "out"
    assert main(["predict", str(tmp_path), "--out", str(out), "--checkpoint",
                 str(blind_checkpoint), "--cup-diameter", "52", "--quiet"]) == 0
    document = json.loads((out / "results.json").read_text())
    sources = {r["image"]: r["geometry"]["pixel_spacing_mm"]["source"]
               for r in document["images"] if "pixel_spacing_mm" in r["geometry"]}
    assert sources == {"plain.dcm": PATIENT_SPACING_SOURCE,
                       "imager.dcm": "DICOM ImagerPixelSpacing"}
    # A tag present but unusable: the row says which and why, not only that one is missing.
    (skewed,) = rows_by_image(read_csv(out / "results.csv"))["skewed.dcm"]
    assert skewed["status"] == (
        "error: missing pixel spacing (--pixel-spacing or meta.csv pixel_spacing_mm; DICOM "
        "ImagerPixelSpacing is not square (0.1 x 0.2 mm); give --pixel-spacing); or use "
        "--assume-defaults")
    assert document["summary"]["patient_spacing"] == 1
    assert "1 image(s) with the detector's pixel spacing taken from DICOM PixelSpacing" in (
        capsys.readouterr().out)


def test_several_inputs_as_a_shell_expands_them(tmp_path: Path, blind_checkpoint: Path) -> None:
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        noise_png(tmp_path / folder / "x.png", size=256)
    noise_png(tmp_path / "a" / "y.png", size=256)
    (tmp_path / "a" / "latest.png").symlink_to("y.png")  # a link keeps its own row
    out = tmp_path / "out"
    specs = [str(tmp_path / "a" / "x.png"), str(tmp_path / "b" / "x.png"), str(tmp_path / "a"),
             f"{tmp_path}/a/*.png", f"{tmp_path}/a/../a/y.png"]
    assert main(["predict", *specs, "--out", str(out), "--checkpoint", str(blind_checkpoint),
                 "--sdd", "1000", "--pixel-spacing", "0.3", "--cup-diameter", "52",
                 "--quiet", "--no-overlays"]) == 0
    names = list(rows_by_image(read_csv(out / "results.csv")))
    # Each file once; both x.png are named by their paths, not merged.
    assert names == [(tmp_path / "a" / "x.png").as_posix(), (tmp_path / "b" / "x.png").as_posix(),
                     "latest.png", "y.png"]


def test_assumptions_printed_once_and_recorded(tmp_path: Path, blind_checkpoint: Path,
                                               capsys: pytest.CaptureFixture) -> None:
    for i in range(3):
        noise_png(tmp_path / f"im{i}.png")
    out = tmp_path / "out"
    assert main(["predict", str(tmp_path), "--out", str(out), "--checkpoint",
                 str(blind_checkpoint), "--sdd", "1000", "--assume-defaults", "--quiet",
                 "--no-overlays"]) == 0
    err = capsys.readouterr().err
    assert err.count("assuming cup diameter = 52 mm") == 1
    assert err.count("assuming pixel spacing") == 1 and "assuming source" not in err
    document = json.loads((out / "results.json").read_text())
    assert set(document["assumptions"]) == {"cup_diameter_mm", "pixel_spacing_mm"}
    geometry = document["images"][0]["geometry"]
    assert geometry["pixel_spacing_mm"] == {"value": ASSUMED_DETECTOR_WIDTH_MM / 256,
                                            "source": "assumed"}
    assert geometry["sdd_mm"]["source"] == "command line"


def test_overlay_draws_the_dome_outline_where_given() -> None:
    """An open curve through the given points, in the cup's colour, and nothing else."""
    from cupnet.overlay import CupDrawing, draw_overlay

    t = np.linspace(0.2 * np.pi, 0.8 * np.pi, 40)
    outline = np.stack([400 + 90 * np.cos(t), 300 - 90 * np.sin(t)], -1)  # an upper arc
    canvas = draw_overlay(np.zeros((600, 800)), [CupDrawing(None, None, None, [], "ok",
                                                            outline)], "").astype(int)
    green = (canvas[..., 1] > 60) & (canvas[..., 1] > canvas[..., 2] + 30)
    drawn = np.argwhere(green)[:, ::-1].astype(float)
    dense = np.stack([400 + 90 * np.cos(np.linspace(t[0], t[-1], 2000)),
                      300 - 90 * np.sin(np.linspace(t[0], t[-1], 2000))], -1)
    dist = np.linalg.norm(drawn[:, None] - dense[None], axis=-1)
    assert len(drawn) > 100
    assert dist.min(1).max() < 2.0  # every drawn pixel on the arc (chords sag < 0.2 px)
    assert dist.min(0).max() < 2.0  # the whole arc drawn, and not closed:
    assert not green[300, 300:500].any()


def test_overlay_text_goes_to_a_corner_that_covers_no_cup() -> None:
    """A cup in the top left keeps its colour: the text had been drawn over it there, on a
    band that dims what it covers to 35 %. It goes to the top right instead, and stays in
    the top left where the cup is elsewhere."""
    from cupnet.overlay import STATUS_COLOURS, CupDrawing, draw_overlay

    image = np.tile(np.linspace(0.8, 0.2, 600)[:, None], (1, 800))  # bright at the top
    lines = ["cup 0: ok", "a second line", "a third line"]

    def drawn(cx: float, cy: float) -> np.ndarray:
        cup = CupDrawing(np.array([cx, cy, 50.0, 30.0, 0.0]), None, None, lines)
        return draw_overlay(image, [cup], "x.png: 1 cup(s)").astype(int)

    top_left = drawn(70.0, 60.0)
    assert top_left[60, 120].tolist() == list(STATUS_COLOURS["ok"])  # the ellipse's right end
    plain = drawn(400.0, 400.0)
    # Row 1 lies in the band, above its text: dimmed where the band is, not elsewhere.
    assert (top_left[1, 798] < 0.5 * plain[1, 798]).all()
    assert (plain[1, 1] < 0.5 * top_left[1, 1]).all()


def test_overlay_labels_a_cup_with_its_results_number() -> None:
    """A cup drawn with ``number`` 1 carries the label a second cup of the list gets, not the
    first's "0": under --landmarks a file's cups 1 and 2 had been labelled 0 and 1 on the
    overlay, beside results.csv's 1 and 2."""
    from cupnet.overlay import CupDrawing, draw_overlay

    cup = CupDrawing(np.array([400.0, 300.0, 80.0, 50.0, 20.0]), None, None, [])
    nothing = CupDrawing(None, None, None, [])
    labelled = draw_overlay(np.zeros((600, 800)), [replace(cup, number=1)], "")
    second = draw_overlay(np.zeros((600, 800)), [nothing, cup], "")
    first = draw_overlay(np.zeros((600, 800)), [cup], "")
    assert np.array_equal(labelled, second) and not np.array_equal(labelled, first)


@pytest.mark.parametrize("check", [False, True])
def test_overlay_marks_a_cup_to_check(check: bool) -> None:
    """A cup the model doubts is drawn in the check colour, its text says so; otherwise the
    status colour and the doubt alone."""
    from cupnet.overlay import CHECK_COLOUR, STATUS_COLOURS, CupDrawing, draw_overlay, pose_lines

    lines = pose_lines(0, "ok", [20.0, 30.0, 1.0, 2.0, 300.0], 0.4, None, 2.5 if check else 0.3,
                       check)
    assert lines[0] == ("cup 0: ok, doubt 2.50 - CHECK BY EYE" if check
                        else "cup 0: ok, doubt 0.30")
    ellipse = np.array([400.0, 300.0, 120.0, 60.0, 30.0])
    canvas = draw_overlay(np.zeros((600, 800)), [CupDrawing(ellipse, None, None, [], "ok",
                                                            None, check)], "")
    colour = CHECK_COLOUR if check else STATUS_COLOURS["ok"]
    assert (canvas == colour).all(-1).sum() > 100  # the ellipse's pixels
    other = STATUS_COLOURS["ok"] if check else CHECK_COLOUR
    assert not (canvas == other).all(-1).any()


def test_overlay_text_gives_the_standard_errors_where_there_are_any() -> None:
    from cupnet.overlay import pose_lines

    pose = [20.04, 30.0, 1.0, 2.0, 300.0]
    plain = pose_lines(0, "ok", pose, 0.4)
    assert plain[1:] == ["  anteversion 20.0 deg, inclination 30.0 deg",
                         "  k 1.0, l 2.0, h 300.0 mm; residual 0.40 px"]
    sd = np.array([0.43, 0.61, 0.12, 0.15, 3.4])
    assert pose_lines(0, "ok", pose, 0.4, pose_sd=sd)[1:] == [
        "  anteversion 20.0 +-0.4 deg, inclination 30.0 +-0.6 deg",
        "  k 1.0 +-0.1, l 2.0 +-0.1, h 300.0 +-3.4 mm; residual 0.40 px"]
    assert pose_lines(0, "ok", pose, 0.4, pose_sd=np.full(5, np.nan)) == plain
    # The second pose: its own angles and h, each in its place.
    assert pose_lines(0, "ambiguous", pose, 0.4, [21.0, 31.0, 3.0, 4.0, 305.0])[3:] == [
        "  or: anteversion 21.0 deg, inclination 31.0 deg, h 305.0 mm"]


@pytest.mark.parametrize(("flags", "preset", "changed"),
                         [([], None, {}), (["--fast"], "fast", {"verify_gate": None}),
                          (["--fastest"], "fastest",
                           {"verify_gate": None, "outline_passes": 0, "thin_rim_gate": None}),
                          (["--check-doubt", "0.5"], None,
                           {"check_doubt": 0.5, "look_again_doubt": 1.8}),
                          (["--metal", "bright"], None, {"metal": "bright"}),
                          (["--keep-outside-field"], None, {"round_field": False}),
                          (["--min-score", "0"], None, {"min_score": 0.0}),
                          (["--denoise-above", "0.02"], None, {"denoise_above": 0.02}),
                          # Never denoise: standard JSON has no Infinity, so null.
                          (["--denoise-above", "inf"], None, {"denoise_above": None}),
                          (["--enlarge-below", "0"], None, {"enlarge_below": 0}),
                          (["--reduce-above", "1500"], None, {"reduce_above": 1500}),
                          (["--reduce-above", "0"], None, {"reduce_above": None}),
                          (["--blurred", "--fast"], "fast",
                           {"blurred": True, "verify_gate": None})])
def test_speed_presets_and_check_doubt_set_the_model_and_are_recorded(
        tmp_path: Path, flags: list[str], preset: str | None, changed: dict) -> None:
    """``--fast`` turns the model's verification off, ``--fastest`` also its outline
    refinement and thin-rim hypotheses (the recorded config shows it, and the preset's name
    is recorded); ``--check-doubt`` sets the flag's threshold (the later looks keep the
    checkpoint's, which was the flag's), ``--metal`` how the images
    show metal, ``--keep-outside-field`` keeps cups outside a round field, ``--min-score``
    sets the weakest locator blob kept, ``--denoise-above`` the noise from which images are
    denoised, ``--enlarge-below`` the side under which they are enlarged, ``--reduce-above``
    that over which they are reduced (0: never), ``--blurred`` runs the blur-trained rim
    network (with a speed preset too); every other setting is the checkpoint's."""
    stored = {"detect_threshold": 2.0, "verify_gate": 1.0, "check_doubt": 1.8,
              "outline_passes": 3, "thin_rim_gate": 0.3, "ambiguous_by_doubt": True,
              "round_field": True, "min_score": 0.8, "blur_rim": True}
    torch.manual_seed(0)  # the same weights each case: their networks are exported once
    model = CupNet(CupNetConfig(**stored))
    weights = save_model(model, tmp_path / "gated.safetensors")
    noise_png(tmp_path / "a.png")
    out = tmp_path / "out"
    args = ["predict", str(tmp_path / "a.png"), "--out", str(out), "--checkpoint", str(weights),
            "--assume-defaults", "--quiet", *flags]
    assert main(args) == 0
    model_info = json.loads((out / "results.json").read_text(),
                            parse_constant=lambda name: pytest.fail(f"{name} in results.json"))
    model_info = model_info["model"]
    assert model_info["speed_preset"] == preset
    expected = json.loads(json.dumps(vars(CupNetConfig(**stored)) | changed))  # as JSON has it
    assert model_info["config"] == expected


def test_an_enlarge_bar_over_the_models_reduce_bar_is_refused_before_any_image(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """``--enlarge-below`` over the checkpoint's ``reduce_above`` would enlarge and reduce
    the same sides (it had been set without the config's check); moved past it together
    with ``--reduce-above`` it runs."""
    weights = save_model(CupNet(CupNetConfig(detect_threshold=2.0, reduce_above=1024)),
                         tmp_path / "model.safetensors")
    noise_png(tmp_path / "a.png")
    args = ["predict", str(tmp_path / "a.png"), "--checkpoint", str(weights),
            "--assume-defaults", "--quiet", "--enlarge-below", "1500"]
    assert main([*args, "--out", str(tmp_path / "refused")]) == 2
    assert ("cannot load the model: reduce_above (1024) must be at least enlarge_below "
            "(1500)") in capsys.readouterr().err
    assert not (tmp_path / "refused" / "results.csv").exists()
    assert main([*args, "--reduce-above", "2000", "--out", str(tmp_path / "out")]) == 0
    config = json.loads((tmp_path / "out" / "results.json").read_text())["model"]["config"]
    assert (config["enlarge_below"], config["reduce_above"]) == (1500, 2000)


def test_blurred_images_need_a_model_with_the_blur_trained_rim_network(
        tmp_path: Path, blind_checkpoint: Path, capsys: pytest.CaptureFixture) -> None:
    """A checkpoint without it stops the run before any image, naming the option; with
    --landmarks there is no network to choose."""
    noise_png(tmp_path / "a.png")
    args = ["predict", str(tmp_path / "a.png"), "--out", str(tmp_path / "out"), "--blurred",
            "--assume-defaults", "--quiet"]
    assert main([*args, "--checkpoint", str(blind_checkpoint)]) == 2
    assert ("cannot load the model: --blurred needs a model with a rim network trained on "
            "blurrier images (blur_rim); this checkpoint has none") in capsys.readouterr().err
    assert not (tmp_path / "out" / "results.csv").exists()
    landmarks = tmp_path / "landmarks.csv"
    landmarks.write_text("image,cup,u,v\n")
    assert main([*args, "--landmarks", str(landmarks)]) == 2
    assert "--blurred chooses the network's rim stage" in capsys.readouterr().err


def test_fast_and_fastest_exclude_each_other(tmp_path: Path,
                                             capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit):
        main(["predict", str(tmp_path), "--out", str(tmp_path / "out"), "--fast", "--fastest"])
    assert "not allowed with argument" in capsys.readouterr().err


def test_implausible_geometry_is_warned_of_once_and_recorded(
        tmp_path: Path, blind_checkpoint: Path, capsys: pytest.CaptureFixture) -> None:
    for i in range(3):
        noise_png(tmp_path / f"im{i}.png")
    meta = tmp_path / "meta.csv"  # im1's spacing in cm: a slip of unit
    meta.write_text("image,pixel_spacing_mm\nim0.png,0.2\nim1.png,0.02\nim2.png,0.2\n")
    out = tmp_path / "out"
    assert main(["predict", str(tmp_path), "--out", str(out), "--checkpoint",
                 str(blind_checkpoint), "--meta", str(meta), "--sdd", "1000",
                 "--cup-diameter", "26", "--quiet", "--no-overlays"]) == 0
    captured = capsys.readouterr()
    diameter = ("cup diameter 26 mm (its radius?) lies outside 36-80 mm: first in im0.png, "
                "from command line")
    spacing = ("pixel spacing 0.02 mm (in cm?) lies outside 0.03-2 mm: first in im1.png, from "
               "meta.csv")
    assert captured.err.count(diameter) == 1 and captured.err.count(spacing) == 1
    assert "source-to-detector" not in captured.err
    assert f"  warning: {diameter}" in captured.out  # repeated in the closing summary
    warnings = json.loads((out / "results.json").read_text())["warnings"]
    assert set(warnings) == {"cup_diameter_mm", "pixel_spacing_mm"}
    assert warnings["pixel_spacing_mm"].startswith(spacing)
    # Warned of, not refused: every image is run.
    assert {r["status"] for r in read_csv(out / "results.csv")} == {"no_cup"}


def test_overlays_of_inputs_named_by_their_paths_stay_under_out(tmp_path: Path,
                                                                 blind_checkpoint: Path,
                                                                 monkeypatch: pytest.MonkeyPatch
                                                                 ) -> None:
    """Two inputs of one name, the second named by its path: relative with '..' (its overlay
    had gone to out/overlays/../../d2, into the input folder) or absolute."""
    for folder in ("d1", "d2", "d3"):
        (tmp_path / "in" / folder).mkdir(parents=True)
        noise_png(tmp_path / "in" / folder / "a.png", size=256)
    (tmp_path / "work").mkdir()
    monkeypatch.chdir(tmp_path / "work")
    assert main(["predict", "../in/d1", "../in/d2", str(tmp_path / "in" / "d3"),
                 "--out", "out", "--checkpoint", str(blind_checkpoint), "--assume-defaults",
                 "--quiet"]) == 0
    names = list(rows_by_image(read_csv(tmp_path / "work" / "out" / "results.csv")))
    assert names == ["../in/d1/a.png", "../in/d2/a.png",
                     (tmp_path / "in" / "d3" / "a.png").as_posix()]
    assert predict.output_name("../in/d2/a.png", ".png") == "__/in/d2/a.png.png"
    # A frame's '#N' ending is marked; a '#' of the file's own stays (a#1.png had taken
    # a_frame1.png's overlay).
    assert predict.output_name("run.dcm#2", ".png") == "run.dcm_frame2.png"
    assert predict.output_name("a#1.png", ".png") != predict.output_name("a_frame1.png", ".png")
    written = sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*.png.png"))
    assert len(written) == 3 and all(p.startswith("work/out/overlays/") for p in written)
    assert sorted(p.name for p in (tmp_path / "in" / "d2").iterdir()) == ["a.png"]
    # Meta rows given by folder find each file's own: the first of the name had kept it
    # alone ("a.png"), which both folders' rows matched, so neither was taken.
    (tmp_path / "work" / "meta.csv").write_text(
        "image,sdd_mm,pixel_spacing_mm,cup_diameter_mm\n"
        "d1/a.png,1001,0.31,50\nd2/a.png,1002,0.32,54\nd3/a.png,1003,0.33,56\n")
    assert main(["predict", "../in/d1", "../in/d2", str(tmp_path / "in" / "d3"), "--out", "out2",
                 "--checkpoint", str(blind_checkpoint), "--meta", "meta.csv", "--quiet",
                 "--no-overlays"]) == 0
    document = json.loads((tmp_path / "work" / "out2" / "results.json").read_text())
    assert [r["geometry"]["sdd_mm"] for r in document["images"]] == [
        {"value": 1000.0 + i, "source": "meta.csv"} for i in (1, 2, 3)]


def test_meta_rows_given_by_folder_reach_a_run_on_one_folder(tmp_path: Path,
                                                             blind_checkpoint: Path) -> None:
    """A run on in/d1 alone names its image a.png; the meta rows d1/a.png and d2/a.png had
    both matched that name alike, so neither was taken (an error row for want of the
    geometry). The file's path finds d1's row, and no row is reported unused but d2's."""
    for folder in ("d1", "d2"):
        (tmp_path / "in" / folder).mkdir(parents=True)
        noise_png(tmp_path / "in" / folder / "a.png", size=256)
    (tmp_path / "meta.csv").write_text("image,sdd_mm,pixel_spacing_mm,cup_diameter_mm\n"
                                       "d1/a.png,1001,0.31,50\nd2/a.png,1002,0.32,54\n")
    out = tmp_path / "out"
    assert main(["predict", str(tmp_path / "in" / "d1"), "--out", str(out), "--checkpoint",
                 str(blind_checkpoint), "--meta", str(tmp_path / "meta.csv"), "--quiet",
                 "--no-overlays"]) == 0
    document = json.loads((out / "results.json").read_text())
    (record,) = document["images"]
    assert record["image"] == "a.png"
    assert record["geometry"]["sdd_mm"] == {"value": 1001.0, "source": "meta.csv"}
    assert "first: d2/a.png" in document["warnings"]["unmatched_meta.csv"]
    # Landmarks given by folder: the image had come out no_cup, its landmarks unfound.
    t = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    (tmp_path / "lm.csv").write_text("image,u,v\n" + "".join(
        f"d1/a.png,{128 + 115 * np.cos(a):.4f},{128 + 70 * np.sin(a):.4f}\n" for a in t))
    assert main(["predict", str(tmp_path / "in" / "d1"), "--out", str(tmp_path / "lm"),
                 "--landmarks", str(tmp_path / "lm.csv"), "--meta", str(tmp_path / "meta.csv"),
                 "--quiet", "--no-overlays"]) == 0
    (row,) = read_csv(tmp_path / "lm" / "results.csv")
    assert row["image"] == "a.png" and row["status"] in ("ok", "ambiguous")


def test_an_overlay_that_cannot_be_written_loses_no_row(tmp_path: Path, blind_checkpoint: Path,
                                                         capsys: pytest.CaptureFixture) -> None:
    """A name one byte short of the file system's limit takes the overlay's '.png' past it:
    the run had stopped with a traceback and a results.csv of its header alone."""
    images = tmp_path / "images"
    images.mkdir()
    long_name = "x" * 251 + ".png"
    for name in ("a.png", long_name, "z.png"):
        noise_png(images / name, size=256)
    out = tmp_path / "out"
    assert main(["predict", str(images), "--out", str(out), "--checkpoint",
                 str(blind_checkpoint), "--assume-defaults", "--quiet"]) == 0
    assert list(rows_by_image(read_csv(out / "results.csv"))) == ["a.png", long_name, "z.png"]
    assert sorted(p.name for p in (out / "overlays").iterdir()) == ["a.png.png", "z.png.png"]
    document = json.loads((out / "results.json").read_text())
    assert f"first: {long_name}" in document["warnings"]["unwritten_images"]
    assert "cannot write overlays/" in capsys.readouterr().err


def test_an_out_that_is_a_file_or_holds_the_input_is_named(tmp_path: Path,
                                                             blind_checkpoint: Path,
                                                             capsys: pytest.CaptureFixture
                                                             ) -> None:
    images = tmp_path / "images"
    images.mkdir()
    noise_png(images / "a.png")
    (tmp_path / "afile").write_text("")
    common = ["--checkpoint", str(blind_checkpoint), "--assume-defaults", "--quiet"]
    # It had said "no images found" (everything under --out is skipped) and, for a file,
    # ended in a FileExistsError traceback.
    assert main(["predict", str(images), "--out", str(images), *common]) == 2
    assert f"--out {images} holds the input folder {images}" in capsys.readouterr().err
    # A quoted glob whose every match lies under --out had said "no images found".
    assert main(["predict", f"{images}/*.png", "--out", str(images), *common]) == 2
    assert "everything" in (err := capsys.readouterr().err) and "lies in the output folder" in err
    assert main(["predict", str(images), "--out", str(tmp_path / "afile"), *common]) == 2
    assert "is a file; give a folder for the results" in capsys.readouterr().err
    # A folder that cannot be made (a file on its path) is named before the model loads; it
    # had ended in a NotADirectoryError traceback after the first batch, with exit 1.
    assert main(["predict", str(images), "--out", str(tmp_path / "afile" / "sub"), *common]) == 2
    assert f"cannot write to --out {tmp_path / 'afile' / 'sub'}: Not a directory" in (
        capsys.readouterr().err)
    assert main(["predict", str(images), "--out", str(images / "cupnet"), *common]) == 0
    assert list(rows_by_image(read_csv(images / "cupnet" / "results.csv"))) == ["a.png"]
    # A second run beside the first, over subfolders: the first's overlays are no input
    # (they had been taken for two more images).
    assert (images / "cupnet" / "overlays" / "a.png.png").is_file()
    assert main(["predict", str(images), "--recursive", "--out", str(images / "cupnet2"),
                 *common]) == 0
    assert list(rows_by_image(read_csv(images / "cupnet2" / "results.csv"))) == ["a.png"]


def test_side_file_rows_no_image_found_are_warned_of(tmp_path: Path, blind_checkpoint: Path,
                                                      capsys: pytest.CaptureFixture) -> None:
    """A meta.csv row or landmark set whose name matches no image (a typo) had been left
    unused without a word; a key with folders that finds its image by file name is used."""
    images = tmp_path / "images"
    images.mkdir()
    for name in ("a.png", "b.png"):
        noise_png(images / name)
    meta = tmp_path / "meta.csv"
    meta.write_text("image,sdd_mm,pixel_spacing_mm,cup_diameter_mm\n"
                    "images/a.png,1000,0.3,52\nb.png,1000,0.3,52\nB_typo.png,1000,0.3,52\n")
    landmarks = tmp_path / "lm.csv"
    rim = [f"a.png,{128 + 110 * np.cos(t):.3f},{128 + 70 * np.sin(t):.3f}"
           for t in np.linspace(0, 2 * np.pi, 16, endpoint=False)]
    landmarks.write_text("\n".join(["image,u,v", *rim, "c.png,1,2"]) + "\n")
    out = tmp_path / "out"
    assert main(["predict", str(images), "--out", str(out), "--meta", str(meta),
                 "--landmarks", str(landmarks), "--quiet"]) == 0
    printed = capsys.readouterr().out
    warnings = json.loads((out / "results.json").read_text())["warnings"]
    assert warnings["unmatched_meta.csv"].startswith("1 meta.csv row(s) matched no image of "
                                                     "the run (first: B_typo.png)")
    assert "(first: c.png)" in warnings["unmatched_landmark"]
    assert "B_typo.png" in printed
    rows = rows_by_image(read_csv(out / "results.csv"))
    assert rows["a.png"][0]["status"] in ("ok", "ambiguous")
    assert rows["b.png"][0]["status"] == "no_cup"
    records = {r["image"]: r for r in json.loads((out / "results.json").read_text())["images"]}
    assert records["a.png"]["geometry"]["sdd_mm"]["source"] == "meta.csv"
    # Resumed with the image the typo meant: the row is used, and no warning says otherwise
    # (the first part's had stayed in the summary and results.json).
    noise_png(images / "B_typo.png")
    assert main(["predict", str(images), "--out", str(out), "--meta", str(meta),
                 "--landmarks", str(landmarks), "--quiet", "--resume"]) == 0
    warnings = json.loads((out / "results.json").read_text())["warnings"]
    assert "unmatched_meta.csv" not in warnings and "(first: c.png)" in warnings[
        "unmatched_landmark"]


def test_a_run_where_every_image_failed_exits_1(tmp_path: Path, blind_checkpoint: Path,
                                                 capsys: pytest.CaptureFixture) -> None:
    """Its rows say why, but a script's `&&` had gone on (exit 0); one image with a row that
    is no error (here no_cup) makes it 0 again."""
    images = tmp_path / "images"
    images.mkdir()
    noise_png(images / "small.png", size=64)  # under 256 px: an error row
    for name in ("empty.png", "empty2.png"):  # two rows of one reason: counted as two
        (images / name).write_bytes(b"")
    common = ["--checkpoint", str(blind_checkpoint), "--assume-defaults", "--quiet"]
    assert main(["predict", str(images), "--out", str(tmp_path / "a"), *common]) == 1
    printed = capsys.readouterr().out
    assert "0 without a cup, 3 error rows\n  2 x error: empty file (0 bytes)\n  1 x " in printed
    noise_png(images / "fine.png", size=256)
    assert main(["predict", str(images), "--out", str(tmp_path / "b"), *common]) == 0


@pytest.mark.parametrize("shape", [(300, 4000), (4000, 300)])
def test_an_oblong_images_overlay_text_goes_on_a_panel_below(shape: tuple[int, int]) -> None:
    """A 4000 x 300 strip's overlay (1024 x 77) had its text cover it whole, cut off; a tall
    one's title was wrapped a word a line and cut. The text now goes on a panel below, at
    least 48 characters wide, every line of it; the image keeps the top left, as drawn
    alone; a 512 px image's overlay keeps its size."""
    from cupnet.overlay import CupDrawing, draw_overlay, pose_lines

    pose = np.array([20.0, 40.0, 1.0, 2.0, 300.0])
    cups = [CupDrawing(np.array([150.0, 150.0, 60.0, 30.0, 10.0]), None, None,
                       pose_lines(j, "ambiguous", pose, 0.3, pose + 1, 0.5, False, None),
                       "ambiguous") for j in range(2)]
    image = np.random.default_rng(0).uniform(0, 1, shape)
    canvas = draw_overlay(image, cups, "strip.png: 2 cup(s)")
    scale = 1024 / max(shape)
    drawn = (round(shape[0] * scale), round(shape[1] * scale))
    assert canvas.shape[0] > drawn[0] and canvas.shape[1] >= max(drawn[1], 400)
    # The image's rows are the image's, undarkened by a text band (grey, not dimmed).
    picture = canvas[:drawn[0], :drawn[1], 0].astype(float)
    assert picture.mean() > 0.8 * image.mean() * 255
    # Every line (the title, then each cup's) on the panel: its ink spans them all.
    (_, height), baseline = cv2.getTextSize("Ag", cv2.FONT_HERSHEY_SIMPLEX, 0.8, 2)
    lines = 1 + sum(len(c.lines) for c in cups)
    ink_rows = np.flatnonzero((canvas[drawn[0]:] > 0).any((1, 2)))
    assert ink_rows[-1] - ink_rows[0] >= (lines - 1) * (height + baseline + 2)
    assert draw_overlay(np.zeros((512, 512)), cups, "a.png: 2 cup(s)").shape == (768, 768, 3)
