"""Unit tests of the streaming core (no ROS): image conversion, timestamp matching, lag, disk writer."""

import json
import os
import re
import threading
from types import SimpleNamespace

import numpy as np
import pytest

from semantic_gs_slam_ros.errors import ImageFormatError, OutputError
from semantic_gs_slam_ros.images import (
    array_to_image_fields,
    depth_to_mm,
    image_to_array,
    resize_nearest,
    resize_rgb,
    rgb_of,
)
from semantic_gs_slam_ros.lag import LagAction, LagController
from semantic_gs_slam_ros.sync import FrameMatcher
from semantic_gs_slam_ros.writer import AsyncFrameWriter, prepare_output_dir


def msg(array, encoding):
    return SimpleNamespace(**array_to_image_fields(array, encoding))


# --- images -------------------------------------------------------------------------------------

@pytest.mark.parametrize("encoding, shape, dtype", [("rgb8", (4, 5, 3), np.uint8), ("rgba8", (4, 5, 4), np.uint8),
                                                    ("32FC1", (4, 5), np.float32), ("16UC1", (4, 5), np.uint16),
                                                    ("mono8", (4, 5), np.uint8)])
def test_image_round_trip(encoding, shape, dtype):
    a = (np.arange(np.prod(shape)) % 250).reshape(shape).astype(dtype)
    assert np.array_equal(image_to_array(msg(a, encoding)), a)


def test_a_sensor_msgs_image_takes_the_fields_and_round_trips():
    """The fields build a real ``sensor_msgs/Image``; ``data`` is an array('B'), which the message takes as it is
    (a ``bytes`` value is checked element by element in Python: 5 ms for a 320 x 240 colour image)."""
    import array

    from sensor_msgs.msg import Image

    a = (np.arange(240 * 320 * 3) % 250).reshape(240, 320, 3).astype(np.uint8)
    fields = array_to_image_fields(a, "rgb8")
    assert isinstance(fields["data"], array.array) and fields["data"].typecode == "B"
    assert np.array_equal(image_to_array(Image(**fields)), a)
    d = np.linspace(0.5, 4.0, 240 * 320, dtype=np.float32).reshape(240, 320)
    assert np.array_equal(image_to_array(Image(**array_to_image_fields(d, "32FC1"))), d)


def test_bgr_is_converted_and_row_padding_removed():
    rgb = np.random.default_rng(0).integers(0, 255, (3, 5, 3), dtype=np.uint8)
    bgr = rgb[..., ::-1]
    padded = np.zeros((3, 16 + 4), np.uint8)
    padded[:, :15] = bgr.reshape(3, 15)
    m = SimpleNamespace(height=3, width=5, encoding="bgr8", is_bigendian=0, step=20, data=padded.tobytes())
    assert np.array_equal(image_to_array(m), rgb)


def test_big_endian_depth():
    d = np.array([[1.5, 2.0]], np.float32)
    m = SimpleNamespace(height=1, width=2, encoding="32FC1", is_bigendian=1, step=8, data=d.astype(">f4").tobytes())
    assert np.array_equal(image_to_array(m), d)


@pytest.mark.parametrize("fields, message", [({"encoding": "yuv422"}, "unsupported image encoding"),
                                             ({"data": b"\x00" * 10}, "expected"),
                                             ({"step": 2}, "bad image geometry"),
                                             ({"height": 0}, "bad image geometry")])
def test_bad_images_are_clear_errors(fields, message):
    m = msg(np.zeros((4, 5), np.float32), "32FC1")
    for k, v in fields.items():
        setattr(m, k, v)
    with pytest.raises(ImageFormatError, match=message):
        image_to_array(m)


def test_depth_metres_to_millimetres_marks_invalid_as_zero():
    d = np.array([[1.2345, np.nan, np.inf], [-1.0, 0.0, 70.0]], np.float32)
    assert depth_to_mm(d).tolist() == [[1234, 0, 0], [0, 0, 0]] or depth_to_mm(d).tolist() == [[1235, 0, 0], [0, 0, 0]]
    assert depth_to_mm(d).dtype == np.uint16
    assert depth_to_mm(np.array([[1.0]]), scale=5000.0).tolist() == [[5000]]
    already = np.array([[7]], np.uint16)
    assert depth_to_mm(already) is already


def test_resizes():
    ids = np.array([[1, 2], [3, 4]], np.uint8)
    assert resize_nearest(ids, 4, 4).tolist() == [[1, 1, 2, 2], [1, 1, 2, 2], [3, 3, 4, 4], [3, 3, 4, 4]]
    flat = np.full((10, 20, 3), 77, np.uint8)
    out = resize_rgb(flat, 12, 7)
    assert out.shape == (7, 12, 3) and (out == 77).all()
    ramp = np.tile(np.linspace(0, 255, 40).astype(np.uint8)[None, :, None], (4, 1, 3))
    small = resize_rgb(ramp, 20, 2)
    assert (np.diff(small[0, :, 0].astype(int)) >= 0).all()
    assert rgb_of(np.zeros((2, 2), np.uint8)).shape == (2, 2, 3)


# --- matching ---------------------------------------------------------------------------------

def test_in_order_pairs():
    m = FrameMatcher(tolerance=0.01)
    out = []
    for i in range(5):
        out += m.push("rgb", i * 0.1, f"c{i}")
        out += m.push("depth", i * 0.1 + 0.004, f"d{i}")
    assert [(f.rgb, f.depth) for f in out] == [(f"c{i}", f"d{i}") for i in range(5)]
    assert m.stats.matched == 5 and sum(m.stats.dropped.values()) == 0


