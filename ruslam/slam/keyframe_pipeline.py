"""What happens to a new keyframe after tracking (local mapping, then loop closing: the order `system.run` gives),
run inline or in one worker thread. The thin threading layer over the synchronous mapping and loop-closing logic.

The tracker sees only `insert_keyframe` and `idle`; `run` calls `catch_up` between frames and `finish` at the end.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable

from ruslam.slam.map import KeyFrame

log = logging.getLogger(__name__)


class KeyframePipeline:
    """Inline: each keyframe is processed before the tracker sees the next frame (reproducible; used by tests)."""

    def __init__(self, process: Callable[[KeyFrame], None]):
        self.process = process

    def insert_keyframe(self, kf: KeyFrame) -> None:
        self.process(kf)

    def idle(self) -> bool:
        return True

    def interrupt(self) -> None:
        """Ask a running local BA to stop early (ORB-SLAM's InterruptBA); nothing runs inline."""

    def catch_up(self, backlog: int) -> None:
        """Wait until at most `backlog` keyframes are queued or being processed (nothing to wait for inline)."""

    def finish(self) -> None:
        """Wait for queued work (nothing to wait for inline)."""


class ThreadedKeyframePipeline(KeyframePipeline):
    """The same processing in a worker thread: `insert_keyframe` queues and returns.

    The tracker runs on while a keyframe is mapped (the BA solve holds no lock), and calls `catch_up` between
    frames: a tracker far ahead of its mapper tracks against a map without the newest points and gets lost.
    """

    def __init__(self, process: Callable[[KeyFrame], None], interrupt: Callable[[], None] | None = None):
        super().__init__(process)
        self.interrupt_ba = interrupt  # e.g. `SolverProcess.interrupt`; None: the BA runs to its end
        self.queue: queue.Queue[KeyFrame | None] = queue.Queue()
        self.pending = 0  # keyframes queued or being processed
        self.done = threading.Condition()
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, name="local-mapping", daemon=True)
        self.thread.start()

    def insert_keyframe(self, kf: KeyFrame) -> None:
        with self.done:
            self.pending += 1
        self.queue.put(kf)

    def idle(self) -> bool:
        return self.pending == 0

    def interrupt(self) -> None:
        if self.interrupt_ba is not None and not self.idle():
            self.interrupt_ba()

    def catch_up(self, backlog: int) -> None:
        with self.done:
            self.done.wait_for(lambda: self.pending <= backlog or not self.thread.is_alive())

    def _run(self) -> None:
        while (kf := self.queue.get()) is not None:
            try:
                self.process(kf)
            except Exception as err:  # noqa: BLE001 (reported by finish(), never lost in the thread)
                log.exception("Keyframe processing failed on %s.", kf)
                self.error = err
            finally:
                with self.done:
                    self.pending -= 1
                    self.done.notify_all()

    def finish(self) -> None:
        self.queue.put(None)
        self.thread.join()
        if self.error is not None:
            raise RuntimeError(f"Keyframe thread (local mapping, loop closing) failed: {self.error}") from self.error
