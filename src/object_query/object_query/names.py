"""Object names as people say them: normalisation, synonyms, "did you mean" (no ROS).

Synonyms file (YAML)::

    synonyms:
      - [sofa, couch, settee]      # a group of names for one kind of object
      - [cup, mug]
      - [bin, trash can, dustbin]

A query resolves to the first name of its group that the map knows, so both ``couch``→``sofa``
and ``cup``→``mug`` work, whichever of them the map's semantic table uses.
"""

from __future__ import annotations

import difflib
import os
import unicodedata
from dataclasses import dataclass, field

import yaml

from object_query.errors import SynonymsError

#: Longest object name accepted in a query (characters, after normalisation).
MAX_NAME_LENGTH = 256
#: Longest name looked at before normalisation (characters): NFKC may turn one character into 18, so a request's
#: name is measured before it is normalised, and a longer one refused unread (bounded work per request).
MAX_RAW_NAME_LENGTH = 4 * MAX_NAME_LENGTH


#: Farthest a position given to the object database or memory may be from the map's origin (m): a home, with room
#: to spare (a reported position, an /object_instances reference); farther is a bad value, refused with the reason.
MAX_COORD_M = 1000.0


def raw_name_error(name: str, what: str = "object name") -> str:
    """Why a name given in a request is refused before it is normalised ("" when it is not): longer than
    :data:`MAX_RAW_NAME_LENGTH` characters."""
    n = len(name)
    return f"{what} too long ({n} characters, at most {MAX_RAW_NAME_LENGTH})" if n > MAX_RAW_NAME_LENGTH else ""


def normalise_name(name: str) -> str:
    """Canonical form of an object name: NFKC, case-folded, ``_``/``-`` as spaces, single spaces.

    Control characters are dropped. ``"  Trash_Can "`` → ``"trash can"``.
    """
    text = unicodedata.normalize("NFKC", str(name)).casefold()
    chars = []
    for ch in text:
        if ch.isspace() or ch in "_-":
            chars.append(" ")
        elif unicodedata.category(ch)[0] != "C":  # drop control/format/unassigned characters
            chars.append(ch)
    return " ".join("".join(chars).split())


def shorten(text: str, limit: int = 64) -> str:
    """``text`` cut to ``limit`` characters with an ellipsis, for messages."""
    return text if len(text) <= limit else text[: limit - 3] + "..."


@dataclass(frozen=True)
class Synonyms:
    """Groups of equivalent names (already normalised), each group in preference order."""

    groups: tuple[tuple[str, ...], ...] = ()
    _index: dict[str, tuple[int, ...]] = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        index: dict[str, list[int]] = {}
        for g, group in enumerate(self.groups):
            for name in group:
                index.setdefault(name, []).append(g)
        object.__setattr__(self, "_index", {k: tuple(v) for k, v in index.items()})

    def alternatives(self, name: str) -> list[str]:
        """Other names of ``name`` (normalised), in group order, without ``name`` itself."""
        out: list[str] = []
        for g in self._index.get(name, ()):
            out.extend(n for n in self.groups[g] if n != name and n not in out)
        return out

    def all_names(self) -> list[str]:
        """Every name mentioned in any group."""
        return sorted(self._index)


def load_synonyms(path: str) -> Synonyms:
    """Read a synonyms YAML file (see module docstring). An empty path gives no synonyms.

    Raises:
        SynonymsError: missing file, bad YAML, or a bad structure; the message names the file.
    """
    if not path:
        return Synonyms()
    if not os.path.isfile(path):
        raise SynonymsError(f"synonyms file not found: synonyms_path={path!r}")
    try:
        with open(path, encoding="utf-8") as fh:
            doc = yaml.safe_load(fh)
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise SynonymsError(f"{path}: not valid YAML ({exc})") from exc
    groups_raw = doc.get("synonyms") if isinstance(doc, dict) else None
    if not isinstance(groups_raw, list):
        raise SynonymsError(f"{path}: expected a mapping with a 'synonyms' list of name lists")
    groups: list[tuple[str, ...]] = []
    for i, group in enumerate(groups_raw):
        if not isinstance(group, list) or len(group) < 2 or not all(isinstance(n, str) for n in group):
            raise SynonymsError(f"{path}: synonyms[{i}] must be a list of at least two names, got {group!r}")
        names = tuple(dict.fromkeys(normalise_name(n) for n in group if normalise_name(n)))
        if len(names) < 2:
            raise SynonymsError(f"{path}: synonyms[{i}] has fewer than two distinct names: {group!r}")
        groups.append(names)
    return Synonyms(tuple(groups))


def closest_names(name: str, known: list[str], n: int = 3) -> list[str]:
    """Up to ``n`` names of ``known`` that look like ``name`` (difflib ratio >= 0.6), best first."""
    return difflib.get_close_matches(name, known, n=n, cutoff=0.6)


def singular_forms(name: str) -> list[str]:
    """Candidate singulars of an English plural: ``cups``→``cup``, ``boxes``→``box``, ``bottles``→``bottle``."""
    out = []
    if name.endswith("ies") and len(name) > 4:
        out.append(name[:-3] + "y")
    if name.endswith("es") and len(name) > 3:
        out.append(name[:-2])
    if name.endswith("s") and not name.endswith("ss") and len(name) > 2:
        out.append(name[:-1])
    return out
