"""cupnet.detection: one image's detections less the repeats of one cup."""

import numpy as np

from cupnet.detection import CupDetection, distinct_cups


def detection(ellipse: list[float], status: str = "ok", doubt: float | None = 0.5
              ) -> CupDetection:
    pose = np.full(5, np.nan) if status.startswith("error") else np.array([20, 40, 0, 0, 900.0])
    return CupDetection(pose=pose, alt_pose=None, ambiguous=False,
                        ellipse=np.asarray(ellipse, np.float64), landmarks=np.zeros((0, 2)),
                        weights=np.zeros(0), residual_px=0.1, status=status, doubt=doubt)


def test_one_cup_found_twice_is_kept_once_by_its_better_detection():
    cup = [400.0, 312.0, 134.6, 15.9, 102.5]
    near = [401.0, 311.0, 133.0, 16.5, 102.0]  # within 10 % of a = 13.5 px
    other = [200.0, 150.0, 80.0, 50.0, 30.0]  # the other hip's cup
    error = detection(cup, status="error: solved h = -1253.2 mm lies outside (0, SDD)",
                      doubt=None)
    doubted, believed = detection(near, doubt=2.7), detection(cup, doubt=0.4)
    second = detection(other)
    kept = distinct_cups([error, second, doubted, believed])
    # A pose over an error, then the lower doubt; the other cup stays; the order is kept.
    assert [k is d for k, d in zip(kept, [second, believed], strict=True)] == [True, True]
    assert distinct_cups([doubted, error]) == [doubted]
    assert distinct_cups([detection(cup, doubt=None), doubted]) == [doubted]


def test_cups_apart_in_place_or_size_are_both_kept():
    cup = [400.0, 312.0, 100.0, 40.0, 10.0]
    moved = [400.0, 323.0, 100.0, 40.0, 10.0]  # centre 11 px away: over 10 % of a
    smaller = [400.0, 312.0, 100.0, 28.0, 10.0]  # b 12 px less
    nan = [np.nan] * 5  # an error without an ellipse is never anyone's repeat
    found = [detection(e) for e in (cup, moved, smaller, nan, nan)]
    assert distinct_cups(found) == found
    assert distinct_cups([]) == []
