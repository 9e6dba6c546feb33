"""The real Whisper tiny.en (bundled, offline) on espeak-ng commands, noise and silence.

The model is loaded once for the module.
"""

import numpy as np
import pytest

from decision_maker.speech import testaudio as ta
from decision_maker.speech.filtering import FilterConfig, judge
from decision_maker.speech.pipeline import PipelineConfig, VoicePipeline
from decision_maker.speech.sources import WavFileSource
from decision_maker.speech.transcriber import Transcriber, TranscriberConfig, bundled_model_path, resolve_model
from decision_maker.speech.vocabulary import Vocabulary

from .voice_testing import MISSING, SKIP_REASON, matches

pytestmark = pytest.mark.skipif(bool(MISSING), reason=SKIP_REASON)

VOCAB = Vocabulary(objects=("bin", "bottle", "chair", "cup", "sofa", "table", "trash"))
COMMANDS = ["give me the bottle", "bring me the cup", "go home", "clean table", "clean the table", "stop", "cancel"]
PAD = ta.silence(0.2)


@pytest.fixture(scope="module")
def transcriber():
    return Transcriber(TranscriberConfig())


def test_bundled_model_is_resolved_offline():
    path = bundled_model_path()
    assert resolve_model("") == path and resolve_model("bundled") == path
    assert resolve_model("tiny.en") == "tiny.en"  # a name is passed through (must be cached locally)


def test_unknown_model_name_fails_without_downloading():
    from decision_maker.speech.errors import ModelLoadError

    with pytest.raises(ModelLoadError, match="nothing is downloaded"):
        Transcriber(TranscriberConfig(model="no-such-model-xyz"))


@pytest.mark.parametrize("noisy", [False, True], ids=["clean", "pink-noise"])
def test_commands_in_several_voices(transcriber, noisy):
    failures = []
    for i, command in enumerate(COMMANDS):
        voice, speed = ta.VOICES[(i + noisy) % len(ta.VOICES)]
        audio = np.concatenate([PAD, ta.speak(command, voice, speed), PAD])
        if noisy:  # moderate pink noise under the speech (≈ 12 dB below it)
            audio = audio + np.resize(ta.noise("pinknoise", audio.size / 16000 + 0.1, 0.08, seed=i + 2), audio.size)
        tr = transcriber.transcribe(audio, VOCAB.prompt())
        verdict = judge(tr.text, tr.no_speech_prob, tr.avg_logprob, tr.compression_ratio, FilterConfig(),
                        VOCAB.prompt_words())
        if not (verdict.kept and matches(verdict.text, command)):
            failures.append(f"{command!r} ({voice} {speed}) -> {tr.text!r} {verdict.reason}")
    assert not failures, failures


def test_noise_and_silence_give_no_command(transcriber):
    for name, audio in [("silence", ta.silence(2.0)), ("pink", ta.noise("pinknoise", 2.0, 0.1)),
                        ("white", ta.noise("whitenoise", 2.0, 0.05))]:
        tr = transcriber.transcribe(audio, VOCAB.prompt())
        verdict = judge(tr.text, tr.no_speech_prob, tr.avg_logprob, tr.compression_ratio, FilterConfig(),
                        VOCAB.prompt_words())
        assert not verdict.kept, f"{name} gave {tr.text!r}"


def test_object_names_in_the_prompt_fix_rare_words(transcriber):
    audio = np.concatenate([PAD, ta.speak("give me the teapot", "en-us", 170), PAD])
    with_teapot = transcriber.transcribe(audio, VOCAB.with_objects(["bottle", "teapot"]).prompt())
    assert matches(with_teapot.text, "give me the teapot") and "teapot" in with_teapot.text.lower()


def test_pipeline_with_wake_word(transcriber, tmp_path):
    stream, _ = ta.compose([
        (None, ta.silence(0.5)), ("robot go home", ta.speak("robot, go home", "en-us", 150)), (None, ta.silence(1.0)),
        ("stop", ta.speak("stop", "en+f2", 170)), (None, ta.silence(1.0)),
    ])
    ta.write_wav(str(tmp_path / "wake.wav"), stream)
    results = []
    cfg = PipelineConfig(wake_word="robot")
    vocab = Vocabulary(VOCAB.command_phrases, VOCAB.objects, wake_word="robot")
    VoicePipeline(cfg, transcriber.transcribe, vocab, results.append).run(WavFileSource(str(tmp_path / "wake.wav"),
                                                                                        pacing=0))
    assert [r.command for r in results] == ["go home", None], [r.to_json() for r in results]
    assert results[1].dropped == "no_wake_word" and matches(results[1].text, "stop")


#: Held-out voices/speeds (not in ta.VOICES) where the vocabulary prompt pulls "give me" towards
#: "clean" ("good, clean the cup": en-gb and en-gb-x-rp at 190 words per minute, 0.3 s of silence
#: around the speech, measured).
HELD_OUT = [("give me the cup", "en-gb", 190), ("give me the cup", "en-gb-x-rp", 190)]


