"""ROS 2 shell of the voice input: microphone / WAV / stdin → offline Whisper → ``/manual_command``.

Topics:
    publishes ``manual_command`` (std_msgs/String): recognised commands, normalised.
    publishes ``audio_command/status`` (std_msgs/String): one JSON line per utterance (text,
        confidence, latency, why dropped) and per event (vocabulary, end_of_source, device_error).
    subscribes ``object_list`` (std_msgs/String, JSON ``{"name": [x, y, z]}``, transient local):
        object names join Whisper's vocabulary prompt.

Parameters: see ``config/params/voice.yaml`` of home_robot_bringup and docs/voice.md. Those
marked read-only are read at start; the vocabulary, wake word and filter thresholds can be
changed at run time (``ros2 param set``).
"""

from __future__ import annotations

import json
import os
import threading
import time
import traceback

os.environ.setdefault("HF_HUB_OFFLINE", "1")  # never download a model (the transcriber enforces it too)

import rclpy  # noqa: E402
from rcl_interfaces.msg import ParameterDescriptor, ParameterType, SetParametersResult  # noqa: E402
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from decision_maker.client.command_client import CommandClient  # noqa: E402
from decision_maker.speech.errors import AudioDeviceError, AudioSourceError, SpeechError  # noqa: E402
from decision_maker.speech.filtering import FilterConfig  # noqa: E402
from decision_maker.speech.pipeline import PipelineConfig, Result, VoicePipeline  # noqa: E402
from decision_maker.speech.segmentation import VadConfig  # noqa: E402
from decision_maker.speech.sources import open_source  # noqa: E402
from decision_maker.speech.transcriber import Transcriber, TranscriberConfig  # noqa: E402
from decision_maker.speech.vocabulary import DEFAULT_COMMAND_PHRASES, Vocabulary, parse_object_list  # noqa: E402
from home_robot_ros.startup import build_node  # noqa: E402

#: Matches object_query_server's latched /object_list.
OBJECT_LIST_QOS = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                             reliability=ReliabilityPolicy.RELIABLE)

# name -> (default, read_only)
_PARAMS: dict[str, tuple[object, bool]] = {
    "source": ("microphone", True),  # microphone | wav | stdin
    "input_device": ("", True),  # PortAudio device name or index; empty = default input
    "wav_path": ("", True),
    "pacing": (1.0, True),  # WAV pacing: 1.0 = real time, 0 = as fast as possible
    "stdin_sample_rate": (16000, True),
    "retry_s": (0.0, True),  # > 0: retry a busy/missing device every retry_s seconds
    "exit_at_end": (False, True),  # WAV/stdin: shut down after the end of the stream
    "wait_for_subscriber_s": (0.0, True),  # WAV/stdin: wait up to this long for a /manual_command subscriber
    "segmentation": ("vad", True),  # vad | fixed
    "chunk_s": (5.0, True),
    "vad_threshold": (0.5, True),
    "min_silence_ms": (400.0, True),
    "speech_pad_ms": (200.0, True),
    "min_speech_ms": (150.0, True),
    "max_utterance_s": (10.0, True),
    "speculative": (True, True),
    "speculative_ms": (100.0, True),
    "model": ("", True),  # path or faster-whisper model name; empty = bundled tiny.en
    "device": ("cpu", True),  # Whisper's device: cpu | cuda | auto
    "compute_type": ("int8", True),
    "cpu_threads": (0, True),
    "beam_size": (5, True),
    "grammar_hypotheses": (5, True),  # out-of-grammar transcript: look at this many hypotheses; 0 = off
    "grammar_max_drop": (0.3, True),  # ... and take one at most this much lower in mean log-probability
    "language": ("en", True),
    "object_list_topic": ("object_list", True),  # empty = no object names in the vocabulary
    "command_phrases": (list(DEFAULT_COMMAND_PHRASES), False),
    "places": ([], False),
    "wake_word": ("", False),
    "wake_word_timeout_s": (5.0, False),
    "max_no_speech_prob": (0.6, False),
    "min_avg_logprob": (-1.0, False),
    "min_stop_avg_logprob": (-1.6, False),  # a stop ("cancel", "stop it") is kept down to this
    "max_compression_ratio": (2.4, False),
    "min_chars": (2, False),
    "max_prompt_echo_words": (8, False),
}


