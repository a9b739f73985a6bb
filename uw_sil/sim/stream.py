"""Frames of the simulated camera side by side: the render of one frame while the model of others runs.

A frame of :class:`uw_sil.sim.simcam.SimCamera` is three steps: :meth:`~SimCamera.plan` (the parameters and
random draws, in the caller's order), :meth:`~SimCamera.render_job` (the OpenGL passes: one context, one
frame at a time; the camera changes between them) and :meth:`~SimCamera.finish` (depth, shading and the
underwater model: numpy and OpenCV, which release the GIL for most of their work). :class:`FrameStream` runs
the OpenGL passes in order on a thread of their own and the rest on ``workers`` threads, and hands the frames
out in the order they were submitted. On 2 cores that overlaps the passes of one frame with the model of
others; a frame is the same as :meth:`SimCamera.render`'s, bit for bit (its draws are fixed when it is
submitted).

Examples
--------
>>> from uw_sil.sim.scene import facing_pose
>>> from uw_sil.sim.simcam import SimCamera
>>> frames = []
>>> with SimCamera() as cam, FrameStream(cam, lambda tag, frame, error: frames.append(tag)) as stream:
...     for k in range(3):
...         stream.submit(facing_pose(2.0 + k * 0.1), tag=k)
>>> frames
[0, 1, 2]
"""
from __future__ import annotations

import collections
import queue
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Optional

__all__ = ["FrameStream", "stream_frames"]


class FrameStream:
    """Pipelined frames of one :class:`uw_sil.sim.simcam.SimCamera`.

    Parameters
    ----------
    sim : SimCamera
        The camera; while the stream is open its renderer belongs to the stream's render thread (no other
        :meth:`~SimCamera.render` calls). Parameter changes take effect from the next :meth:`submit`.
    deliver : callable ``(tag, frame, error)``
        Called once per frame made, in submission order, from one of the stream's threads (never two at once):
        the :class:`~uw_sil.sim.simcam.SimFrame` and None, or None and the exception of a frame that failed.
        An exception it raises does not stop the stream; :meth:`close` raises the first.
    workers : int
        Threads running the underwater model (1: render and model overlap, models one at a time).
    max_pending : int, optional
        Every frame is made: frames submitted and not yet delivered; :meth:`submit` waits while that many are
        (default: ``workers`` + 2: one being rendered, one waiting for its render, one per model thread).
    newest_only : bool
        A live camera: :meth:`submit` never waits, a frame waiting for its render is replaced by the next one
        submitted (counted in :attr:`dropped`, not delivered), and a render starts only while fewer than
        ``workers`` + 1 frames are on their way, with the newest pose: a frame waits for no more than one model
        before its own.
    """

    def __init__(self, sim, deliver: Callable, workers: int = 2, max_pending: Optional[int] = None,
                 newest_only: bool = False):
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.sim = sim
        self.newest_only = bool(newest_only)
        self.dropped = 0
        self._deliver = deliver
        # newest_only: taken before a render starts (one per model thread and one being rendered); else: a frame
        # on its way
        self._slots = threading.BoundedSemaphore(workers + 1 if newest_only else max_pending or workers + 2)
        self._waiting: collections.deque = collections.deque()
        self._cv = threading.Condition()
        self._models = ThreadPoolExecutor(workers, thread_name_prefix="sim-model")
        self._lock = threading.Lock()
        self._ready: dict = {}
        self._rendered = 0
        self._due = 0
        self._closed = False
        self._cancel = False
        self._deliver_error = None
        self._thread = threading.Thread(target=self._render_loop, name="sim-render", daemon=True)
        self._thread.start()

    def submit(self, T_cam_panel, image: bool = True, tag=None) -> None:
        """Queue a frame (planned now: the parameters as they are and the next random draws); waits while
        ``max_pending`` frames are on their way (not with ``newest_only``)."""
        if self._closed:
            raise RuntimeError("the frame stream is closed")
        job = self.sim.plan(T_cam_panel, image)
        if not self.newest_only:
            self._slots.acquire()
        with self._cv:
            if self.newest_only and self._waiting:
                self.dropped += len(self._waiting)
                self._waiting.clear()
            self._waiting.append((job, tag))
            self._cv.notify()

    def close(self, cancel: bool = False) -> None:
        """Deliver every submitted frame (``cancel``: only those whose render has begun, e.g. at shutdown), then
        stop the threads; raises the first exception ``deliver`` raised."""
        if self._closed:
            return
        with self._cv:
            self._closed = True
            self._cancel = cancel
            self._cv.notify()
        self._thread.join()
        self._models.shutdown(wait=True)
        if self._deliver_error is not None:
            raise self._deliver_error

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ------------------------------------------------------------------ threads

    def _next_job(self):
        """The next frame to render, or None once closed and nothing (more) is to be rendered."""
        with self._cv:
            while not self._waiting and not self._closed:
                self._cv.wait()
            if self._cancel:
                dropped = len(self._waiting)
                self._waiting.clear()
                if not self.newest_only:
                    for _ in range(dropped):
                        self._slots.release()
            return self._waiting.popleft() if self._waiting else None

    def _render_loop(self):
        while True:
            if self.newest_only:
                self._slots.acquire()            # a model thread will be free about when this render is done
            item = self._next_job()
            if item is None:
                if self.newest_only:
                    self._slots.release()
                return
            job, tag = item
            seq = self._rendered
            self._rendered += 1
            try:
                rendered = self.sim.render_job(job)
            except Exception as e:                 # noqa: BLE001 - handed to deliver with its frame
                self._done(seq, tag, None, e)
                continue
            self._models.submit(self._finish, seq, tag, rendered)

    def _finish(self, seq, tag, rendered):
        try:
            frame, error = self.sim.finish(*rendered), None
        except Exception as e:                     # noqa: BLE001 - handed to deliver with its frame
            frame, error = None, e
        self._done(seq, tag, frame, error)

    def _done(self, seq, tag, frame, error):
        with self._lock:
            self._ready[seq] = (tag, frame, error)
            while self._due in self._ready:
                tag_, frame_, error_ = self._ready.pop(self._due)
                self._due += 1
                try:
                    self._deliver(tag_, frame_, error_)
                except Exception as e:             # noqa: BLE001 - the next frames are still delivered
                    self._deliver_error = self._deliver_error or e
                finally:
                    self._slots.release()


def stream_frames(sim, poses, image: bool = True, workers: int = 2):
    """The frames of ``poses`` in order, made side by side by a :class:`FrameStream` (a generator: at most a few
    frames ahead of the consumer; the same frames as ``sim.render`` of each pose in turn)."""
    out: queue.Queue = queue.Queue(maxsize=workers + 2)
    stop = threading.Event()

    def feed():
        try:
            with FrameStream(sim, lambda tag, frame, error: out.put((frame, error)), workers=workers) as stream:
                for T in poses:
                    if stop.is_set():
                        break
                    stream.submit(T, image=image)
        except Exception as e:                     # noqa: BLE001 - raised in the consumer
            out.put((None, e))
        out.put(None)

    feeder = threading.Thread(target=feed, name="sim-feed", daemon=True)
    feeder.start()
    try:
        while (item := out.get()) is not None:
            frame, error = item
            if error is not None:
                raise error
            yield frame
    finally:
        stop.set()
        while feeder.is_alive():                   # let the feeder finish its frames (nobody takes them)
            try:
                out.get(timeout=0.1)
            except queue.Empty:
                pass
