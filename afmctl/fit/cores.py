"""A second core for independent fits of one stage: calls run side by side on threads.

The fits' heavy parts release Python's global lock: the numba kernels are compiled ``nogil``,
and NumPy's products, copies and ufuncs release it. So fits that do not depend on each other
(the grid's start assignments' first steps, the held-out errors of its runs) can share one
process's memory, their bases of hundreds of MB included, and still run at once. SciPy's NNLS
holds the lock (a tenth of a grid fit's time), as does the Python between the kernels.

Only work that is needed runs so: the grid's kernels stream their bases through memory, and two
of them at once share its bandwidth. On this project's 2-core machine two linearizations at
once took 1.4x as long as one alone (so 1.4x the work per second, each 1.4x slower). Work that
might not be needed (the runner-up start assignment's fits, beside the best's in case they
were asked for) slowed the fit it ran beside by about a fifth, and is no longer started.

Results do not depend on the threads: each call computes what it would alone (one BLAS thread
each, as the fits ask), and :func:`together` returns them in the calls' order. At most
:data:`MAX_WORKERS` run at once: each holds its own linearized problem (memory), and a
laboratory's PC may be running the stage beside.
"""

from __future__ import annotations

import functools
import os
import signal
import threading
from collections.abc import Callable, Iterable, Sequence
from typing import TypeVar

A = TypeVar("A")
T = TypeVar("T")
#: Calls run at once at most (each holds its own linearized problem).
MAX_WORKERS = 2


def workers() -> int:
    """How many calls :func:`together` runs at once here: the cores this process may use, at
    most :data:`MAX_WORKERS`; 1 inside a call of :func:`together` (no nesting) and in a worker
    process of a pool that takes the cores already (:func:`pool_worker`)."""
    if getattr(_inside, "busy", False) or _alone:
        return 1
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(MAX_WORKERS, cores))


def pool_worker() -> None:
    """The initializer of a worker process in a pool with a process per core (diagnose's
    candidates, the x/y axes): it ignores Ctrl-C (leaving the pool in the parent terminates it)
    and runs :func:`together`'s calls one after another (the pool takes the cores already)."""
    global _alone
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _alone = True


def together(calls: Sequence[Callable[[], T]]) -> list[T]:
    """Each of ``calls`` called once, up to :func:`workers` at once; their results in order.

    The calling thread works too; the others are daemon threads, so an interrupt (which Python
    delivers to the main thread) leaves at once, not held up by a call still running on one. If
    a call raises, the first error in the calls' order is raised once every call has ended.

    Examples
    --------
    >>> together([lambda: 1, lambda: 2, lambda: 3])
    [1, 2, 3]
    """
    n, helpers = len(calls), workers() - 1
    if helpers < 1 or n < 2:
        return [call() for call in calls]
    results: list[T | None] = [None] * n
    errors: list[BaseException | None] = [None] * n
    left = iter(range(n))
    lock = threading.Lock()
    stop = threading.Event()  # the caller was interrupted: take no further call

    def work(catch: type[BaseException]) -> None:
        _inside.busy = True
        try:
            while True:
                with lock:
                    i = None if stop.is_set() else next(left, None)
                if i is None:
                    return
                try:
                    results[i] = calls[i]()
                except catch as exc:  # re-raised in the caller's thread below
                    errors[i] = exc
        finally:
            _inside.busy = False

    threads = [threading.Thread(target=work, args=(BaseException,), daemon=True)
               for _ in range(min(helpers, n - 1))]
    for t in threads:
        t.start()
    try:
        work(Exception)  # an interrupt here leaves at once ...
    except BaseException:
        stop.set()  # ... and the other threads end after the call they are in
        raise
    for t in threads:
        t.join()
    for exc in errors:
        if exc is not None:
            raise exc
    return results  # type: ignore[return-value]


def mapped(fun: Callable[[A], T], xs: Iterable[A]) -> list[T]:
    """``list(map(fun, xs))``, the calls side by side (:func:`together`): the ``workers`` of
    :func:`scipy.optimize.least_squares`, whose finite differences each evaluate the model on
    every sweep."""
    return together([functools.partial(fun, x) for x in xs])


_inside = threading.local()
_alone = False

__all__ = ["MAX_WORKERS", "workers", "pool_worker", "together", "mapped"]
