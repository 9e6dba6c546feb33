"""Unit tests of name handling (no ROS): normalisation, the synonyms file, suggestions."""

from __future__ import annotations

import os

import pytest

from object_query.errors import SynonymsError
from object_query.names import closest_names, load_synonyms, normalise_name, singular_forms

BUNDLED = os.path.join(os.path.dirname(__file__), "..", "config", "synonyms.yaml")


@pytest.mark.parametrize("raw, norm", [("  Trash_Can ", "trash can"), ("TRASH-CAN", "trash can"),
                                       ("Straße", "strasse"), ("ｃｕｐ", "cup"), ("a\x00b\u200bc", "abc"), ("\t\n", ""),
                                       ("dining\ttable", "dining table")])
def test_normalise(raw, norm):
    assert normalise_name(raw) == norm


def test_bundled_synonyms_cover_the_issue_examples():
    syn = load_synonyms(BUNDLED)
    assert "sofa" in syn.alternatives("couch")
    assert "mug" in syn.alternatives("cup") and "cup" in syn.alternatives("mug")
    assert "bin" in syn.alternatives("trash can")


def test_empty_path_means_no_synonyms():
    assert load_synonyms("").groups == ()


@pytest.mark.parametrize("text, pattern", [("synonyms: [", "not valid YAML"), ("- [a, b]", "'synonyms' list"),
                                           ("synonyms: [[a]]", r"synonyms\[0\] must be a list of at least two"),
                                           ("synonyms: [[a, 3]]", r"synonyms\[0\]"),
                                           ("synonyms: [[Cup, CUP]]", "fewer than two distinct")])
def test_bad_synonyms_files(tmp_path, text, pattern):
    p = tmp_path / "syn.yaml"
    p.write_text(text)
    with pytest.raises(SynonymsError, match=pattern):
        load_synonyms(str(p))


def test_missing_synonyms_file_names_the_parameter(tmp_path):
    with pytest.raises(SynonymsError, match=r"synonyms_path=.*nope\.yaml"):
        load_synonyms(str(tmp_path / "nope.yaml"))


def test_closest_and_singulars():
    assert closest_names("bottel", ["bottle", "table", "bin"]) == ["bottle"]
    assert closest_names("zzz", ["bottle"]) == []
    assert "box" in singular_forms("boxes") and "cup" in singular_forms("cups") and "berry" in singular_forms("berries")
    assert singular_forms("glass") == []


def test_bundled_synonyms_cover_the_coco_names_people_say():
    """The words people say for the COCO detector's classes lead to those classes (mug -> cup, TV -> tv, ...)."""
    syn = load_synonyms(BUNDLED)
    for said, coco in [("mug", "cup"), ("table", "dining table"), ("television", "tv"), ("TV", "tv"),
                       ("sofa", "couch"), ("fridge", "refrigerator"), ("plant", "potted plant"),
                       ("phone", "cell phone"), ("glass", "wine glass"), ("notebook computer", "laptop")]:
        key = normalise_name(said)
        assert key == coco or coco in syn.alternatives(key), (said, coco)
    for name in ("laptop", "book", "bottle", "bowl", "chair"):
        assert syn.alternatives(name), name
