"""Bundle adjustment in a child process, for the threaded SLAM.

gtsam holds the GIL while it builds and solves a graph (~0.5 s for a local BA of 15k observations), so a mapper
thread that solves in-process stalls the tracker for that long. Solved in a child process, the mapper thread only
waits on a pipe (GIL released) and the tracker runs on. The child is started once per run (spawned: a forked child
would inherit torch's thread pools) and receives plain arrays: `bundle_adjustment`'s arguments and result.
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

import numpy as np

from ruslam.slam.bundle_adjustment import bundle_adjustment


def _limit_blas(threads: int | None) -> None:
    if threads is not None:
        from threadpoolctl import threadpool_limits  # noqa: PLC0415 (child process only)

        threadpool_limits(threads, user_api="blas")


class SolverProcess:
    """A callable with `bundle_adjustment`'s signature that solves in one persistent child process."""

    def __init__(self, blas_threads: int | None = 1):
        self.pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                                        initializer=_limit_blas, initargs=(blas_threads,))
        self.pool.submit(int)  # start the child now (~1 s to spawn and import), while the map initialises

    def __call__(self, *args, **kwargs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        try:
            return self.pool.submit(bundle_adjustment, *args, **kwargs).result()
        except BrokenProcessPool as err:
            raise RuntimeError("The bundle-adjustment process died (out of memory or killed); run the SLAM with "
                               "`synchronous: true` or `mapping_process: false` to solve in-process.") from err

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)
