"""Speech core of the voice input (no ROS): audio sources, endpointing, Whisper, filtering.

``audio_command_node`` is the thin ROS shell around :class:`~decision_maker.speech.pipeline.VoicePipeline`.
"""