def test_out_of_order_and_missing_depth_never_mispair():
    now = [0.0]
    m = FrameMatcher(tolerance=0.01, max_wait=0.35, clock=lambda: now[0])
    out = []
    # depth of frame 1 is missing, depth of frame 3 arrives before its colour, frame 2's colour late;
    # images arrive 0.1 s apart (wall clock)
    events = [("rgb", 0.0, "c0"), ("depth", 0.0, "d0"), ("rgb", 0.1, "c1"), ("depth", 0.3, "d3"),
              ("depth", 0.2, "d2"), ("rgb", 0.3, "c3"), ("rgb", 0.2, "c2"), ("rgb", 0.6, "c6"), ("depth", 0.6, "d6")]
    for s, t, v in events:
        now[0] += 0.1
        out += m.push(s, t, v)
    pairs = [(f.rgb, f.depth) for f in out]
    assert sorted(pairs) == [("c0", "d0"), ("c2", "d2"), ("c3", "d3"), ("c6", "d6")]
    assert m.stats.dropped["rgb"] == 1  # c1 waited longer than max_wait
    assert all(p[0][1:] == p[1][1:] for p in pairs)


def test_fast_replay_is_not_dropped():
    """A recording sent much faster than real time (stamps 1 s apart, arriving at once) all matches,
    whatever the interleaving of the topics."""
    m = FrameMatcher(tolerance=0.01, use_semantic=True, clock=lambda: 0.0)
    out = []
    for i in range(10):
        out += m.push("depth", float(i + 1), i)
        out += m.push("semantic", float(i + 1), i)
    for i in reversed(range(10)):
        out += m.push("rgb", float(i + 1), i)
    assert sorted((f.rgb, f.depth, f.semantic) for f in out) == [(i, i, i) for i in range(10)]


def test_ambiguous_match_is_not_forced():
    m = FrameMatcher(tolerance=0.05)
    m.push("rgb", 0.00, "c0")
    m.push("rgb", 0.04, "c1")
    out = m.push("depth", 0.035, "d1")  # nearest colour is c1, not c0
    assert [(f.rgb, f.depth) for f in out] == [("c1", "d1")]


def test_semantic_stream_required_when_enabled():
    m = FrameMatcher(tolerance=0.01, use_semantic=True)
    assert m.push("rgb", 1.0, "c") == [] and m.push("depth", 1.0, "d") == []
    out = m.push("semantic", 1.001, "s")
    assert [(f.rgb, f.depth, f.semantic) for f in out] == [("c", "d", "s")]
    with pytest.raises(ValueError):
        FrameMatcher().push("semantic", 0.0, "s")


def test_flush_and_duplicates_are_counted():
    m = FrameMatcher()
    m.push("rgb", 1.0, "a")
    m.push("rgb", 1.0, "b")
    m.flush()
    assert m.stats.duplicates == 1 and m.stats.dropped["rgb"] == 1 and m.pending() == {"rgb": 0, "depth": 0}


# --- lag ------------------------------------------------------------------------------------------

def test_lag_hysteresis():
    lag = LagController(high=300, low=150)
    seq = [10, 301, 302, 200, 151, 149, 160, 301]
    acts = [lag.update(b) for b in seq]
    assert acts == [LagAction.NONE, LagAction.UNSUBSCRIBE, LagAction.NONE, LagAction.NONE, LagAction.NONE,
                    LagAction.RESUBSCRIBE, LagAction.NONE, LagAction.UNSUBSCRIBE]
    assert lag.pauses == 2
    with pytest.raises(ValueError):
        LagController(high=10, low=10)


# --- writer ---------------------------------------------------------------------------------------

def test_writer_writes_complete_frames_in_order(tmp_path):
    from PIL import Image

    from semantic_gs_slam_ros.sync import MatchedFrame

    prepare_output_dir(str(tmp_path))
    done, got = threading.Event(), []

    def on_written(w):
        got.append(w)
        if len(got) == 3:
            done.set()

    writer = AsyncFrameWriter(str(tmp_path), on_written)
    rgb = np.full((6, 8, 3), 120, np.uint8)
    for i in range(3):
        depth = np.full((6, 8), 1000 + i, np.uint16)
        assert writer.submit(MatchedFrame(i * 0.1, rgb, depth, np.full((6, 8), 7, np.uint8)))
    assert done.wait(10)
    writer.close()
    assert [w.index for w in got] == [0, 1, 2]
    assert np.array(Image.open(got[2].depth_path)).tolist() == np.full((6, 8), 1002).tolist()
    assert np.array(Image.open(got[0].semantic_path)).max() == 7
    records = [json.loads(line) for line in open(tmp_path / "completed.jsonl")]
    assert [r["index"] for r in records] == [0, 1, 2] and records[1]["depth"] == "depths/depth000001.png"
    assert not [f for f in os.listdir(tmp_path / "frames") if f.endswith(".tmp")]


def test_clean_start_and_unwritable_directory(tmp_path):
    (tmp_path / "frames").mkdir()
    (tmp_path / "depths").mkdir()
    (tmp_path / "frames" / "frame000000.jpg").write_text("x")  # an earlier run's
    (tmp_path / "depths" / "depth000003.png.tmp").write_text("x")
    (tmp_path / "completed.jsonl").write_text("{}\n")
    prepare_output_dir(str(tmp_path))
    assert os.listdir(tmp_path / "frames") == [] and os.listdir(tmp_path / "depths") == []
    assert not (tmp_path / "completed.jsonl").exists()
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(OutputError, match="not writable"):
        prepare_output_dir(str(blocker / "sub"))


def test_a_folder_with_files_a_run_did_not_write_is_refused_and_left_as_it_is(tmp_path):
    (tmp_path / "frames").mkdir()
    (tmp_path / "frames" / "frame000000.jpg").write_text("a run's")
    (tmp_path / "frames" / "holiday_photo.jpg").write_text("a person's")
    (tmp_path / "completed.jsonl").write_text("{}\n")
    with pytest.raises(OutputError, match=r"holds files a run did not write \(frames/holiday_photo.jpg\); nothing "
                                          "was removed"):
        prepare_output_dir(str(tmp_path))
    assert sorted(os.listdir(tmp_path / "frames")) == ["frame000000.jpg", "holiday_photo.jpg"]
    assert (tmp_path / "completed.jsonl").exists() and not (tmp_path / "depths").exists()
    prepare_output_dir(str(tmp_path), clean=False)  # a resumed run removes nothing, so it may share the folder


