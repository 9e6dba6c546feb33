"""Integration: espeak-ng commands streamed through the real audio_command_node process into ROS 2.

Each test starts one node process (which loads Whisper once) on its own ROS domain and listens
on /manual_command and /audio_command/status from the test process.
"""

from __future__ import annotations

import json
import subprocess
import threading

import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from decision_maker.speech import testaudio as ta
from decision_maker.speech.sources import list_input_devices
from home_robot_bringup.nodeset import find_executable
from home_robot_bringup.process import node_environment
from home_robot_bringup.testing import wait_for

from .voice_testing import MISSING, SKIP_REASON, matches

pytestmark = [pytest.mark.ros, pytest.mark.skipif(bool(MISSING), reason=SKIP_REASON)]

NODE = "audio_command_node"


class Listener:
    """Collects /manual_command and /audio_command/status messages (thread-safe)."""

    def __init__(self, node) -> None:
        self._lock = threading.Lock()  # guards commands, status
        self.commands: list[str] = []
        self.status: list[dict] = []
        node.create_subscription(String, "manual_command", self._on_command, 10)
        node.create_subscription(String, "audio_command/status", self._on_status, 50)

    def _on_command(self, msg: String) -> None:
        with self._lock:
            self.commands.append(msg.data)

    def _on_status(self, msg: String) -> None:
        with self._lock:
            self.status.append(json.loads(msg.data))

    def clear(self) -> None:
        with self._lock:
            self.commands.clear()
            self.status.clear()

    def events(self, kind: str) -> list[dict]:
        with self._lock:
            return [s for s in self.status if s.get("event") == kind]

    def finished(self) -> bool:
        """The node reported the end of its source and every published command arrived."""
        if not self.events("end_of_source"):
            return False
        published = [u for u in self.events("utterance") if u["command"]]
        with self._lock:
            return len(self.commands) >= len(published)

    def dump(self) -> str:
        with self._lock:
            return json.dumps({"commands": self.commands, "status": self.status}, indent=1)


def wav_node(path: str, **params) -> list[str]:
    sets = {"source": "wav", "wav_path": path, "pacing": 0.0, "wait_for_subscriber_s": 20.0, **params}
    return [f"{NODE}.{k}={json.dumps(v)}" for k, v in sets.items()]


def stream_of(commands: list[tuple[str, str, int]], gap_s: float = 1.2, noise_under: int | None = None):
    """Silence, then each command (text, voice, speed) followed by ``gap_s`` of silence."""
    parts = [(None, ta.silence(0.6))]
    for i, (text, voice, speed) in enumerate(commands):
        speech = ta.speak(text, voice, speed)
        if i == noise_under:
            speech = speech + np.resize(ta.noise("pinknoise", speech.size / 16000 + 0.1, 0.08, seed=5), speech.size)
        parts += [(text, speech), (None, ta.silence(gap_s))]
    return parts


def test_vad_mode_publishes_each_command_and_ignores_noise(launch_nodes, ros_node, tmp_path):
    listener = Listener(ros_node)
    parts = stream_of([("give me the bottle", "en-us", 170), ("go home", "en+m3", 140),
                       ("clean the table", "en+f2", 170), ("stop", "en-us", 140)], noise_under=2)
    parts.insert(3, (None, ta.noise("pinknoise", 2.5, 0.1)))  # a stretch of noise between two commands
    parts.append((None, ta.noise("whitenoise", 2.0, 0.05)))
    parts.append((None, ta.silence(0.8)))
    stream, utts = ta.compose(parts)
    ta.write_wav(str(tmp_path / "commands.wav"), stream)

    launch_nodes(nodeset="voice", set=wav_node(str(tmp_path / "commands.wav")))
    assert wait_for(listener.finished, 120), listener.dump()
    expected = [u.text for u in utts]
    assert len(listener.commands) == len(expected), listener.dump()
    for heard, want in zip(listener.commands, expected, strict=True):
        assert matches(heard, want), f"heard {heard!r} for {want!r}\n{listener.dump()}"
    utterances = listener.events("utterance")
    published = [u for u in utterances if u["command"]]
    assert all(u["mode"] == "vad" and not u["cut"] and 0 < u["confidence"] <= 1 for u in published)
    assert all(u["latency_s"] >= 0 and u["transcribe_s"] > 0 for u in published)
    assert listener.events("ready")[0]["source"].startswith("wav:")


