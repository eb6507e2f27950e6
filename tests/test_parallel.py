"""Network calls spread over worker threads: results, order, modes and thread settings."""

from __future__ import annotations

import threading

import pytest
import torch

from cupnet.parallel import _pool, map_on_cores


@pytest.fixture
def two_threads():
    previous = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(previous)


def test_map_on_cores_matches_the_serial_map_in_order(two_threads):
    conv = torch.nn.Conv2d(1, 4, 3)
    items = list(torch.randn(7, 1, 1, 16, 16))
    with torch.inference_mode():
        ours = map_on_cores(conv, items)
        serial = [conv(item) for item in items]
    assert len(ours) == 7
    for a, b in zip(ours, serial, strict=True):
        assert torch.equal(a, b)


def test_map_on_cores_runs_on_worker_threads_and_leaves_the_callers_setting(two_threads):
    names = map_on_cores(lambda _: threading.current_thread().name, range(6))
    assert all(name.startswith("cupnet-cores") for name in names)
    # Each worker runs one intra-op thread (they had taken up the caller's count at their
    # first torch call, after it was restored), and the caller's count stays as it was.
    assert map_on_cores(lambda _: torch.get_num_threads(), range(2)) == [1, 1]
    assert torch.get_num_threads() == 2


def test_map_on_cores_runs_in_the_callers_thread_with_one_torch_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        names = map_on_cores(lambda _: threading.current_thread().name, range(3))
    finally:
        torch.set_num_threads(previous)
    assert names == [threading.current_thread().name] * 3


def test_map_on_cores_carries_the_callers_grad_and_inference_modes(two_threads):
    weight = torch.ones(3, requires_grad=True)
    grad_out = map_on_cores(lambda x: x * weight, [torch.ones(3), torch.ones(3)])
    assert all(out.requires_grad for out in grad_out)
    sum(out.sum() for out in grad_out).backward()
    assert torch.equal(weight.grad, torch.full((3,), 2.0))
    with torch.no_grad():
        assert not any(o.requires_grad for o in map_on_cores(lambda x: x * weight,
                                                             [torch.ones(3)] * 2))
    with torch.inference_mode():
        assert all(o.is_inference() for o in map_on_cores(lambda x: x * weight,
                                                          [torch.ones(3)] * 2))


def num_threads_of_a_new_thread() -> int:
    """``torch.get_num_threads()`` in a thread started now (its first torch call takes up
    the process's count then)."""
    seen: list[int] = []
    thread = threading.Thread(target=lambda: seen.append(torch.get_num_threads()))
    thread.start()
    thread.join()
    return seen[0]


def test_threads_started_after_map_on_cores_get_the_callers_count(two_threads):
    """Each worker's torch.set_num_threads(1) also sets the count of every thread started
    later (a data loader's, a server's): the pool gives the caller's back once its workers
    are set. A fresh pool, as the count is set while one is made."""
    _pool.cache_clear()
    assert num_threads_of_a_new_thread() == 2
    map_on_cores(lambda _: None, range(4))
    assert num_threads_of_a_new_thread() == 2