@pytest.mark.parametrize("field, value, words", [
    ("sync_tolerance", float("nan"), "sync_tolerance must be a finite number >= 0, got nan"),
    ("sync_max_wait", -1.0, "sync_max_wait must be a finite number >= 0"),
    ("depth_scale", 0.0, "depth_scale must be a finite number > 0"),
    ("lag_low", 500, "0 <= lag_low < lag_high, got 500 and 300"),
    ("width", -5, "width and height must be >= 0"),
])
def test_session_settings_that_cannot_work_are_refused(tmp_path, field, value, words):
    from semantic_gs_slam_ros.errors import StreamingError
    from semantic_gs_slam_ros.session import SessionConfig

    with pytest.raises(StreamingError, match=re.escape(words)):
        SessionConfig(work_dir=str(tmp_path), **{field: value})


@pytest.mark.parametrize("text, words", [
    ("[" * 100_000, "must be JSON"),
    ('{"99999999999999999999999": "chair"}', "ids are whole numbers 0 .. 2^31 - 1"),
    ('{"-1": "chair"}', "ids are whole numbers"),
    ('{"1": {"a": 1}}', "names strings of at most 256 characters"),
])
def test_semantic_classes_of_the_wrong_shape_are_refused(text, words):
    from semantic_gs_slam_ros.errors import StreamingError
    from semantic_gs_slam_ros.run_gs_slam_server import parse_classes

    with pytest.raises(StreamingError, match=re.escape(words)):
        parse_classes(text)
    assert parse_classes('{"0": "void", "1": "chair", "7": "cup"}') == {0: "void", 1: "chair", 7: "cup"}


def test_writer_failure_is_reported_not_raised(tmp_path):
    from semantic_gs_slam_ros.sync import MatchedFrame

    prepare_output_dir(str(tmp_path))
    writer = AsyncFrameWriter(str(tmp_path), lambda w: None)
    os.rmdir(tmp_path / "depths")
    (tmp_path / "depths").write_text("now a file")  # writing into it fails
    writer.submit(MatchedFrame(0.0, np.zeros((2, 2, 3), np.uint8), np.zeros((2, 2), np.uint16)))
    writer.close()
    assert writer.error is not None and "cannot write frames" in str(writer.error)
    assert not writer.submit(MatchedFrame(0.1, np.zeros((2, 2, 3), np.uint8), np.zeros((2, 2), np.uint16)))
    assert writer.refused == 1


def test_session_drops_malformed_images_and_keeps_running(tmp_path):
    """A colour image on the depth topic is refused with a clear error; the run is not ended."""
    from semantic_gs_slam_ros.session import SessionConfig, StreamingSession

    session = StreamingSession(SessionConfig(work_dir=str(tmp_path), width=0, height=0, checkpoint_every=0), None)
    with pytest.raises(ImageFormatError, match="depth image must be single-channel"):
        session.on_image("depth", 0.0, np.zeros((4, 4, 3), np.uint8))
    session.on_image("depth", 0.0, np.ones((4, 4), np.float32))
    session.on_image("rgb", 0.0, np.zeros((4, 4, 3), np.uint8))
    session.data_transfer_done()
    result = session.run()
    assert result.success and result.frames_processed == 1 and "recorded 1 frames" in result.message


class RecordingEngine:
    """A SlamEngine that records what the session gives it (the session is what is tested here)."""

    def __init__(self) -> None:
        self.frames: list[tuple[float, np.ndarray | None]] = []

    def add_frame(self, rgb, depth, semantics, timestamp, odom_c2w=None):
        self.frames.append((timestamp, odom_c2w))
        return np.eye(4) if odom_c2w is None else odom_c2w

    def save_map(self, out_dir):
        os.makedirs(out_dir, exist_ok=True)
        for name in ("params.npz", "semantic.json"):
            with open(os.path.join(out_dir, name), "w") as fh:
                fh.write("{}")
        return os.path.join(out_dir, "params.npz"), os.path.join(out_dir, "semantic.json")

    def save_checkpoint(self, ckpt_dir):
        pass

    num_gaussians = 0


