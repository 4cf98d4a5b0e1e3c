"""The ``pixie`` command (``pixie = pixie.__main__:main``; also ``python -m pixie``).

The thread policy (:mod:`pixie.threads`) goes into the environment first, before numpy, torch or OpenCV are
imported: OpenMP reads ``OMP_WAIT_POLICY`` and ``OMP_NUM_THREADS`` once, when it loads.
"""

from __future__ import annotations

import sys

from pixie.threads import configure_env, imports_without_gc, threads_from_argv

configure_env(threads_from_argv(sys.argv[1:]))

with imports_without_gc():  # torch + pixie: ~0.25 s less start-up (pixie.threads)
    from pixie.app.cli import main  # noqa: E402  (after the thread environment is set)

__all__ = ["main"]

if __name__ == "__main__":
    sys.exit(main())