def test_silence_and_noise_alone_publish_nothing(launch_nodes, ros_node, tmp_path):
    listener = Listener(ros_node)
    stream, _ = ta.compose([(None, ta.silence(2.0)), (None, ta.noise("pinknoise", 3.0, 0.1)),
                            (None, ta.noise("whitenoise", 3.0, 0.05)), (None, ta.noise("brownnoise", 2.0, 0.2)),
                            (None, ta.silence(1.0))])
    ta.write_wav(str(tmp_path / "noise.wav"), stream)
    for mode in ("vad", "fixed"):
        listener.clear()
        sup = launch_nodes(nodeset="voice", set=wav_node(str(tmp_path / "noise.wav"), segmentation=mode))
        assert wait_for(listener.finished, 120), listener.dump()
        assert listener.commands == [], listener.dump()
        assert all(u["command"] is None for u in listener.events("utterance")), listener.dump()
        if mode == "fixed":  # the seed's mode transcribes every chunk: 11 s = 2 full chunks + the tail
            assert len(listener.events("utterance")) == 3, listener.dump()
        sup.stop()


def test_fixed_chunk_mode_still_works(launch_nodes, ros_node, tmp_path):
    listener = Listener(ros_node)
    chunk = 5.0
    parts = []
    for text, voice, speed in [("go home", "en-us", 170), ("bring me the cup", "en+f2", 170),
                               ("clean table", "en+m3", 140)]:
        speech = ta.speak(text, voice, speed)
        parts += [(None, ta.silence(1.0)), (text, speech), (None, ta.silence(chunk - 1.0 - speech.size / 16000))]
    stream, utts = ta.compose(parts)
    ta.write_wav(str(tmp_path / "chunks.wav"), stream)
    launch_nodes(nodeset="voice", set=wav_node(str(tmp_path / "chunks.wav"), segmentation="fixed", chunk_s=chunk))
    assert wait_for(listener.finished, 120), listener.dump()
    assert len(listener.commands) == 3, listener.dump()
    for heard, want in zip(listener.commands, [u.text for u in utts], strict=True):
        assert matches(heard, want), f"heard {heard!r} for {want!r}\n{listener.dump()}"
    assert all(u["mode"] == "fixed" and u["cut"] and abs(u["audio_s"] - chunk) < 0.01
               for u in listener.events("utterance"))


def _start_stdin_node(ros_domain: int, *params: str) -> subprocess.Popen:
    exe = find_executable("decision_maker", NODE)
    args = [exe, "--ros-args", "-p", "source:=stdin", "-p", "exit_at_end:=true", "-p", "wait_for_subscriber_s:=20.0"]
    for p in params:
        args += ["-p", p]
    return subprocess.Popen(args, env=node_environment(ros_domain), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT)


def test_stdin_stream_uses_object_names_from_object_list(ros_node, ros_domain):
    listener = Listener(ros_node)
    latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
    pub = ros_node.create_publisher(String, "object_list", latched)
    pub.publish(String(data=json.dumps({"bottle": [5.2, 0.3, 1.0], "teapot": [1.0, 2.0, 0.9]})))

    proc = _start_stdin_node(ros_domain)
    out: list[str] = []
    reader = threading.Thread(target=lambda: out.extend(line.decode(errors="replace") for line in proc.stdout),
                              daemon=True)
    reader.start()
    try:
        # the latched object list reaches the node (a late joiner) and becomes part of the prompt
        assert wait_for(lambda: any("teapot" in e["objects"] for e in listener.events("vocabulary")), 60), \
            "".join(out) + listener.dump()
        # "teapot" is heard as "bottle"/"table" without it in the prompt (measured), and right with it
        stream, _ = ta.compose(stream_of([("give me the teapot", "en-us", 170), ("stop", "en+f2", 170)]))
        pcm = (np.clip(stream, -1, 1) * 32767).astype("<i2").tobytes()
        proc.stdin.write(pcm)
        proc.stdin.close()
        assert wait_for(listener.finished, 120), "".join(out) + listener.dump()
        assert proc.wait(timeout=30) == 0, "".join(out)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
    assert len(listener.commands) == 2 and matches(listener.commands[0], "give me the teapot") \
        and "teapot" in listener.commands[0] and listener.commands[1] == "stop", listener.dump()


