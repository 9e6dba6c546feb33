#!/usr/bin/env python3
"""Check that every relative link and #anchor in README.md and docs/**/*.md resolves.

Anchors follow GitHub's rule: the heading in lower case, characters other than letters, digits, spaces,
hyphens and underscores removed, spaces turned into hyphens, repeats numbered -1, -2, ...

Usage: python scripts/check_doc_links.py [--allow-missing PATH ...]. Exit 0 when every link resolves, 1 otherwise
(each broken link printed as FILE:LINE: TARGET: reason).
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
FENCE = re.compile(r"^\s*(```|~~~)")


def slug(text: str) -> str:
    """GitHub's anchor of a heading."""
    text = re.sub(r"`([^`]*)`", r"\1", text)
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)
    text = text.strip().lower()
    text = "".join(c for c in text if c.isalnum() or c in " -_")
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every anchor a Markdown file defines (headings, numbered repeats, and explicit <a id/name>)."""
    seen: dict[str, int] = {}
    out: set[str] = set()
    in_fence = False
    for line in path.read_text(encoding="utf-8").splitlines():
        if FENCE.match(line):
            in_fence = not in_fence
            continue
        if in_fence:
            continue
        m = HEADING.match(line)
        if m:
            base = slug(m.group(2))
            n = seen.get(base, 0)
            out.add(base if n == 0 else f"{base}-{n}")
            seen[base] = n + 1
        out.update(re.findall(r"<a\s+(?:id|name)=\"([^\"]+)\"", line))
    return out


def links(path: Path):
    """(line number, target) of every Markdown link outside code fences and inline code."""
    in_fence = False
    for no, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if FENCE.match(line):
            in_fence = not in_fence
            continue
        if in_fence:
            continue
        for target in LINK.findall(re.sub(r"`[^`]*`", "", line)):
            yield no, target


def check(files: list[Path], allow_missing: set[Path]) -> list[str]:
    problems = []
    cache: dict[Path, set[str]] = {}
    for f in files:
        for no, target in links(f):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("//"):
                continue  # http:, https:, mailto: ... are not checked here
            path_part, _, anchor = target.partition("#")
            dest = (f.parent / path_part).resolve() if path_part else f
            where = f"{f.relative_to(ROOT)}:{no}: {target}"
            if not dest.exists():
                if dest not in allow_missing:
                    problems.append(f"{where}: no such file")
                continue
            if anchor and dest.suffix == ".md":
                if dest not in cache:
                    cache[dest] = anchors(dest)
                if anchor not in cache[dest]:
                    problems.append(f"{where}: no heading with anchor #{anchor}")
    return problems


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--allow-missing", nargs="*", default=[],
                    help="files that may not exist yet (pages another branch brings), relative to the repository")
    args = ap.parse_args(argv)
    files = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    allow = {(ROOT / p).resolve() for p in args.allow_missing}
    problems = check(files, allow)
    for p in problems:
        print(p)
    print(f"{len(files)} files checked, {len(problems)} broken link(s)")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