def test_grammar_rescoring_recovers_commands_the_prompt_pulled_away(transcriber):
    pad = ta.silence(0.3)
    rescored = []
    for command, voice, speed in HELD_OUT:
        audio = np.concatenate([pad, ta.speak(command, voice, speed), pad])
        plain = transcriber.transcribe(audio, VOCAB.prompt())
        tr = transcriber.transcribe(audio, VOCAB.prompt(), grammar=VOCAB.in_grammar)
        said = tr.text.lower().rstrip(".")
        if VOCAB.in_grammar(plain.text):  # nothing to rescore: the transcript is kept as it is
            assert tr.text == plain.text, (voice, speed, plain.text, tr.text)
            continue
        # the failure reproduced: never a different command; recovered, it says what it replaced
        assert said == command or not VOCAB.in_grammar(tr.text), (voice, speed, plain.text, tr.text)
        if said == command:
            assert tr.avg_logprob > FilterConfig().min_avg_logprob  # the filter keeps it
            assert tr.rescored_from == plain.text and tr.hypotheses > 0
            rescored.append(plain.text)
    # the failure of the issue reproduces and is recovered here (else this test no longer tests the
    # rescoring); which case it is varies: CTranslate2 int8 on a busy CPU does not always give the
    # same best transcript, and sometimes a mishearing whose beam holds no command ("good leave the cup")
    assert rescored, "neither held-out case reproduced the failure and was recovered"


def test_grammar_does_not_pull_a_misheard_word_to_another_object(transcriber):
    """en-gb at 160 wpm: "chair" → "cab"; the beam's "bring me the cup" is 0.36 lower: not taken."""
    audio = np.concatenate([PAD, ta.speak("bring me the chair", "en-gb", 160), PAD])
    plain = transcriber.transcribe(audio, VOCAB.prompt())
    if VOCAB.in_grammar(plain.text):
        pytest.skip(f"Whisper heard {plain.text!r} on this machine: no misheard word to guard")
    tr = transcriber.transcribe(audio, VOCAB.prompt(), grammar=VOCAB.in_grammar)
    assert tr.text.lower().rstrip(".") != "bring me the cup", tr
    loose = Transcriber.__new__(Transcriber)  # same loaded model, a wide margin: the danger it guards against
    loose.__dict__.update(transcriber.__dict__, config=TranscriberConfig(grammar_max_drop=5.0))
    loose.__dict__.pop("_window_decoder", None)
    wide = loose.transcribe(audio, VOCAB.prompt(), grammar=VOCAB.in_grammar)
    if wide.rescored_from and wide.text.lower().rstrip(".") != "bring me the chair":
        # without the margin the beam's wrong command was taken, which the default margin does not publish
        # (when the beam holds no command at all, both keep Whisper's mishearing: nothing to compare)
        assert tr.text != wide.text, (tr, wide)


def test_grammar_path_equals_faster_whisper_when_in_grammar(transcriber):
    """The one-window decoder reproduces WhisperModel.transcribe (text and score) for commands."""
    for i, command in enumerate(COMMANDS[:4]):  # 4 voices/speeds, 4 commands (CPU time)
        voice, speed = ta.VOICES[i % len(ta.VOICES)]
        audio = np.concatenate([PAD, ta.speak(command, voice, speed), PAD])
        plain = transcriber.transcribe(audio, VOCAB.prompt())
        tr = transcriber.transcribe(audio, VOCAB.prompt(), grammar=VOCAB.in_grammar)
        if VOCAB.in_grammar(plain.text):
            assert (tr.text, tr.rescored_from, tr.hypotheses) == (plain.text, "", 0)
            assert tr.avg_logprob == pytest.approx(plain.avg_logprob, abs=1e-4)
            assert tr.no_speech_prob == pytest.approx(plain.no_speech_prob, abs=1e-4)


def test_grammar_leaves_other_speech_and_noise_alone(transcriber):
    """Speech that is no command stays what Whisper heard; noise and silence still give nothing."""
    for text in ("what time is it", "the weather is nice today"):
        audio = np.concatenate([PAD, ta.speak(text, "en-us", 170), PAD])
        tr = transcriber.transcribe(audio, VOCAB.prompt(), grammar=VOCAB.in_grammar)
        assert not VOCAB.in_grammar(tr.text) and tr.rescored_from == "", tr
    for name, audio in [("silence", ta.silence(2.0)), ("pink", ta.noise("pinknoise", 2.0, 0.1)),
                        ("white", ta.noise("whitenoise", 2.0, 0.05))]:
        tr = transcriber.transcribe(audio, VOCAB.prompt(), grammar=VOCAB.in_grammar)
        verdict = judge(tr.text, tr.no_speech_prob, tr.avg_logprob, tr.compression_ratio, FilterConfig(),
                        VOCAB.prompt_words())
        assert not verdict.kept, f"{name} gave {tr.text!r}"


def test_a_misheard_cancel_is_recovered_and_kept_as_a_stop(transcriber):
    """en+m3 at 140 wpm: "cancel" → "console," (prompted); the beam's "cancel" scores about -1.0 to
    -1.4, under the general floor (-1.0) but over the stop floor (-1.6): it is published."""
    audio = np.concatenate([ta.silence(0.3), ta.speak("cancel", "en+m3", 140), ta.silence(0.3)])
    tr = transcriber.transcribe(audio, VOCAB.prompt(), grammar=VOCAB.in_grammar)
    verdict = judge(tr.text, tr.no_speech_prob, tr.avg_logprob, tr.compression_ratio, FilterConfig())
    assert verdict.kept and verdict.text == "cancel", (tr, verdict)
