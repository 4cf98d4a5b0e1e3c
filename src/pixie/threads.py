"""The one thread policy of every pixie process (standard library only: it runs before numpy and torch load).

pixie's heavy work runs in torch (matcher), OpenCV (image ops, PnP), NumPy's BLAS and Embree. Each brings its own
thread pool, and OpenMP pools busy-wait between parallel regions by default: on a machine shared with another
CPU-bound process, torch's default (one thread per core, spinning) made ``pixie estimate`` 9x slower (48 s
against 5.3 s with ``--threads 1``) and ``pixie refs build`` 8x slower. The policy:

* ``OMP_WAIT_POLICY=PASSIVE`` (idle OpenMP threads sleep instead of spinning), and ``OMP_NUM_THREADS``,
  ``MKL_NUM_THREADS``, ``OPENBLAS_NUM_THREADS`` set to the thread count, each only when the user did not set it:
  :func:`configure_env`, called by the ``pixie`` command before anything imports numpy or torch;
* then :func:`set_threads` fixes torch's, OpenCV's and (when ``threadpoolctl`` is installed) BLAS's pools;
* the default count (:func:`default_threads`) is measured on the 2-core project machine under load
  (bench/RESULTS.md, "Threads (issue 21)"): half the CPUs this process may use, at most 4, at least 1;
* reference-rendering worker processes use 1 OpenCV thread each (:func:`one_thread_while_forking`).

The same process policy covers imports: :func:`imports_without_gc` holds Python's cyclic garbage collector off while
a large package imports (each full pass walks every object torch created: ~0.3 s of a ``pixie estimate`` call's
start) and freezes what was imported, so later passes skip it.
"""

from __future__ import annotations

import gc
import os
import sys
from contextlib import contextmanager

from pixie.errors import PixieError

__all__ = ["COUNT_VARS", "default_threads", "configure_env", "threads_from_argv", "set_threads", "get_threads",
           "map_threads", "one_thread_while_forking", "imports_without_gc"]

COUNT_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def _cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        return os.cpu_count() or 1


def default_threads() -> int:
    """Threads per process when the user names none: half the usable CPUs, 1..4 (1 on a 2-core machine)."""
    return max(1, min(4, _cpus() // 2))


def configure_env(threads: int | None = None) -> None:
    """Passive OpenMP waiting, and the pools' sizes (``threads``, default :func:`default_threads`), in the
    environment, where the user has not set them. Effective only before torch / numpy are imported."""
    n = str(threads or default_threads())
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    for var in COUNT_VARS:
        os.environ.setdefault(var, n)


def threads_from_argv(argv: list[str]) -> int | None:
    """The value of ``--threads N`` / ``--threads=N`` in a command line (None when absent or not a number)."""
    for i, a in enumerate(argv):
        val = argv[i + 1] if a == "--threads" and i + 1 < len(argv) else a.partition("=")[2] if a.startswith(
            "--threads=") else None
        if val is not None:
            try:
                return int(val) if int(val) >= 1 else None
            except ValueError:
                return None
    return None


def get_threads() -> int:
    """torch's intra-op thread count (without importing torch when nothing loaded it yet)."""
    torch = sys.modules.get("torch")
    return torch.get_num_threads() if torch is not None else int(os.environ.get("OMP_NUM_THREADS") or default_threads())


def set_threads(n: int | None = None) -> int:
    """Use ``n`` threads (default :func:`default_threads`) in torch, OpenCV and BLAS in this process; returns
    the previous torch thread count."""
    import cv2
    import torch

    n = default_threads() if n is None else n
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise PixieError(f"threads must be a whole number >= 1, got {n!r}")
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    cv2.setNumThreads(n)
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # optional: without it BLAS keeps OPENBLAS/MKL_NUM_THREADS from configure_env
        pass
    else:
        threadpool_limits(n)
    return before



def map_threads(fn, items, workers: int | None = None) -> list:
    """``[fn(x) for x in items]``, run by ``workers`` threads (default :func:`get_threads`, the process's count).

    For independent jobs whose heavy parts release the GIL (Embree's ray casting, NumPy, OpenCV): the edge
    alignment of a query's starts. The results keep the order of ``items`` and do not depend on ``workers``; with
    one worker (or fewer than two items) nothing is started. An exception in a job is raised here."""
    items = list(items)
    n = get_threads() if workers is None else int(workers)
    if n <= 1 or len(items) < 2:
        return [fn(x) for x in items]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=min(n, len(items)), thread_name_prefix="pixie") as ex:
        return list(ex.map(fn, items))


@contextmanager
def one_thread_while_forking():
    """OpenCV at one thread while worker processes are forked, so that they inherit a serial OpenCV (1 thread
    each); the parent's setting is restored after. Changing thread pools *in* a forked child deadlocks (OpenCV's
    and GNU OpenMP's pools are not fork-safe), so the workers never do; torch does no work in them."""
    import cv2

    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


@contextmanager
def imports_without_gc():
    """No cyclic garbage collection while the block imports; then ``gc.freeze()`` the (long-lived) result.

    Nested or already-disabled collection is left as found. Meant for a process's start (the ``pixie`` command, the
    first matcher): ``gc.freeze`` moves every object alive then out of the collected generations for good, so
    cyclic garbage made before it would stay; modules are never garbage.
    """
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.freeze()
            gc.enable()
