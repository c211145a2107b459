"""The next view's render, made while this one is observed.

A view's Top-K render depends on the map, its camera and the raster settings only
(``view_step.render_view``), not on its regions or on the views before it. The accumulator's
per-view work is a render whose kernels use both cores, then observations on one core (their
pass over the view's Top-K entries is serial); rendering the next queued view on a second thread
meanwhile keeps the second core busy. Each view's observations are those of the same render,
bit for bit: only when it is made changes. The two threads run at once because the render's
and the observations' numba kernels are compiled with ``nogil=True`` and the C kernels are
called through ctypes: none holds the interpreter lock while it computes. The offline runs
(``pipeline.offline``) do the same: the next view rendered while this one's regions, features
and observations are made.

Safe only where numba's threading layer takes parallel kernels from two threads at once (``omp``
or ``tbb``; ``workqueue`` aborts the process): ``RenderAhead.available`` says so, and elsewhere
nothing is rendered ahead. A render that failed ahead is not reported here: the view is rendered
again in the foreground, where its error is handled as it always was.
"""

from __future__ import annotations

import logging
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np
from numba import njit, prange

from ..scene import Camera, Gaussians
from .table import Method
from .view_step import ViewRender, render_view

log = logging.getLogger(__name__)
SAFE_LAYERS = ("omp", "tbb")  # numba threading layers that are thread-safe


@njit(parallel=True, cache=True)
def _choose_layer(values):
    """A parallel kernel that does nothing useful: running it makes numba choose its layer."""
    for i in prange(values.shape[0]):
        values[i] = i


def _same_camera(a: Camera, b: Camera) -> bool:
    return (
        a.name == b.name
        and (a.width, a.height) == (b.width, b.height)
        and np.array_equal(a.K, b.K)
        and np.array_equal(a.world_from_camera, b.world_from_camera)
    )


class RenderAhead:
    """Views rendered ahead, in the order they will be taken, on one worker thread with
    ``threads`` numba threads (the setting is per calling thread; 0 = numba's default, None =
    the creating thread's). At most
    ``MAX_PENDING`` at a time: the view in hand's (started in the turn before) and the next one's."""

    MAX_PENDING = 2

    def __init__(self, gaussians: Gaussians, method: Method, threads: int | None = None):
        import numba

        self.gaussians, self.method = gaussians, method
        self.threads = numba.get_num_threads() if threads is None else threads  # None: the caller's
        self.pool: ThreadPoolExecutor | None = None
        self.pending: list[tuple[Camera, Future[ViewRender]]] = []  # oldest first
        self.used = self.missed = 0  # renders taken from ahead / started ahead and not taken

    @staticmethod
    def available() -> bool:
        """Whether parallel kernels may run on two threads at once here: numba's threading
        layer, chosen when the first parallel kernel runs (one is run here if none has)."""
        import numba

        _choose_layer(np.zeros(2, np.int64))
        return numba.threading_layer() in SAFE_LAYERS

    def _init_worker(self) -> None:
        if self.threads > 0:
            import numba

            numba.set_num_threads(min(self.threads, numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]

    def start(self, camera: Camera) -> None:
        """Render ``camera``'s view on the worker after those pending, unless it is pending
        already; with ``MAX_PENDING`` pending the oldest is dropped (its view was passed over)."""
        if any(_same_camera(c, camera) for c, _ in self.pending):
            return
        if len(self.pending) >= self.MAX_PENDING:
            self._drop(1)
        if self.pool is None:
            self.pool = ThreadPoolExecutor(1, thread_name_prefix="render-ahead", initializer=self._init_worker)
        self.pending.append((camera, self.pool.submit(render_view, self.gaussians, camera, self.method)))

    def take(self, camera: Camera) -> ViewRender | None:
        """The render of ``camera``'s view when it was started ahead (waiting for it to end), else
        None: the caller renders it. Views are taken in the order they were started, so renders
        pending before this one are dropped (their views were passed over: refused, duplicates);
        those after it stay."""
        at = next((i for i, (c, _) in enumerate(self.pending) if _same_camera(c, camera)), None)
        if at is None:
            return None
        self._drop(at)
        _, future = self.pending.pop(0)
        try:
            view = future.result()
        except Exception as exc:  # rendered again in the foreground, where its error is handled
            log.debug("the render ahead of view %s failed (%s): rendering it again", camera.name, exc)
            self.missed += 1
            return None
        self.used += 1
        return view

    def _drop(self, count: int) -> None:
        """Drop the ``count`` oldest pending renders: one not started never runs; a running one
        ends and its result is discarded."""
        for _, future in self.pending[:count]:
            future.cancel()
        del self.pending[:count]
        self.missed += count

    def close(self) -> None:
        """Stop the worker (a render under way ends first: the kernels cannot be interrupted)."""
        self._drop(len(self.pending))
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)
            self.pool = None