def test_missing_microphone_is_reported_not_a_traceback(ros_domain):
    if list_input_devices():
        pytest.skip("this machine has an input device")
    exe = find_executable("decision_maker", NODE)
    env = node_environment(ros_domain)
    once = subprocess.run([exe, "--ros-args", "-p", "source:=microphone"], env=env, capture_output=True, text=True,
                          timeout=60)
    text = once.stdout + once.stderr
    assert once.returncode == 2, text
    assert "cannot open the default input device" in text or "PortAudio is not installed" in text, text
    assert "fix:" in text and "Traceback" not in text, text

    # retry_s > 0: keeps trying (and saying so) until stopped
    proc = subprocess.Popen([exe, "--ros-args", "-p", "source:=microphone", "-p", "retry_s:=0.3"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    try:
        assert wait_for(lambda: sum("retrying in 0.3 s" in line for line in list(lines)) >= 2, 60), "".join(lines)
        assert proc.poll() is None
    finally:
        proc.send_signal(2)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def test_invalid_parameter_is_rejected_at_start(ros_domain):
    exe = find_executable("decision_maker", NODE)
    run = subprocess.run([exe, "--ros-args", "-p", "segmentation:=blocks", "-p", "source:=stdin"],
                         env=node_environment(ros_domain), capture_output=True, text=True, timeout=60,
                         stdin=subprocess.DEVNULL)
    assert run.returncode == 2 and "segmentation must be one of" in run.stdout + run.stderr


def test_wake_word_and_filter_parameters_change_at_run_time(ros_node, ros_domain):
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    listener = Listener(ros_node)
    proc = _start_stdin_node(ros_domain)
    out: list[str] = []
    threading.Thread(target=lambda: out.extend(line.decode(errors="replace") for line in proc.stdout),
                     daemon=True).start()
    try:
        client = AsyncParameterClient(ros_node, NODE)
        assert client.wait_for_services(timeout_sec=60), "".join(out)

        def set_params(params):
            fut = client.set_parameters(params)
            done = threading.Event()
            fut.add_done_callback(lambda _f: done.set())
            assert done.wait(20), "set_parameters timed out"
            return fut.result().results

        (bad,) = set_params([Parameter("max_no_speech_prob", value=1.5)])
        assert not bad.successful and "max_no_speech_prob" in bad.reason
        (ok,) = set_params([Parameter("wake_word", value="robot")])
        assert ok.successful, ok.reason
        assert wait_for(lambda: any(e["prompt"].startswith("robot,") for e in listener.events("vocabulary")), 20)

        stream, _ = ta.compose(stream_of([("robot go home", "en-us", 150), ("stop", "en+f2", 170)]))
        proc.stdin.write((np.clip(stream, -1, 1) * 32767).astype("<i2").tobytes())
        proc.stdin.close()
        assert wait_for(listener.finished, 120), "".join(out) + listener.dump()
        assert proc.wait(timeout=30) == 0, "".join(out)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
    assert listener.commands == ["go home"], listener.dump()
    dropped = [u for u in listener.events("utterance") if u["command"] is None]
    assert len(dropped) == 1 and dropped[0]["dropped"] == "no_wake_word" and matches(dropped[0]["text"], "stop")
