"""Voice latency benchmark: end of speech → message on /manual_command, VAD vs fixed 5-s chunks.

Run: ``source scripts/env.sh && python bench/voice_latency.py`` (≈ 2-3 min; needs espeak-ng, sox).

For each mode a real ``audio_command_node`` process reads raw PCM from stdin, written by this
script in real time (20 ms blocks, paced by the clock) — as a microphone would deliver it. The
commands are spoken by espeak-ng (several voices and speeds), trimmed so that the last sample is
the end of speech, separated by silence. Latency = arrival of the command on /manual_command in
this process − the moment the block holding the last speech sample was written. The real-time
factor of transcription comes from the node's status lines (Whisper time / audio seconds).

The machine is shared (2 cores, other jobs running): timings are noisy; the load average is
printed with the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np

from decision_maker.speech import testaudio as ta
from decision_maker.speech.text import word_edit_distance, words
from home_robot_bringup.domain import DomainLease
from home_robot_bringup.nodeset import find_executable
from home_robot_bringup.process import node_environment

COMMANDS = ["give me the bottle", "go home", "clean the table", "stop", "bring me the cup", "cancel",
            "clean table", "give me the cup"]
BLOCK = 320  # samples written per block (20 ms)


@dataclass
class Spoken:
    text: str
    end_sample: int
    end_time: float = float("nan")  # monotonic time the block holding the last speech sample was written


def build_stream(n: int, seed: int = 7) -> tuple[np.ndarray, list[Spoken]]:
    rng = np.random.default_rng(seed)
    parts: list[tuple[str | None, np.ndarray]] = [(None, ta.silence(1.0))]
    for i in range(n):
        voice, speed = ta.VOICES[i % len(ta.VOICES)]
        text = COMMANDS[i % len(COMMANDS)]
        parts += [(None, ta.silence(float(rng.uniform(0.3, 2.0)))), (text, ta.speak(text, voice, speed)),
                  (None, ta.silence(2.0))]
    parts.append((None, ta.silence(6.0)))  # lets the last fixed chunk fill
    stream, utts = ta.compose(parts)
    return stream, [Spoken(u.text, u.end) for u in utts]


def percentile(xs: list[float], q: float) -> float:
    return float(np.percentile(xs, q)) if xs else float("nan")


def run_mode(mode: str, stream: np.ndarray, spoken: list[Spoken], domain: int) -> dict:
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from std_msgs.msg import String

    spoken = [Spoken(s.text, s.end_sample) for s in spoken]
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node("voice_bench", context=ctx)
    lock = threading.Lock()  # guards arrivals, status
    arrivals: list[tuple[float, str]] = []
    status: list[dict] = []

    def on_cmd(msg: String) -> None:
        t = time.monotonic()
        with lock:
            arrivals.append((t, msg.data))

    def on_status(msg: String) -> None:
        with lock:
            status.append(json.loads(msg.data))

    node.create_subscription(String, "manual_command", on_cmd, 50)
    node.create_subscription(String, "audio_command/status", on_status, 100)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    spin = threading.Thread(target=ex.spin, daemon=True)
    spin.start()

    exe = find_executable("decision_maker", "audio_command_node")
    proc = subprocess.Popen([exe, "--ros-args", "-p", "source:=stdin", "-p", f"segmentation:={mode}",
                             "-p", "exit_at_end:=true", "-p", "wait_for_subscriber_s:=30.0"],
                            env=node_environment(domain), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT)
    log: list[bytes] = []
    threading.Thread(target=lambda: log.extend(proc.stdout), daemon=True).start()
    try:
        deadline = time.monotonic() + 60
        while not any(b"ready:" in line for line in list(log)):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("node did not start:\n" + b"".join(log).decode(errors="replace"))
            time.sleep(0.05)
        while node.count_publishers("manual_command") == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(1.0)  # the node waits for our subscription (wait_for_subscriber_s), then reads

        pcm = (np.clip(stream, -1, 1) * 32767).astype("<i2")
        ends = sorted((s.end_sample, i) for i, s in enumerate(spoken))
        next_end = 0
        t0 = time.monotonic()
        for start in range(0, pcm.size, BLOCK):
            stop = min(start + BLOCK, pcm.size)
            due = t0 + stop / 16000
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            proc.stdin.write(pcm[start:stop].tobytes())
            proc.stdin.flush()
            now = time.monotonic()
            while next_end < len(ends) and ends[next_end][0] <= stop:
                spoken[ends[next_end][1]].end_time = now
                next_end += 1
        proc.stdin.close()
        deadline = time.monotonic() + 60
        while not any(s.get("event") == "end_of_source" for s in list(status)) and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(0.5)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
        ex.shutdown(timeout_sec=1.0)
        node.destroy_node()
        ctx.try_shutdown()

    # match each command to the latest spoken utterance that had ended before it arrived
    latencies, right, heard = [], 0, []
    used: set[int] = set()
    with lock:
        got = list(arrivals)
    for t, text in got:
        cands = [i for i, s in enumerate(spoken) if s.end_time <= t and i not in used]
        if not cands:
            continue
        best = min(cands[-2:], key=lambda i: (word_edit_distance(text, spoken[i].text), -i))
        used.add(best)
        latencies.append(t - spoken[best].end_time)
        ok = words(text) == words(spoken[best].text)
        right += ok
        heard.append(f"{spoken[best].text!r}→{text!r}" + ("" if ok else " ✗"))
    utts = [s for s in status if s.get("event") == "utterance"]
    whisper_s = sum(u["transcribe_s"] for u in utts)
    audio_s = sum(u["audio_s"] for u in utts)
    return {
        "mode": mode, "spoken": len(spoken), "published": len(got), "exact": right,
        "median_s": statistics.median(latencies) if latencies else float("nan"),
        "p90_s": percentile(latencies, 90), "max_s": max(latencies) if latencies else float("nan"),
        "rtf": whisper_s / audio_s if audio_s else float("nan"),
        "whisper_per_utt_s": statistics.median([u["transcribe_s"] for u in utts]) if utts else float("nan"),
        "speculative": sum(bool(u.get("speculative")) for u in utts), "transcriptions": len(utts),
        "heard": heard,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--utterances", type=int, default=12)
    ap.add_argument("--modes", default="vad,fixed")
    ap.add_argument("-v", "--verbose", action="store_true", help="print what was heard")
    args = ap.parse_args(argv)
    if ta.missing_tools():
        print(f"needs {ta.missing_tools()} (apt-get install espeak-ng sox)", file=sys.stderr)
        return 2
    stream, spoken = build_stream(args.utterances)
    print(f"stream: {stream.size / 16000:.1f} s, {len(spoken)} commands (espeak-ng, {len(ta.VOICES)} voices), "
          f"written to the node's stdin in real time; load average before: {os.getloadavg()[0]:.2f} on "
          f"{os.cpu_count()} cores")
    rows = []
    with DomainLease() as lease:
        for mode in args.modes.split(","):
            rows.append(run_mode(mode, stream, spoken, lease.domain_id))
            if args.verbose:
                print(f"  {mode}: " + ", ".join(rows[-1]["heard"]))
    print(f"{'mode':6} {'spoken':>6} {'published':>9} {'exact':>5} {'median s':>8} {'p90 s':>6} {'max s':>6} "
          f"{'whisper/utt s':>13} {'RTF':>5} {'speculative':>11}")
    for r in rows:
        print(f"{r['mode']:6} {r['spoken']:6d} {r['published']:9d} {r['exact']:5d} {r['median_s']:8.3f} "
              f"{r['p90_s']:6.3f} {r['max_s']:6.3f} {r['whisper_per_utt_s']:13.3f} {r['rtf']:5.2f} "
              f"{r['speculative']:>5d}/{r['transcriptions']:<5d}")
    print(f"load average after: {os.getloadavg()[0]:.2f} (shared machine: timings are noisy). "
          "RTF = Whisper seconds / audio seconds transcribed (fixed mode transcribes every 5 s chunk).")
    vad = [r for r in rows if r["mode"] == "vad"]
    if vad:
        print(f"target median < 0.8 s with VAD: {'met' if vad[0]['median_s'] < 0.8 else 'NOT met'} "
              f"({vad[0]['median_s']:.3f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
