"""The documents' tooling: the figures blocks benchmarks rewrite, and the link checker."""

import importlib.util
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _load(name, path):
    spec = importlib.util.spec_from_file_location(name, os.path.join(ROOT, path))
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


figures = _load("bench_figures", "bench/figures.py")

PAGE = """# Figures
<!-- figures:a -->
old a
<!-- /figures:a -->
text between
<!-- figures:b -->
old b
<!-- /figures:b -->
"""


def test_replace_block_changes_only_its_block():
    out = figures.replace_block(PAGE, "a", "new a\nsecond line\n")
    assert "<!-- figures:a -->\nnew a\nsecond line\n<!-- /figures:a -->" in out
    assert "old a" not in out
    assert "old b" in out and "text between" in out


@pytest.mark.parametrize("name", ["missing", "Bad-Name"])
def test_replace_block_refuses_a_block_it_cannot_find(name):
    with pytest.raises(figures.FiguresError):
        figures.replace_block(PAGE, name, "x")


def test_replace_block_refuses_a_duplicated_block():
    with pytest.raises(figures.FiguresError, match="2 block"):
        figures.replace_block(PAGE + PAGE, "a", "x")


def test_write_block_keeps_the_provenance(tmp_path):
    page = tmp_path / "figures.md"
    page.write_text(PAGE)
    prov = figures.Provenance(date="2026-01-01 00:00 UTC", machine="2 cores", load_at_start=1.5, commit="abc",
                              command="python bench/x.py")
    figures.write_block("b", "| m | v |\n|---|---|\n| t | 1 |", prov, path=page)
    text = page.read_text()
    assert "| t | 1 |" in text and "load 1.5 at the start, commit abc: `python bench/x.py`" in text
    assert "old a" in text


def test_link_checker_finds_a_broken_anchor_and_file(tmp_path):
    checker = _load("check_doc_links", "scripts/check_doc_links.py")
    ok = tmp_path / "a.md"
    ok.write_text("# Title `x`\n## Same\n## Same\n[1](#title-x) [2](#same-1) [3](b.md)\n```\n[no](#inside-code)\n```\n")
    bad = tmp_path / "b.md"
    bad.write_text("[gone](a.md#nowhere) [missing](c.md)\n")
    checker.ROOT = tmp_path
    problems = checker.check([ok, bad], allow_missing=set())
    assert len(problems) == 2
    assert "no heading with anchor #nowhere" in problems[0] and "no such file" in problems[1]


def test_repository_documents_have_no_broken_links():
    r = subprocess.run([sys.executable, os.path.join(ROOT, "scripts", "check_doc_links.py")],
                       capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr
