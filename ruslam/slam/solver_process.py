"""Bundle adjustment in a child process, for the threaded SLAM.

gtsam holds the GIL while it builds and solves a graph (~0.5 s for a local BA of 15k observations), so a mapper
thread that solves in-process stalls the tracker that long. Solved in a child process, the mapper thread only waits
on a pipe (GIL released) and the tracker runs on. The child is a plain Python running `main` below: it reads
pickled `bundle_adjustment` arguments on stdin and writes the result on stdout (multiprocessing's spawn would
re-import the caller's main script in the child, torch included: 590 MB resident instead of 124 MB).

The tracker's interrupt is one byte of a memory-mapped, already unlinked temporary file that both processes map
and the child's LM loop reads. (It was a SIGUSR1 whose handler set a `threading.Event`: a signal landing while the
child cleared that event re-entered its lock, or one landing before the child had installed the handler killed it,
and the SLAM hung or failed.)
"""

from __future__ import annotations

import mmap
import pickle
import subprocess
import sys
import tempfile
import threading

import numpy as np


class SolverProcess:
    """A callable with `bundle_adjustment`'s signature that solves in one persistent child process."""

    def __init__(self, blas_threads: int | None = 1):
        self.stop_file = tempfile.TemporaryFile()
        self.stop_file.write(b"\0")
        self.stop_file.flush()
        fd = self.stop_file.fileno()
        self.stop = mmap.mmap(fd, 1)  # byte 0: 1 = return after the current LM iteration
        command = [sys.executable, "-c", "from ruslam.slam.solver_process import main; main()", str(fd),
                   str(blas_threads or 0)]
        self.process = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, pass_fds=(fd,))
        self.lock = threading.Lock()  # one problem at a time (the mapper thread; the tracker's initial BA)

    def __call__(self, *args, **kwargs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        with self.lock:
            self.stop[0] = 0
            try:
                pickle.dump((args, kwargs), self.process.stdin, protocol=pickle.HIGHEST_PROTOCOL)
                self.process.stdin.flush()
                ok, result = pickle.load(self.process.stdout)
            except (EOFError, OSError, pickle.UnpicklingError) as err:
                raise RuntimeError(f"The bundle-adjustment process died (exit code {self.process.poll()}); run the "
                                   "SLAM with `synchronous: true` or `solver_process: false` to solve in-process.") \
                    from err
        if not ok:
            raise RuntimeError(f"Bundle adjustment failed in the solver process: {result}")
        return result

    def interrupt(self) -> None:
        """Ask the solve in flight to return after its current LM iteration (ORB-SLAM's InterruptBA: the tracker
        wants a keyframe); nothing when the child is idle."""
        if self.lock.locked():
            self.stop[0] = 1

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.stdin.close()  # the child ends at end of input
            try:
                self.process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.process.stdout.close()
        self.stop.close()
        self.stop_file.close()


def main() -> None:
    """The child: solve each problem read from stdin until it closes."""
    from threadpoolctl import threadpool_limits  # noqa: PLC0415 (the child only)

    from ruslam.slam.bundle_adjustment import bundle_adjustment  # noqa: PLC0415

    fd, blas_threads = int(sys.argv[1]), int(sys.argv[2])
    if blas_threads:
        threadpool_limits(blas_threads, user_api="blas")
    stop = mmap.mmap(fd, 1)  # set by `SolverProcess.interrupt`, cleared by the parent for each problem
    requests, results = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # a print or log line must never land in the result pipe
    while True:
        try:
            args, kwargs = pickle.load(requests)
        except EOFError:
            return
        try:
            reply = (True, bundle_adjustment(*args, should_stop=lambda: stop[0] != 0, **kwargs))
        except Exception as err:  # noqa: BLE001 (sent to the parent, which raises it)
            reply = (False, f"{type(err).__name__}: {err}")
        pickle.dump(reply, results, protocol=pickle.HIGHEST_PROTOCOL)
        results.flush()
