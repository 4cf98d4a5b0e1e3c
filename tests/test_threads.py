"""pixie.threads: the process's thread policy and the thread map the alignment runs its starts with."""

from __future__ import annotations

import threading

import pytest

from pixie.threads import map_threads


def test_map_threads_keeps_the_order_of_the_items():
    """Results come back in the items' order whatever order the jobs finish in (the later items finish first)."""
    import time

    def slow_first(i):
        time.sleep(0.02 * (5 - i))
        return i * i

    assert map_threads(slow_first, range(6), workers=3) == [i * i for i in range(6)]
    assert map_threads(slow_first, range(6), workers=1) == [i * i for i in range(6)]


def test_map_threads_runs_jobs_at_once_with_two_workers_and_in_the_caller_with_one():
    """Two workers: both jobs wait at one barrier and pass it (they run at the same time). One worker: every job runs
    in the calling thread, one after the other, so no thread is started."""
    barrier = threading.Barrier(2, timeout=10)
    assert map_threads(lambda i: barrier.wait() >= 0, [0, 1], workers=2) == [True, True]
    caller = threading.current_thread()
    assert map_threads(lambda i: threading.current_thread() is caller, range(4), workers=1) == [True] * 4


def test_map_threads_raises_a_jobs_exception():
    def job(i):
        if i == 2:
            raise ValueError("job 2 failed")
        return i

    for workers in (1, 2):
        with pytest.raises(ValueError, match="job 2 failed"):
            map_threads(job, range(4), workers=workers)


def test_renders_from_several_threads_equal_the_serial_renders(proc_mesh, K640, make_pose):
    """One renderer shared by two threads (the alignment's starts) gives every pose's render bit for bit; the scene
    is committed when the renderer is built, so even its first renders may run at once."""
    import numpy as np

    from pixie.geometry.render import Renderer

    poses = [make_pose(proc_mesh, seed, distance_factor=3.0, offset_px=60) for seed in range(6)]
    ren = Renderer(proc_mesh)
    serial = [ren.render(T, K640, 480, 640) for T in poses]
    shared = Renderer(proc_mesh)  # a second, fresh renderer: its first renders run on two threads at once
    threaded = map_threads(lambda T: shared.render(T, K640, 480, 640), poses, workers=2)
    for a, b in zip(serial, threaded):
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.normals, b.normals)
        np.testing.assert_array_equal(a.tri_ids, b.tri_ids)