def pose_at(x: float, yaw_deg: float = 0.0) -> np.ndarray:
    a = np.radians(yaw_deg)
    m = np.eye(4)
    m[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    m[0, 3] = x
    return m


def send(session, stamp: float) -> None:
    session.on_image("depth", stamp, np.ones((4, 4), np.float32))
    session.on_image("rgb", stamp, np.zeros((4, 4, 3), np.uint8))


def test_session_pairs_odometry_by_stamp_skips_still_frames_and_ignores_images_after_done(tmp_path):
    from semantic_gs_slam_ros.errors import StreamingError
    from semantic_gs_slam_ros.session import SessionConfig, StreamingSession

    cfg = SessionConfig(work_dir=str(tmp_path), width=0, height=0, checkpoint_every=0, use_odometry=True,
                        min_motion_m=0.05, min_motion_deg=5.0, sync_tolerance=0.02)
    engine = RecordingEngine()
    session = StreamingSession(cfg, engine)
    poses = {1.0: pose_at(0.0), 2.0: pose_at(0.01), 3.0: pose_at(0.2), 4.0: pose_at(0.21, 10.0)}
    for t, p in poses.items():
        session.on_odometry(t + 0.005, p)  # within sync_tolerance of the frame
    with pytest.raises(StreamingError, match="finite"):
        session.on_odometry(9.0, np.full((4, 4), np.nan))
    for t in (1.0, 2.0, 3.0, 4.0):
        send(session, t)
    session.data_transfer_done()
    send(session, 5.0)  # a live camera goes on: not this run's
    result = session.run()
    assert result.success
    stamps = [t for t, _ in engine.frames]
    assert stamps == [1.0, 3.0, 4.0]  # 2.0 moved 1 cm and did not turn: skipped
    for t, odom in engine.frames:
        np.testing.assert_array_equal(odom, poses[t])
    p = session.progress()
    assert p.still == 1 and p.after_done == 2 and p.with_odometry == 3
    assert p.backlog == 0  # a frame skipped as still is done with: a robot standing still never fills the backlog


def test_session_tracks_a_frame_without_odometry_when_none_is_near_its_stamp(tmp_path, monkeypatch):
    import semantic_gs_slam_ros.session as session_mod
    from semantic_gs_slam_ros.session import SessionConfig, StreamingSession

    monkeypatch.setattr(session_mod, "ODOMETRY_WAIT", 0.05)
    engine = RecordingEngine()
    session = StreamingSession(SessionConfig(work_dir=str(tmp_path), width=0, height=0, checkpoint_every=0,
                                             use_odometry=True), engine)
    session.on_odometry(1.5, pose_at(1.0))  # 0.5 s away from the frame: not its pose
    send(session, 1.0)
    session.data_transfer_done()
    assert session.run().success
    assert len(engine.frames) == 1 and engine.frames[0][1] is None


class GatedEngine(RecordingEngine):
    """Holds its first frame until ``gate`` is set: the camera goes on meanwhile, as when SLAM is slower than it."""

    def __init__(self) -> None:
        super().__init__()
        self.entered, self.gate = threading.Event(), threading.Event()

    def add_frame(self, rgb, depth, semantics, timestamp, odom_c2w=None):
        if not self.frames:
            self.entered.set()
            assert self.gate.wait(30.0), "the test never released the first frame"
        return super().add_frame(rgb, depth, semantics, timestamp, odom_c2w)


@pytest.mark.parametrize(("max_behind", "mapped"), [(3, [1.0, 8.0, 9.0, 10.0]), (0, [float(t) for t in range(1, 11)])])
def test_session_skips_the_oldest_waiting_frames_beyond_max_behind(tmp_path, max_behind, mapped):
    """A live camera: while SLAM is busy with frame 1, frames 2-10 arrive; with max_behind 3 the six oldest are
    skipped before or after the disk writer (counted, logged, in the result), with 0 (the default) none is."""
    from semantic_gs_slam_ros.session import SessionConfig, StreamingSession

    logs: list[str] = []
    engine = GatedEngine()
    session = StreamingSession(SessionConfig(work_dir=str(tmp_path), width=0, height=0, checkpoint_every=0,
                                             max_behind=max_behind), engine, log=logs.append)
    send(session, 1.0)
    out: list = []
    runner = threading.Thread(target=lambda: out.append(session.run(poll=0.01)))
    runner.start()
    try:
        assert engine.entered.wait(30.0)
        for t in range(2, 11):
            send(session, float(t))
            assert wait_until(lambda: session.progress().writing == 0, 30.0)  # written before the next comes
        waiting = len(mapped) - 1  # frame 1 is in the engine; these wait for it
        assert wait_until(lambda: session.progress().writing == 0 and session.progress().backlog == 1 + waiting, 30.0)
        session.data_transfer_done()
    finally:
        engine.gate.set()
        runner.join(30.0)
    p = session.progress()
    assert out[0].success and [t for t, _ in engine.frames] == mapped
    assert p.behind == 10 - len(mapped) and p.processed == len(mapped) and p.backlog == 0
    said = f"{p.behind} frames skipped while SLAM was more than {max_behind} frames behind"
    assert (said in out[0].message) == (max_behind > 0)
    said = "max_behind=3 frames behind the camera: skipping the oldest"
    assert any(said in line for line in logs) == (max_behind > 0)


def test_max_behind_skips_frames_still_waiting_for_the_disk_writer_and_the_run_ends(tmp_path, monkeypatch):
    """The writer slower than the camera: the oldest frames of its queue are skipped unwritten, and the run still
    ends once the rest are processed (it does not wait for frames that will never be written)."""
    import semantic_gs_slam_ros.writer as writer_mod
    from semantic_gs_slam_ros.session import SessionConfig, StreamingSession

    entered, gate = threading.Event(), threading.Event()
    real_write = writer_mod.write_jpeg

    def slow_first_write(path, rgb, quality=95):  # the disk holds the first frame until the test lets it go
        if not entered.is_set():
            entered.set()
            assert gate.wait(30.0)
        real_write(path, rgb, quality)

    monkeypatch.setattr(writer_mod, "write_jpeg", slow_first_write)
    engine = RecordingEngine()
    session = StreamingSession(SessionConfig(work_dir=str(tmp_path), width=0, height=0, checkpoint_every=0,
                                             max_behind=2), engine)
    try:
        send(session, 1.0)
        assert entered.wait(30.0)
        for t in range(2, 7):  # frames 2-6 queue behind it: 2, 3, 4 are skipped before they are written
            send(session, float(t))
        assert session.progress().writing == 2 and session.progress().behind == 3
    finally:
        gate.set()
    session.data_transfer_done()
    result = session.run(poll=0.01)
    assert result.success and [t for t, _ in engine.frames] == [1.0, 5.0, 6.0]
    assert sorted(os.listdir(tmp_path / "frames")) == [f"frame{i:06d}.jpg" for i in range(3)]  # 1, 5, 6 on disk
    assert session.progress().backlog == 0


class BackgroundCheckpointEngine(RecordingEngine):
    """A threaded engine whose checkpoints are written later, when the test says (``finish``), as a mapping
    thread writes them between its jobs."""

    def __init__(self, queue_full: bool = False) -> None:
        super().__init__()
        self.pending: list[tuple[str, object]] = []
        self.queue_full = queue_full

    def save_checkpoint(self, ckpt_dir):
        raise AssertionError("a threaded engine's checkpoint is written in the background")

    def save_checkpoint_in_background(self, ckpt_dir, then):
        if self.queue_full:
            return False
        self.pending.append((ckpt_dir, then))
        return True

    def finish(self, error=None) -> None:
        ckpt_dir, then = self.pending.pop(0)
        if error is None:
            os.makedirs(ckpt_dir, exist_ok=True)
            with open(os.path.join(ckpt_dir, "checkpoint.json"), "w") as fh:
                fh.write("{}")
        then(error)


def _checkpointing_session(tmp_path, engine, log):
    from semantic_gs_slam_ros.session import SessionConfig, StreamingSession

    return StreamingSession(SessionConfig(work_dir=str(tmp_path / "w"), width=0, height=0, checkpoint_every=2),
                            engine, log=log.append)


def test_a_threaded_engines_checkpoint_is_written_in_the_background_one_at_a_time(tmp_path):
    """The frames do not wait for a threaded engine's checkpoint: it is queued, and the session's place in the
    stream is published with it once the engine's part is written; a checkpoint due while one is in flight is
    skipped and counted; the next one after it is taken."""
    from semantic_gs_slam_ros.session import checkpoint_state

    engine, log = BackgroundCheckpointEngine(), []
    session = _checkpointing_session(tmp_path, engine, log)
    ckpt = tmp_path / "w" / "checkpoint"
    for i in range(4):  # checkpoints due after frames 2 and 4: the second finds the first in flight
        send(session, float(i))
    session.data_transfer_done()
    result = session.run()
    assert result.success and len(engine.frames) == 4
    assert len(engine.pending) == 1 and not ckpt.exists()  # queued, not written yet: nothing published
    engine.finish()
    assert (ckpt / "engine" / "checkpoint.json").is_file()
    assert checkpoint_state(str(tmp_path / "w"))["processed"] == 2  # the place when it was asked for
    assert any("checkpoints skipped while the last one was still being written: 1" in m for m in log), log


class FailingLater(BackgroundCheckpointEngine):
    """The mapping thread reports the first checkpoint's failure while frames go on (after the third)."""

    def add_frame(self, *args, **kw):
        out = super().add_frame(*args, **kw)
        if len(self.frames) == 3:
            self.finish(OSError("disk full"))
        return out


class WritesAtOnce(BackgroundCheckpointEngine):
    """No mapping thread: the checkpoint is written (here: fails) during the call, ``then`` called there."""

    def save_checkpoint_in_background(self, ckpt_dir, then):
        then(OSError("disk full"))
        return True


@pytest.mark.parametrize(("engine_type", "frames_taken"), [(FailingLater, 3), (WritesAtOnce, 2)])
def test_a_checkpoint_that_cannot_be_written_ends_the_run_with_its_message(tmp_path, engine_type, frames_taken):
    """A failure reported by the mapping thread ends the run at the next frame; one during the call (no mapping
    thread) at the frame the checkpoint was due after, as a caller-written checkpoint does. The map so far is
    still written."""
    engine, log = engine_type(), []
    session = _checkpointing_session(tmp_path, engine, log)
    for i in range(10):
        send(session, float(i))
    session.data_transfer_done()
    result = session.run()
    assert "cannot write the checkpoint or map: disk full" in result.message, result.message
    assert len(engine.frames) == frames_taken
    assert os.path.isfile(result.map_path)


def test_a_checkpoint_the_mapping_queue_cannot_take_is_skipped(tmp_path):
    engine, log = BackgroundCheckpointEngine(queue_full=True), []
    session = _checkpointing_session(tmp_path, engine, log)
    for i in range(4):
        send(session, float(i))
    session.data_transfer_done()
    assert session.run().success
    assert any("checkpoints skipped while the last one was still being written: 2" in m for m in log), log


def test_session_refuses_a_negative_max_behind(tmp_path):
    from semantic_gs_slam_ros.errors import StreamingError
    from semantic_gs_slam_ros.session import SessionConfig

    with pytest.raises(StreamingError, match="max_behind must be >= 0"):
        SessionConfig(work_dir=str(tmp_path), max_behind=-1)


def wait_until(predicate, timeout: float) -> bool:
    import time

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return bool(predicate())


class ReportingEngine(RecordingEngine):
    """Reports a lost track on its 2nd frame and a drift correction on its 3rd (like EngineAdapter.frame_report)."""

    def frame_report(self):
        n = len(self.frames)
        if n == 2:
            return True, False, ""
        if n == 3:
            return False, True, "loop with frame 0: correct (4.0 cm, 1.00 deg, agreement 60% -> 85%)"
        note = "loop with frame 0: consistent (0.2 cm, 0.10 deg, agreement 90% -> 90%)"
        return False, False, note if n == 4 else ""


def test_session_counts_and_reports_lost_tracks_and_drift_corrections(tmp_path):
    from semantic_gs_slam_ros.session import SessionConfig, StreamingSession

    logs: list[str] = []
    cfg = SessionConfig(work_dir=str(tmp_path), width=0, height=0, checkpoint_every=0)
    session = StreamingSession(cfg, ReportingEngine(), log=logs.append)
    for t in (1.0, 2.0, 3.0, 4.0):
        send(session, t)
    session.data_transfer_done()
    result = session.run()
    p = session.progress()
    assert result.success and p.processed == 4 and p.lost == 1 and p.drift_corrections == 1
    assert "tracking lost on 1 frames, drift corrected 1 times" in result.message
    assert any("tracking lost" in m for m in logs) and any("drift corrected" in m for m in logs)


def test_engine_adapter_reports_the_engines_last_frame():
    from semantic_gs_slam.config import SlamConfig
    from semantic_gs_slam.slam import SLAM
    from semantic_gs_slam.synthetic.scenes import default_intrinsics
    from semantic_gs_slam_ros.engine import EngineAdapter

    k = default_intrinsics(32, 18)
    adapter = EngineAdapter(SLAM(SlamConfig(intrinsics=k, threads=1)))
    assert adapter.frame_report() == (False, False, "")
    rgb, depth = np.full((18, 32, 3), 128, np.uint8), np.full((18, 32), 2.0, np.float32)
    adapter.add_frame(rgb, depth, None, 0.0)
    assert adapter.frame_report() == (False, False, "")
    assert len(adapter.slam.logs) == 1  # the report is the engine's own log of that frame
    assert adapter.run_note().startswith("1 frames tracked, 1 keyframes, 0 keyframes deferred while mapping was busy")
    assert "noisy" not in adapter.run_note()
    # the keyframe front end with a noisy camera's depth: the note says its keyframes were smoothed
    from semantic_gs_slam.config import TrackingConfig

    k = default_intrinsics(64, 48)
    noisy = EngineAdapter(SLAM(SlamConfig(intrinsics=k, threads=1, tracking=TrackingConfig(frontend="keyframe"))))
    rng = np.random.default_rng(0)
    depth = (2.0 + 0.02 * rng.standard_normal((48, 64))).astype(np.float32)
    noisy.add_frame(np.full((48, 64, 3), 128, np.uint8), depth, None, 0.0)
    assert "1 keyframes' depth smoothed as a noisy camera's (roughness 0.00" in noisy.run_note(), noisy.run_note()
    assert "re-posed" not in noisy.run_note()
    noisy.slam.rejoined_frames = 3  # as after a lost stretch re-posed on recovery (test_recovery_real.py runs one)
    assert "0 frames lost (3 re-posed in the map once recovered)" in noisy.run_note(), noisy.run_note()
    noisy.slam.resumed = [[7, 36]]  # as after a camera lost on unseen ground (test_recovery_real.py runs one)
    assert "(3 re-posed in the map once recovered; mapping resumed 1 time(s) on the lost frames' own track, not " \
        "relocalised in the map (from frames 7))" in noisy.run_note(), noisy.run_note()
    noisy.slam.reanchored = [[7, 80, 103.4, 14.3]]  # ... and later moved into the map's frame (the same file)
    assert "; 1 resumed track(s) later relocalised and moved into the map's frame (from frames 7))" in \
        noisy.run_note(), noisy.run_note()


def _short_fits(cfg):
    """Few Adam steps per frame (the first frame's 60 by default are most of a short run's time): the sessions below
    check what the session does with the engine's frames, results and failures, not the map's quality."""
    cfg.mapping.first_frame_iters, cfg.mapping.iters = 5, 3
    return cfg


def _engine_session(tmp_path, refine_iters: int, log: list[str], refine_poses: bool = False,
                    refine_seconds: float = 0.0, engine_refines_poses: bool = False):
    """A session around the real engine (EngineAdapter + SLAM) fed four frames of the synthetic home."""
    from semantic_gs_slam.config import SlamConfig
    from semantic_gs_slam.slam import SLAM
    from semantic_gs_slam.synthetic.scenes import HomeRenderer, default_intrinsics, trajectory
    from semantic_gs_slam_ros.engine import EngineAdapter
    from semantic_gs_slam_ros.session import SessionConfig, StreamingSession

    k = default_intrinsics(128, 72)
    cfg = _short_fits(SlamConfig(intrinsics=k, threads=1))
    cfg.mapping.keyframe_every = 2  # frames 0 and 2 are keyframes: a pose to refine besides the gauge
    cfg.mapping.refine_poses = engine_refines_poses
    engine = EngineAdapter(SLAM(cfg))
    session = StreamingSession(SessionConfig(work_dir=str(tmp_path / "work"), width=0, height=0, checkpoint_every=0,
                                             refine_iters=refine_iters, refine_poses=refine_poses,
                                             refine_seconds=refine_seconds),
                               engine, log=log.append)
    r = HomeRenderer(0)
    for i, c2w in enumerate(trajectory(4, 6.0)):
        rgb, depth, _ = r.render(c2w, k)
        session.on_image("depth", float(i), depth.astype(np.float32))
        session.on_image("rgb", float(i), np.round(rgb * 255).astype(np.uint8))  # as a camera sends it
    session.data_transfer_done()
    return session, engine


@pytest.mark.parametrize(("asked", "engine_default"), [(False, False), (True, False), (False, True)])
def test_session_refines_the_map_before_writing_it(tmp_path, asked, engine_default):
    """The session's refine_poses asks for the poses too; without it the engine's mapping.refine_poses decides
    (the realtime profile's)."""
    from semantic_gs_slam.mapping.gaussian_map import load_params

    log: list[str] = []
    session, engine = _engine_session(tmp_path, 25, log, refine_poses=asked, engine_refines_poses=engine_default)
    poses = asked or engine_default
    calls: list[tuple[int, bool]] = []
    before: list[np.ndarray] = []  # the map's colours and the last pose when the refinement starts
    refine = engine.refine

    def watched(n, poses=None, should_stop=None):  # the real refinement, its call recorded
        before.append(engine.slam.map.params["rgb_colors"].detach().cpu().numpy().copy())
        before.append(engine.slam.poses[-1].copy())
        calls.append((n, poses))
        assert should_stop is not None and should_stop() is False
        return refine(n, poses=poses, should_stop=should_stop)

    engine.refine = watched
    result = session.run()
    assert result.success and "refined 25 of 25 iterations" in result.message, result.message
    assert calls == [(25, True if asked else None)]
    what = "refining the map and its views' poses:" if poses else "refining the map:"
    assert any(what in m and "25 iterations over all 2 keyframes in turn" in m for m in log), log
    # the map written is the refined one: the engine's map after the refinement, not the one before it
    written = load_params(result.map_path)
    colours = written["rgb_colors"]
    np.testing.assert_array_equal(colours, engine.slam.map.params["rgb_colors"].detach().cpu().numpy())
    assert colours.shape != before[0].shape or not np.array_equal(colours, before[0])
    # poses move only when asked to (the last frame follows its keyframe's correction)
    assert np.array_equal(engine.slam.poses[-1], before[1]) is not poses


def test_session_cancel_during_the_refinement_still_writes_the_map(tmp_path):
    import threading

    log: list[str] = []
    session, engine = _engine_session(tmp_path, 100000, log)
    refine = engine.refine

    def refine_and_cancel(n, poses=None, should_stop=None):
        threading.Timer(0.5, session.cancel).start()  # as the action's cancel callback would, from elsewhere
        return refine(n, poses=poses, should_stop=should_stop)

    engine.refine = refine_and_cancel
    result = session.run()
    assert result.success and os.path.isfile(result.map_path)
    import re

    m = re.search(r"refined (\d+) of 100000 iterations", result.message)
    assert m and 0 < int(m.group(1)) < 100000, result.message
    assert any("(cancelled)" in line for line in log) and not any("failed" in line for line in log)


def test_session_refinement_ends_at_its_time_budget(tmp_path):
    import re

    log: list[str] = []
    session, engine = _engine_session(tmp_path, 0, log, refine_seconds=0.5)
    result = session.run()
    assert result.success and os.path.isfile(result.map_path)
    m = re.search(r"refined (\d+) iterations in ([\d.]+) s", result.message)
    assert m and int(m.group(1)) > 0, result.message
    assert any("refining the map: iterations (at most 0.5 s)" in line for line in log), log
    assert any("(time budget)" in line for line in log), log


def test_session_refinement_failure_is_reported_and_the_map_still_written(tmp_path):
    log: list[str] = []
    session, engine = _engine_session(tmp_path, 50, log)

    def broken(n, poses=False, should_stop=None):
        raise RuntimeError("out of memory")

    engine.refine = broken
    result = session.run()
    assert result.success and os.path.isfile(result.map_path)
    assert "map refinement failed (out of memory)" in result.message
    assert any("map refinement failed: out of memory; the map is written as it is" in line for line in log)


def test_session_refuses_bad_refinement_settings(tmp_path):
    from semantic_gs_slam_ros.errors import StreamingError
    from semantic_gs_slam_ros.session import SessionConfig

    with pytest.raises(StreamingError, match="refine_iters must be >= 0"):
        SessionConfig(work_dir=str(tmp_path), refine_iters=-1)
    with pytest.raises(StreamingError, match="refine_poses needs refine_iters > 0 or refine_seconds > 0"):
        SessionConfig(work_dir=str(tmp_path), refine_poses=True)
    with pytest.raises(StreamingError, match="refine_seconds must be >= 0"):
        SessionConfig(work_dir=str(tmp_path), refine_seconds=-1.0)
    SessionConfig(work_dir=str(tmp_path), refine_poses=True, refine_seconds=5.0)


def _labelled_engine_session(tmp_path, bad: set[int], n: int, log: list[str]):
    """A session around the real engine with the geometry labelling stage (label-less frames, as a real camera
    sends them), fed ``n`` frames of the synthetic home; the frames in ``bad`` have no depth at all."""
    from semantic_gs_slam.config import SlamConfig
    from semantic_gs_slam.slam import SLAM
    from semantic_gs_slam.synthetic.scenes import HomeRenderer, default_intrinsics, trajectory
    from semantic_gs_slam_ros.engine import EngineAdapter, make_labels
    from semantic_gs_slam_ros.session import SessionConfig, StreamingSession

    k = default_intrinsics(128, 72)
    stage = make_labels("geometry", "", k, streamed_labels=False)
    engine = EngineAdapter(SLAM(_short_fits(SlamConfig(intrinsics=k, threads=1))), stage)
    session = StreamingSession(SessionConfig(work_dir=str(tmp_path / "work"), width=0, height=0,
                                             checkpoint_every=0), engine, log=log.append)
    r = HomeRenderer(0)
    for i, c2w in enumerate(trajectory(n, 6.0)):
        rgb, depth, _ = r.render(c2w, k)
        session.on_image("depth", float(i), np.zeros_like(depth, np.float32) if i in bad else depth.astype(np.float32))
        session.on_image("rgb", float(i), np.round(rgb * 255).astype(np.uint8))
    session.data_transfer_done()
    return session, engine, stage


def test_session_skips_a_frame_the_engine_refuses_before_the_labelling_stage_sees_it(tmp_path):
    log: list[str] = []
    session, engine, stage = _labelled_engine_session(tmp_path, {2}, 4, log)
    seen: list[tuple[int, int]] = []
    result = session.run(on_progress=lambda p: seen.append((p.processed, p.skipped)))
    assert seen == [(1, 0), (2, 0), (2, 1), (3, 1)]  # the skipped frame is reported when it is skipped
    p = session.progress()
    assert result.success and result.frames_processed == 3 and p.skipped == 1 and p.refused == 0, result.message
    assert p.backlog == 0  # the skipped frame is done with
    assert engine.slam.timestamps == [0.0, 1.0, 3.0]
    assert stage._calls == 3  # the stateful labelling stage never saw the refused frame
    assert any(line.startswith("frame 2 skipped by SLAM:") and "depth" in line for line in log), log
    assert os.path.isfile(result.map_path)


def test_session_stops_after_refused_frames_in_a_row_and_writes_the_map(tmp_path, monkeypatch):
    import semantic_gs_slam_ros.session as session_mod

    monkeypatch.setattr(session_mod, "MAX_BAD_IN_A_ROW", 2)
    log: list[str] = []
    # frame 1 alone is skipped (the count starts again at frame 2); frames 3 and 4 in a row stop the run
    session, engine, _ = _labelled_engine_session(tmp_path, {1, 3, 4}, 6, log)
    result = session.run()
    assert not result.success and result.frames_processed == 2, result.message
    assert result.message.startswith("2 frames in a row could not be used (the last, frame 4:"), result.message
    assert engine.slam.timestamps == [0.0, 2.0]  # frame 5 was not processed
    from semantic_gs_slam.mapping.gaussian_map import load_params

    assert len(load_params(result.map_path)["means3D"]) == engine.num_gaussians > 0  # the map of frames 0 and 2


def test_session_ends_the_run_when_the_engine_fails_and_writes_the_map_so_far(tmp_path):
    log: list[str] = []
    session, engine, _ = _labelled_engine_session(tmp_path, set(), 4, log)
    real_add = engine.slam.add_frame

    def fails_on_the_third(*args, **kwargs):  # the engine failing (a bug, out of memory) on one frame
        if len(engine.slam.poses) == 2:
            raise RuntimeError("CUDA out of memory")
        return real_add(*args, **kwargs)

    engine.slam.add_frame = fails_on_the_third
    result = session.run()
    assert not result.success and result.frames_processed == 2, result.message
    assert result.message.startswith("SLAM failed on frame 2 (RuntimeError: CUDA out of memory)"), result.message
    assert os.path.isfile(result.map_path) and len(engine.slam.poses) == 2
    assert any("Traceback" in line and "the map of the frames mapped so far is written" in line for line in log)


def test_session_reports_an_engine_failure_whose_map_cannot_be_saved(tmp_path):
    """After the engine failed, its state may not save: the result says both, and nothing is raised."""
    log: list[str] = []
    session, engine, _ = _labelled_engine_session(tmp_path, set(), 3, log)
    real_add = engine.slam.add_frame

    def fails_on_the_second(*args, **kwargs):
        if len(engine.slam.poses) == 1:
            raise RuntimeError("CUDA error: an illegal memory access")
        return real_add(*args, **kwargs)

    def broken_save(out_dir, ply=True):
        raise ValueError("inconsistent state")

    engine.slam.add_frame = fails_on_the_second
    engine.slam.save = broken_save
    result = session.run()
    assert not result.success and result.frames_processed == 1 and result.map_path == ""
    assert result.message == ("SLAM failed on frame 1 (RuntimeError: CUDA error: an illegal memory access); the map "
                              "could not be written (ValueError: inconsistent state)"), result.message


def test_session_continues_a_saved_map_given_as_start_map_in_its_frame(tmp_path):
    """The server's ``start_map``: the engine made by make_engine continues the saved map; a first frame the map never
    saw is reported lost (not mapped), the next ones are relocalised in the map's frame and mapped into it."""
    from semantic_gs_slam.config import SlamConfig
    from semantic_gs_slam.geometry import pose_error
    from semantic_gs_slam.mapping.gaussian_map import load_params
    from semantic_gs_slam.slam import SLAM
    from semantic_gs_slam.synthetic.scenes import HomeRenderer, default_intrinsics, trajectory
    from semantic_gs_slam_ros.engine import make_engine
    from semantic_gs_slam_ros.errors import StreamingError
    from semantic_gs_slam_ros.session import SessionConfig, StreamingSession

    k = default_intrinsics(128, 72)
    cfg = _short_fits(SlamConfig(intrinsics=k, threads=1))
    poses = trajectory(9, 40.0)
    r = HomeRenderer(0)
    first = SLAM(cfg, initial_c2w=poses[0])  # the saved map's frame: the world's
    for i in range(4):
        rgb, depth, _ = r.render(poses[i], k)
        first.add_frame(rgb, depth, None, float(i))
    saved = str(tmp_path / "saved")
    first.save(saved, ply=False)
    n_saved = len(first.map)
    camera = (k.fx, k.fy, k.cx, k.cy, k.width, k.height)
    session_cfg = SessionConfig(work_dir=str(tmp_path / "work"), width=0, height=0, checkpoint_every=0)
    # a bad start_map is a clear error (the goal aborts with it; the server keeps running)
    (tmp_path / "corrupt").mkdir()
    (tmp_path / "corrupt" / "params.npz").write_bytes(b"not a zip")
    for bad, why in ((str(tmp_path / "nowhere"), "not a folder"), (str(tmp_path / "corrupt"), "not a readable .npz")):
        with pytest.raises(StreamingError, match=f"cannot continue the saved map .*{why}"):
            make_engine("", lambda: camera, session_cfg, start_map=bad)
    engine = make_engine("", lambda: camera, session_cfg, start_map=saved, overrides={"threads": 1})
    engine.slam.cfg.mapping.first_frame_iters, engine.slam.cfg.mapping.iters = 5, 3
    log: list[str] = []
    session = StreamingSession(session_cfg, engine, log=log.append)
    views = [poses[2] @ np.diag([-1.0, 1.0, -1.0, 1.0])] + poses[1:7]  # first the wall behind the camera
    for i, c2w in enumerate(views):
        rgb, depth, _ = r.render(c2w, k)
        session.on_image("depth", float(i), depth.astype(np.float32))
        session.on_image("rgb", float(i), np.round(rgb * 255).astype(np.uint8))
    session.data_transfer_done()
    result = session.run()
    assert result.success and result.frames_processed == 7, result.message
    assert any(line.startswith("frame 0: not relocalised in the saved map yet") for line in log), log
    # relocalisation is tried on the first frame, then on every tracking.relocalise_every-th (3): frame 3
    assert [lg.pose_source for lg in engine.slam.logs][:5] == ["lost"] * 3 + ["relocalised", "recovered"]
    assert pose_error(engine.slam.poses[3], poses[3])[0] < 0.02  # in the saved map's frame
    assert len(load_params(result.map_path)["means3D"]) > n_saved  # the saved map, grown


GOOD_K = [585.0, 0.0, 320.0, 0.0, 585.0, 240.0, 0.0, 0.0, 1.0]


@pytest.mark.parametrize("k, size, message", [
    ([float("inf")] + GOOD_K[1:], (640, 480), "focal lengths must be finite and positive, got fx=inf"),
    ([0.0] * 9, (640, 480), "focal lengths must be finite and positive, got fx=0.0 fy=0.0"),
    (GOOD_K[:2] + [float("nan")] + GOOD_K[3:], (640, 480), "principal point must be finite, got cx=nan"),
    (GOOD_K, (0, 0), "width and height must be the calibrated image size, got 0x0"),
    (GOOD_K[:8], (640, 480), "must hold 9 numbers (3x3), got 8"),
])
def test_a_camera_info_that_is_no_usable_camera_is_refused_with_the_reason(k, size, message):
    from semantic_gs_slam_ros.engine import camera_info_intrinsics
    from semantic_gs_slam_ros.errors import StreamingError

    with pytest.raises(StreamingError) as err:
        camera_info_intrinsics(k, [0.0] * 5, *size)
    assert message in str(err.value)


def test_a_camera_info_gives_its_pinhole_and_notes_lens_distortion():
    from semantic_gs_slam_ros.engine import camera_info_intrinsics

    assert camera_info_intrinsics(GOOD_K, [0.0] * 5, 640, 480) == ((585.0, 585.0, 320.0, 240.0, 640, 480), "")
    assert camera_info_intrinsics(GOOD_K, [], 640, 480)[1] == ""  # no coefficients at all: none to correct
    k, note = camera_info_intrinsics(GOOD_K, [0.2624, -0.9531, -0.0054, 0.0026, 1.1633], 640, 480, "plumb_bob")
    assert k == (585.0, 585.0, 320.0, 240.0, 640, 480)
    assert "lens distortion (plumb_bob: 0.2624 -0.9531 -0.0054 0.0026 1.1633)" in note and "rectified" in note


def test_the_client_sends_its_folders_absolute(tmp_path, monkeypatch):
    """A relative output_dir / map_dir means the client's working folder: the server, elsewhere, refuses relative
    ones."""
    from semantic_gs_slam_ros.run_gs_slam_client import _absolute

    monkeypatch.chdir(tmp_path)
    assert _absolute("run1") == str(tmp_path / "run1") and _absolute("") == "" and _absolute("/abs") == "/abs"
