"""The command senders' side, used by the input nodes (text, voice, cancel) to reach the decision maker.

* :mod:`.command_client` — the client of the decision maker's command service.
* :mod:`.console` — the terminal prompt of the text and cancel nodes.
"""
