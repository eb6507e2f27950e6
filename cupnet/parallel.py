"""Small independent network calls spread over the CPU's cores, one call per worker thread.

The rim networks run on many small strips (about 85 an image), one by one on a CPU so that
each strip's activations stay in cache. Convolutions that small gain little from PyTorch's
intra-op threads (12 strips on the 2-core machine: 85 ms on one thread, 82 on two, 300 on
two while another process keeps a core busy, its OpenMP threads waiting on each other),
so with ``n`` torch threads the calls go to ``n`` worker threads of one intra-op thread
each instead (53 ms, 86 under that load). Each call computes exactly what it computes on
one thread, so the results are bit-identical to a one-thread run.
"""

from __future__ import annotations

import functools
import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import torch

Item = TypeVar("Item")
Result = TypeVar("Result")


def map_on_cores(function: Callable[[Item], Result], items: Sequence[Item]) -> list[Result]:
    """``[function(item) for item in items]``, on up to ``torch.get_num_threads()`` worker
    threads of one intra-op thread each (in order; serially with one thread or one item).

    The caller's grad and inference modes (thread-local in PyTorch) hold in the workers.
    """
    workers = min(torch.get_num_threads(), len(items))
    if workers <= 1:
        return [function(item) for item in items]
    grad, inference = torch.is_grad_enabled(), torch.is_inference_mode_enabled()

    def call(item: Item) -> Result:
        with torch.inference_mode(inference), torch.set_grad_enabled(grad):
            return function(item)

    return list(_pool(workers, os.getpid()).map(call, items))


@functools.cache
def _pool(workers: int, pid: int) -> ThreadPoolExecutor:
    """A pool of ``workers`` threads, each set to one intra-op thread (keyed by process id:
    a forked child has none of its parent's threads)."""
    threads = torch.get_num_threads()
    started = threading.Barrier(workers + 1)

    def one_thread() -> None:
        # A thread takes up the process's count at its first torch call, and a count set
        # before it would be overwritten then: that call first, then one thread.
        torch.get_num_threads()
        torch.set_num_threads(1)
        started.wait()

    pool = ThreadPoolExecutor(workers, thread_name_prefix=f"cupnet-cores-{pid}",
                              initializer=one_thread)
    for _ in range(workers):  # start every worker now, so each runs its initializer
        pool.submit(lambda: None)
    started.wait()
    # torch.set_num_threads also sets the count that threads started later take up; the
    # workers keep theirs (one), the rest of the process gets the caller's back.
    torch.set_num_threads(threads)
    return pool