class AudioCommandNode(Node):
    """Wires the speech pipeline to topics and parameters.

    Raises:
        SpeechError: invalid parameters or the model cannot be loaded (reported by main()).
    """

    def __init__(self) -> None:
        super().__init__("audio_command_node")
        for name, (default, read_only) in _PARAMS.items():
            if isinstance(default, list):
                desc = ParameterDescriptor(type=ParameterType.PARAMETER_STRING_ARRAY, read_only=read_only)
            else:
                desc = ParameterDescriptor(read_only=read_only)
            self.declare_parameter(name, default, desc)
        p = self._p
        self._objects: tuple[str, ...] = ()
        self._vocab_lock = threading.Lock()  # guards _objects (subscription vs parameter callbacks)
        self.done = threading.Event()  # set when the node should exit (main polls it)
        self.exit_code = 0
        self._stop = threading.Event()  # stops the audio thread

        self._pipeline_config = self._make_pipeline_config(p)
        self._transcriber = Transcriber(TranscriberConfig(
            model=p("model"), device=p("device"), compute_type=p("compute_type"), cpu_threads=p("cpu_threads"),
            beam_size=p("beam_size"), language=p("language"), grammar_hypotheses=p("grammar_hypotheses"),
            grammar_max_drop=float(p("grammar_max_drop"))))
        warm_s = self._transcriber.warm_up()
        self.get_logger().info(f"Whisper model {self._transcriber.model_path} loaded in "
                               f"{self._transcriber.load_s:.2f} s, warmed up in {warm_s:.2f} s ({p('device')}, "
                               f"{p('compute_type')}, beam {p('beam_size')})")
        self._pipeline = VoicePipeline(self._pipeline_config, self._transcriber.transcribe, self._vocabulary(),
                                       self._on_result)
        self._command_pub = self.create_publisher(String, "manual_command", 10)
        # acknowledged through the brain's submit_command service when it is up, else this topic (warned once)
        self._commands = CommandClient(self, publisher=self._command_pub)
        self._status_pub = self.create_publisher(String, "audio_command/status", 10)
        if p("object_list_topic"):
            self.create_subscription(String, p("object_list_topic"), self._on_object_list, OBJECT_LIST_QOS)
        self.add_on_set_parameters_callback(self._validate)
        self.add_post_set_parameters_callback(self._apply)
        self._audio_thread = threading.Thread(target=self._audio_loop, name="audio", daemon=True)

    def start(self) -> None:
        """Start listening (the audio thread logs ``ready:`` once the source is open)."""
        self._audio_thread.start()

    def shutdown(self) -> None:
        self._stop.set()
        self._audio_thread.join(2.0)

    # --- parameters -----------------------------------------------------------------------------
    def _p(self, name: str) -> object:
        return self.get_parameter(name).value

    @staticmethod
    def _make_filter(p) -> FilterConfig:  # noqa: ANN001 - a getter
        return FilterConfig(max_no_speech_prob=float(p("max_no_speech_prob")),
                            min_avg_logprob=float(p("min_avg_logprob")),
                            min_stop_avg_logprob=float(p("min_stop_avg_logprob")),
                            max_compression_ratio=float(p("max_compression_ratio")),
                            min_chars=int(p("min_chars")), max_prompt_echo_words=int(p("max_prompt_echo_words")))

    def _make_pipeline_config(self, p) -> PipelineConfig:  # noqa: ANN001 - a getter
        vad = VadConfig(threshold=float(p("vad_threshold")), min_silence_ms=float(p("min_silence_ms")),
                        speech_pad_ms=float(p("speech_pad_ms")), min_speech_ms=float(p("min_speech_ms")),
                        max_utterance_s=float(p("max_utterance_s")),
                        speculative_ms=float(p("speculative_ms")) if p("speculative") else None)
        return PipelineConfig(segmentation=str(p("segmentation")), vad=vad, chunk_s=float(p("chunk_s")),
                              filter=self._make_filter(p), wake_word=str(p("wake_word")),
                              wake_word_timeout_s=float(p("wake_word_timeout_s")))

    def _vocabulary(self) -> Vocabulary:
        with self._vocab_lock:
            objects = self._objects
        return Vocabulary(tuple(self._p("command_phrases")), objects, tuple(self._p("places")),
                          str(self._p("wake_word")))

    def _validate(self, params: list[Parameter]) -> SetParametersResult:
        values = {name: self._p(name) for name in _PARAMS}
        values.update({q.name: q.value for q in params})
        try:
            self._make_pipeline_config(values.__getitem__)
        except SpeechError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply(self, params: list[Parameter]) -> None:
        names = {q.name for q in params}
        if names & {"max_no_speech_prob", "min_avg_logprob", "min_stop_avg_logprob", "max_compression_ratio",
                    "min_chars", "max_prompt_echo_words"}:
            self._pipeline.set_filter(self._make_filter(self._p))
        if names & {"wake_word", "wake_word_timeout_s"}:
            self._pipeline.set_wake_word(str(self._p("wake_word")), float(self._p("wake_word_timeout_s")))
        if names & {"command_phrases", "places", "wake_word"}:
            self._update_vocabulary()

    # --- vocabulary -----------------------------------------------------------------------------
    def _on_object_list(self, msg: String) -> None:
        try:
            names = parse_object_list(msg.data)
        except SpeechError as exc:
            self.get_logger().warning(f"ignoring /object_list: {exc}")
            return
        with self._vocab_lock:
            self._objects = names
        self._update_vocabulary()

    def _update_vocabulary(self) -> None:
        vocab = self._vocabulary()
        self._pipeline.set_vocabulary(vocab)
        prompt = self._pipeline.prompt
        self.get_logger().info(f"vocabulary: {prompt}")
        self._status({"event": "vocabulary", "prompt": prompt, "objects": list(vocab.objects)})

    # --- audio ----------------------------------------------------------------------------------
    def _status(self, payload: dict) -> None:
        self._status_pub.publish(String(data=json.dumps(payload)))

    def _on_result(self, result: Result) -> None:  # pipeline's result thread
        if result.command:
            self._commands.submit_async(result.command, lambda ack: ack.accepted or self.get_logger().warn(
                f"command '{ack.text}' {ack.state}: {ack.message}"))
            self.get_logger().info(f"command: '{result.command}' (confidence {result.confidence:.2f}, "
                                   f"latency {result.latency_s:.2f} s)")
        elif result.dropped == "empty":  # silence: every chunk of it in fixed mode
            self.get_logger().debug("dropped (empty)")
        else:
            self.get_logger().info(f"dropped ({result.dropped}): '{result.raw}'")
        self._status_pub.publish(String(data=result.to_json()))

    def _audio_loop(self) -> None:
        """The audio thread: :meth:`_listen`, and any failure it did not expect reported and the node ended (exit 2)
        instead of a node that runs on with no audio."""
        try:
            self._listen()
        except Exception as exc:  # noqa: BLE001 - the thread's last word: logged, the node exits
            self.get_logger().error(f"audio failed: {exc!r}\n{traceback.format_exc()}")
            self._status({"event": "device_error", "message": f"audio failed: {exc!r}"[:300]})
            self.exit_code = 2
            self.done.set()

    def _listen(self) -> None:
        p = self._p
        kind = str(p("source"))
        retry_s = float(p("retry_s"))
        announced = False
        while not self._stop.is_set():
            try:
                source = open_source(kind, device=str(p("input_device")), wav_path=str(p("wav_path")),
                                     pacing=float(p("pacing")), sample_rate=int(p("stdin_sample_rate")))
            except AudioSourceError as exc:
                if self._device_problem(exc, retry_s):
                    continue
                return
            if not announced:
                self.get_logger().info(f"ready: listening on {source.name} ({self._pipeline_config.segmentation} "
                                       f"segmentation); commands go to /manual_command")
                announced = True
            if kind != "microphone":
                self._wait_for_subscribers(float(p("wait_for_subscriber_s")))
            self._status({"event": "ready", "source": source.name,
                          "segmentation": self._pipeline_config.segmentation, "prompt": self._pipeline.prompt})
            try:
                self._pipeline.run(source, self._stop)
            except AudioSourceError as exc:
                if self._device_problem(exc, retry_s):
                    continue
                return
            finally:
                source.close()
            if kind == "microphone" or self._stop.is_set():
                continue
            self.get_logger().info(f"end of {source.name}")
            self._status({"event": "end_of_source", "source": source.name})
            if p("exit_at_end"):
                self.done.set()
            return

    def _wait_for_subscribers(self, timeout_s: float) -> None:
        """Recorded audio (WAV/stdin) is not played into the void: wait for a command subscriber.

        ``timeout_s`` <= 0 = do not wait; after the timeout the stream starts anyway.
        """
        if timeout_s <= 0:
            return
        deadline = time.monotonic() + timeout_s
        while not self._stop.is_set() and time.monotonic() < deadline:
            if self._command_pub.get_subscription_count() > 0 and self._status_pub.get_subscription_count() > 0:
                self._stop.wait(0.3)  # let the subscriber's side finish matching too
                return
            self._stop.wait(0.05)
        self.get_logger().warning(f"no subscriber on /manual_command after {timeout_s:g} s; streaming anyway")

    def _device_problem(self, exc: AudioSourceError, retry_s: float) -> bool:
        """Report a source problem; True = retry after the wait, False = give up (node exits)."""
        self.get_logger().error(str(exc))
        self._status({"event": "device_error", "message": str(exc)})
        if isinstance(exc, AudioDeviceError) and retry_s > 0:
            self.get_logger().warning(f"retrying in {retry_s:g} s (retry_s)")
            return not self._stop.wait(retry_s)
        self.exit_code = 2
        self.done.set()
        return False


def main(args: list[str] | None = None) -> int:
    rclpy.init(args=args)
    node = build_node(AudioCommandNode, "audio_command_node", (SpeechError,))
    if node is None:
        return 2
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    node.start()
    try:
        while rclpy.ok() and not node.done.is_set():
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.shutdown()
        code = node.exit_code
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    raise SystemExit(main())
