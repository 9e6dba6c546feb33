"""Typed errors of the object-query package."""


class ObjectQueryError(Exception):
    """Base class of every error raised by the object-query core."""


class MapLoadError(ObjectQueryError):
    """A map or semantic-label file is missing, unreadable or malformed."""


class SynonymsError(ObjectQueryError):
    """The synonyms YAML file is missing or malformed."""


class ObjectMemoryError(ObjectQueryError):
    """A memory update or memory file is invalid."""
