"""Asynchronous disk writer (pure): matched frames → ``frames/*.jpg`` + ``depths/*.png`` (+ semantics).

ROS callbacks only enqueue (never touch the disk). The writer thread writes each file under a
temporary name and renames it into place, then appends the frame to ``completed.jsonl`` and hands
it to the consumer; so whoever reads the folder (the SLAM loop, a replay, the seed's per-frame
subprocess) only ever sees fully written frames.
"""

from __future__ import annotations

import errno
import json
import os
import queue
import re
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from semantic_gs_slam_ros.errors import OutputError
from semantic_gs_slam_ros.sync import MatchedFrame


@dataclass(frozen=True)
class WrittenFrame:
    """A frame fully on disk (paths) and in memory (arrays)."""

    index: int
    stamp: float
    rgb_path: str
    depth_path: str
    semantic_path: str | None
    frame: MatchedFrame


def write_png(path: str, array: np.ndarray) -> None:
    """uint8 [H,W(,3)] or uint16 [H,W] PNG, written atomically (tmp + rename)."""
    from PIL import Image

    tmp = path + ".tmp"
    dtype = np.uint16 if array.dtype == np.uint16 else np.uint8
    img = Image.fromarray(np.ascontiguousarray(array, dtype=dtype))  # uint16 -> mode I;16
    img.save(tmp, format="PNG", compress_level=1)
    os.replace(tmp, path)


def write_jpeg(path: str, rgb: np.ndarray, quality: int = 95) -> None:
    from PIL import Image

    tmp = path + ".tmp"
    Image.fromarray(np.ascontiguousarray(rgb)).save(tmp, format="JPEG", quality=quality)
    os.replace(tmp, path)


#: the files a run writes in each folder (``.tmp``: one being written when the last run stopped)
_OWN_FILES = {"frames": re.compile(r"frame\d{6,}\.jpg(\.tmp)?"), "depths": re.compile(r"depth\d{6,}\.png(\.tmp)?"),
              "semantics": re.compile(r"semantic\d{6,}\.png(\.tmp)?")}


def prepare_output_dir(root: str, clean: bool = True) -> None:
    """Create ``root/{frames,depths,semantics}``; with ``clean``, remove frames of an earlier run.

    Only files named as a run names them are ever removed: a folder that holds anything else there (a user's
    photos in ``frames/``) is refused, and nothing in it is touched.

    Raises:
        OutputError: the folder cannot be created or written, or holds files a run did not write.
    """
    try:
        if clean:
            foreign = [os.path.join(sub, name) for sub, own in _OWN_FILES.items()
                       if os.path.isdir(os.path.join(root, sub))
                       for name in sorted(os.listdir(os.path.join(root, sub))) if not own.fullmatch(name)]
            if foreign:
                raise OutputError(f"output directory {root!r} holds files a run did not write "
                                  f"({', '.join(foreign[:3])}{' ...' if len(foreign) > 3 else ''}); nothing was "
                                  "removed: choose an empty folder, or one an earlier run wrote")
        for sub in _OWN_FILES:
            d = os.path.join(root, sub)
            os.makedirs(d, exist_ok=True)
            if clean:
                for name in os.listdir(d):
                    os.remove(os.path.join(d, name))
        record = os.path.join(root, "completed.jsonl")
        if clean and os.path.exists(record):
            os.remove(record)
        probe = os.path.join(root, ".write_probe")
        with open(probe, "w") as fh:
            fh.write("ok")
        os.remove(probe)
    except OSError as exc:
        raise OutputError(f"output directory {root!r} is not writable: {exc.strerror or exc}") from exc


class AsyncFrameWriter:
    """Writes frames on a thread; ``submit`` never blocks.

    Args:
        root: output folder (see :func:`prepare_output_dir`).
        on_written: called on the writer thread with each :class:`WrittenFrame`.
        max_queue: frames waiting to be written; beyond it ``submit`` refuses (counted).
        start_index: index of the first frame (to continue numbering after a resume).
    """

    def __init__(self, root: str, on_written: Callable[[WrittenFrame], None], max_queue: int = 1000,
                 start_index: int = 0) -> None:
        self.root = root
        self._on_written = on_written
        self._queue: queue.Queue[MatchedFrame | None] = queue.Queue(maxsize=max_queue)
        self._next_index = start_index  # only touched by the writer thread
        self.written = 0
        self.refused = 0
        self.error: OutputError | None = None
        self._thread = threading.Thread(target=self._run, name="frame-writer", daemon=True)
        self._thread.start()

    def submit(self, frame: MatchedFrame) -> bool:
        """Queue a frame; False (and counted) if the writer failed or its queue is full."""
        if self.error is not None:
            self.refused += 1
            return False
        try:
            self._queue.put_nowait(frame)
            return True
        except queue.Full:
            self.refused += 1
            return False

    def pending(self) -> int:
        return self._queue.qsize()

    def drop_oldest(self) -> bool:
        """Take the oldest frame waiting to be written out of the queue, unwritten (a live camera's lag bound);
        False when none waits. Never blocks."""
        try:
            frame = self._queue.get_nowait()
        except queue.Empty:
            return False
        if frame is None:  # the stop request of close(): it goes back (the slot it left is free), nothing dropped
            try:
                self._queue.put_nowait(None)
            except queue.Full:  # a frame took the slot meanwhile: close() gives up on the daemon thread in time
                pass
            return False
        return True

    def close(self, timeout: float = 30.0) -> None:
        """Write what is queued, then stop the thread (waits at most ``timeout`` s). Idempotent."""
        if not self._thread.is_alive():
            return
        try:
            self._queue.put(None, timeout=timeout)
        except queue.Full:
            pass
        self._thread.join(timeout)

    def _run(self) -> None:
        record_path = os.path.join(self.root, "completed.jsonl")
        while True:
            frame = self._queue.get()
            if frame is None:
                return
            if self.error is not None:
                continue
            try:
                written = self._write(frame)
                with open(record_path, "a", encoding="utf-8") as rec:
                    rec.write(json.dumps({"index": written.index, "stamp": written.stamp,
                                          "rgb": os.path.relpath(written.rgb_path, self.root),
                                          "depth": os.path.relpath(written.depth_path, self.root)}) + "\n")
            except OSError as exc:
                why = "disk full" if exc.errno == errno.ENOSPC else (exc.strerror or str(exc))
                self.error = OutputError(f"cannot write frames to {self.root!r}: {why}")
                continue
            except Exception as exc:  # a bad frame must not kill the writer thread silently
                self.error = OutputError(f"cannot write frame to {self.root!r}: {exc}")
                continue
            self.written += 1
            self._on_written(written)

    def _write(self, frame: MatchedFrame) -> WrittenFrame:
        i = self._next_index
        rgb_path = os.path.join(self.root, "frames", f"frame{i:06d}.jpg")
        depth_path = os.path.join(self.root, "depths", f"depth{i:06d}.png")
        write_jpeg(rgb_path, frame.rgb)
        write_png(depth_path, frame.depth)
        sem_path = None
        if frame.semantic is not None:
            sem_path = os.path.join(self.root, "semantics", f"semantic{i:06d}.png")
            sem = np.asarray(frame.semantic)
            write_png(sem_path, sem.astype(np.uint16) if sem.max(initial=0) > 255 else sem.astype(np.uint8))
        self._next_index += 1
        return WrittenFrame(i, frame.stamp, rgb_path, depth_path, sem_path, frame)
