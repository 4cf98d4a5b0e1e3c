"""Spread per-item work over Ray workers (optional: ``pip install "pixie-pose[ray]"``).

Used by ``pixie run --ray`` and ``pixie estimate --batch ... --ray``. The driver prepares everything that is
built once (reference sets, saved to files) and hands workers a :class:`WorkerSpec`: a module-level ``setup``
function that loads what a worker keeps (estimators, from those files) and a module-level ``process`` function
that turns one item into one JSON-able record. Items are handed out one at a time as workers finish, and
records come back to the driver, which alone writes outputs (so a run stays resumable and its files whole).

Results equal a serial run's bit for bit when both run with the same torch/OpenCV thread count
(:func:`pixie.threads.set_threads`; ``--threads``, default 1): every random choice in the pipeline has a fixed seed per call.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

from pixie.errors import PixieError
from pixie.threads import set_threads

__all__ = ["WorkerSpec", "set_threads", "init_ray", "ray_map", "serial_map"]


@dataclass(frozen=True)
class WorkerSpec:
    """What a worker runs: ``state = setup(args)`` once, then ``process(state, item) -> record`` per item.

    ``setup`` and ``process`` must be module-level functions (workers import them by name).
    """

    setup: Callable[[dict], Any]
    process: Callable[[Any, Any], dict]
    args: dict = field(default_factory=dict)
    threads: int = 1


def serial_map(spec: WorkerSpec, items: Sequence[Any], on_result: Callable[[int, dict], None]) -> None:
    """Run ``spec`` over ``items`` in this process, calling ``on_result(index, record)`` after each."""
    before = set_threads(spec.threads)
    try:
        state = spec.setup(spec.args)
        for i, item in enumerate(items):
            on_result(i, spec.process(state, item))
    finally:
        set_threads(before)


def init_ray(address: str | None = None, num_cpus: int | None = None):
    """Import Ray and connect: to ``address`` (``auto``, ``HOST:PORT`` or ``ray://HOST:10001``) or a new local one.

    Raises
    ------
    PixieError
        When Ray is not installed.
    """
    try:
        import ray
    except ImportError as exc:
        raise PixieError('--ray needs Ray, an optional dependency: pip install "pixie-pose[ray]"') from exc
    if not ray.is_initialized():
        kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": True}
        if address:
            kwargs["address"] = address
        elif num_cpus is not None:
            kwargs["num_cpus"] = num_cpus
        ray.init(**kwargs)
    return ray


class _Worker:
    def __init__(self, spec: WorkerSpec):
        set_threads(spec.threads)
        self.spec = spec
        self.state = spec.setup(spec.args)

    def process(self, item: Any) -> dict:
        return self.spec.process(self.state, item)


def ray_map(spec: WorkerSpec, items: Sequence[Any], on_result: Callable[[int, dict], None],
            workers: int | None = None, address: str | None = None) -> int:
    """Run ``spec`` over ``items`` on Ray actors, calling ``on_result(index, record)`` in the driver as each ends.

    ``workers`` actors (default: the cluster's CPUs // ``spec.threads``) each reserve ``spec.threads`` CPUs.
    Items are given out dynamically, two in flight per actor. Returns the number of actors used.
    """
    if not items:
        return 0
    ray = init_ray(address)
    n = workers or max(1, int(ray.cluster_resources().get("CPU", 1)) // max(1, spec.threads))
    n = max(1, min(n, len(items)))
    actor_cls = ray.remote(num_cpus=spec.threads)(_Worker)
    actors = [actor_cls.remote(spec) for _ in range(n)]
    queue = iter(enumerate(items))
    pending: dict[Any, tuple[Any, int]] = {}

    def submit(actor: Any) -> None:
        nxt = next(queue, None)
        if nxt is not None:
            pending[actor.process.remote(nxt[1])] = (actor, nxt[0])

    try:
        for _ in range(2):
            for a in actors:
                submit(a)
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            actor, index = pending.pop(done[0])
            on_result(index, ray.get(done[0]))
            submit(actor)
    finally:
        for a in actors:
            ray.kill(a)
    return n
