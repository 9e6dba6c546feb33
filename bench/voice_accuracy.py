#!/usr/bin/env python3
"""Voice accuracy benchmark: commands heard exactly, before vs after command-grammar rescoring.

Run: ``source scripts/env.sh && python bench/voice_accuracy.py [--quick]`` (≈ 3-6 min on 2 busy
cores; needs espeak-ng and sox).

Every command is spoken by espeak-ng in voices and speeds that the tests do not use (British,
Scottish, RP, Lancaster, West Midlands, Caribbean, New York, and the f3/m1/Storm/klatt variants,
at 130/160/190 words per minute), padded with 0.2 s of silence, and transcribed by the bundled
tiny.en with the vocabulary prompt (beam 5), as the node does. Non-command sentences are spoken
too: rescoring must not turn them into commands.

"before" is Whisper's best transcript (what the node published before rescoring); "after" is
the transcript the node publishes now (the best-scoring in-grammar hypothesis when the best one
is outside the grammar). Both come from the same encoder pass of the same audio; a test checks
that "before" equals ``WhisperModel.transcribe``'s text. Figures per utterance: exact (the
normalised text is the command), wrong command (a different command of the grammar: the
dangerous error), other (out of grammar: the decision maker rejects it), and the transcription
time.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np

from decision_maker.speech import testaudio as ta
from decision_maker.speech.filtering import FilterConfig, judge
from decision_maker.speech.text import normalise
from decision_maker.speech.transcriber import Transcriber, TranscriberConfig
from decision_maker.speech.vocabulary import Vocabulary

VOCAB = Vocabulary(objects=("bin", "bottle", "chair", "cup", "sofa", "table", "trash"))
COMMANDS = ["give me the cup", "give me the bottle", "bring me the chair", "give me the trash", "go home",
            "clean table", "clean the table", "stop", "cancel"]
OTHER = ["what time is it", "the weather is nice today", "turn on the light"]
VOICES = ["en-gb", "en-gb-scotland", "en-gb-x-rp", "en-gb-x-gbclan", "en-gb-x-gbcwmd", "en-029", "en-us-nyc",
          "en+f3", "en+m1", "en+Storm", "en+klatt"]
SPEEDS = [130, 160, 190]


def load() -> str:
    one, five, _ = os.getloadavg()
    return f"load average {one:.2f} (1 min) {five:.2f} (5 min) on {os.cpu_count()} CPUs"


def kept_text(tr_text: str, avg_logprob: float, no_speech: float, ratio: float) -> str:
    """The normalised text the node would publish, or "" when the filter drops it."""
    verdict = judge(tr_text, no_speech, avg_logprob, ratio, FilterConfig(), VOCAB.prompt_words())
    return verdict.text if verdict.kept else ""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="4 voices x 2 speeds (≈ 1 min)")
    ap.add_argument("-v", "--verbose", action="store_true", help="print every changed or missed utterance")
    opts = ap.parse_args()
    voices, speeds = (VOICES[:4], SPEEDS[1:]) if opts.quick else (VOICES, SPEEDS)
    missing = ta.missing_tools()
    if missing:
        print(f"needs {', '.join(missing)} (apt-get install espeak-ng sox)")
        return 2
    tr = Transcriber(TranscriberConfig())
    tr.warm_up()
    pad = ta.silence(0.2)
    print(f"{len(voices)} voices x {len(speeds)} speeds x ({len(COMMANDS)} commands + {len(OTHER)} other "
          f"sentences); tiny.en int8 beam 5 with the vocabulary prompt; {load()}")
    before = {"exact": 0, "wrong command": 0, "other": 0}
    after = dict(before)
    false_before = false_after = 0
    times: list[float] = []
    rescored = 0
    t_start = time.perf_counter()
    for voice in voices:
        for speed in speeds:
            for said in COMMANDS + OTHER:
                audio = np.concatenate([pad, ta.speak(said, voice, speed), pad])
                t = tr.transcribe(audio, VOCAB.prompt(), grammar=VOCAB.in_grammar)
                times.append(t.elapsed_s)
                after_text = kept_text(t.text, t.avg_logprob, t.no_speech_prob, t.compression_ratio)
                # before = Whisper's best hypothesis of the same pass (score unknown once replaced: judge on text)
                before_text = (normalise(t.rescored_from) if t.rescored_from else after_text)
                rescored += bool(t.rescored_from)
                if said in OTHER:
                    false_before += VOCAB.in_grammar(before_text)
                    false_after += VOCAB.in_grammar(after_text)
                    continue
                for text, tally in ((before_text, before), (after_text, after)):
                    kind = ("exact" if text == said else "wrong command" if VOCAB.in_grammar(text) else "other")
                    tally[kind] += 1
                if opts.verbose and (t.rescored_from or after_text != said):
                    print(f"  {voice:15s} {speed}  {said!r:22s} before {before_text!r:28s} after {after_text!r}")
    n = len(voices) * len(speeds) * len(COMMANDS)
    m = len(voices) * len(speeds) * len(OTHER)
    wall = time.perf_counter() - t_start
    print(f"commands exact:          before {before['exact']:3d}/{n}   after {after['exact']:3d}/{n}   "
          f"(+{after['exact'] - before['exact']})")
    print(f"wrong command published: before {before['wrong command']:3d}/{n}   after {after['wrong command']:3d}/{n}")
    print(f"out of grammar (rejected by the decision maker): before {before['other']}/{n}, after {after['other']}/{n}")
    print(f"non-command speech turned into a command: before {false_before}/{m}, after {false_after}/{m}")
    ts = sorted(times)
    print(f"transcription per utterance (grammar path): median {statistics.median(ts):.2f} s, "
          f"p90 {ts[int(0.9 * (len(ts) - 1))]:.2f} s; {rescored} of {len(ts)} utterances rescored; "
          f"{wall:.0f} s in all; {load()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
