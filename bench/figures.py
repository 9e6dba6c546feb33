"""Let a benchmark write its figures into docs/figures.md.

A benchmark's block in ``docs/figures.md`` sits between two markers::

    <!-- figures:NAME -->
    ... replaced as a whole ...
    <!-- /figures:NAME -->

A benchmark that supports it takes ``--write-figures`` (:func:`add_argument`), notes the load before it measures
(:func:`Provenance.start`), and at the end calls :func:`write_block` with its Markdown table. The block gets a
line with the date, the machine, the load at the start, the commit and the command, so every figure keeps its
provenance. Nothing here changes what a benchmark measures.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import platform
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FIGURES = ROOT / "docs" / "figures.md"


class FiguresError(Exception):
    """The figures file has no block of that name, or its markers are malformed."""


def add_argument(ap: argparse.ArgumentParser) -> None:
    """Add ``--write-figures`` (write this run's figures into docs/figures.md) to a benchmark's parser."""
    ap.add_argument("--write-figures", action="store_true",
                    help=f"replace this benchmark's block in {FIGURES.relative_to(ROOT)} with this run's figures")


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _gpu_name() -> str:
    """The first GPU's name from nvidia-smi, or "" (no GPU, or no driver tools)."""
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                             text=True, timeout=10, check=False)
    except (OSError, subprocess.SubprocessError):
        return ""
    return out.stdout.strip().splitlines()[0] if out.returncode == 0 and out.stdout.strip() else ""


def _commit() -> str:
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              timeout=10, check=False).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True, timeout=10, check=False).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return (head or "unknown") + (" with local changes" if dirty else "")


@dataclass
class Provenance:
    """When, where and how a run was made: the load is taken before the benchmark measures anything."""

    date: str
    machine: str
    load_at_start: float
    commit: str
    command: str

    @classmethod
    def start(cls, argv: list[str] | None = None) -> Provenance:
        """Note the provenance now (call it before measuring)."""
        gpu = _gpu_name()
        machine = f"{os.cpu_count()} cores ({_cpu_name()})" + (f", {gpu}" if gpu else ", no GPU")
        args = sys.argv if argv is None else argv
        script = os.path.relpath(args[0], ROOT) if args else "?"
        command = " ".join(["python", shlex.quote(script), *(shlex.quote(a) for a in args[1:]
                                                             if a != "--write-figures")])
        return cls(date=dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"), machine=machine,
                   load_at_start=os.getloadavg()[0], commit=_commit(), command=command)

    def line(self) -> str:
        """One Markdown line: date, machine, load, commit, command."""
        return (f"*{self.date}, {self.machine}, load {self.load_at_start:.1f} at the start, commit {self.commit}: "
                f"`{self.command}`*")


def replace_block(text: str, name: str, body: str) -> str:
    """``text`` with the block ``name`` replaced by ``body``.

    Raises:
        FiguresError: no block of that name, or more than one.
    """
    if not re.fullmatch(r"[a-z0-9_]+", name):
        raise FiguresError(f"block name must be lower-case letters, digits and _, got {name!r}")
    pattern = re.compile(rf"(<!-- figures:{name} -->\n).*?(<!-- /figures:{name} -->)", re.S)
    found = pattern.findall(text)
    if len(found) != 1:
        raise FiguresError(f"{'no' if not found else len(found)} block(s) <!-- figures:{name} --> ... "
                           f"<!-- /figures:{name} --> in the figures file (exactly one is needed)")
    return pattern.sub(lambda m: m.group(1) + body.rstrip("\n") + "\n" + m.group(2), text)


def write_block(name: str, table: str, provenance: Provenance, path: Path = FIGURES) -> None:
    """Replace block ``name`` of ``path`` with ``table`` and the provenance line, atomically."""
    text = path.read_text(encoding="utf-8")
    new = replace_block(text, name, f"{table.rstrip()}\n\n{provenance.line()}")
    tmp = path.with_suffix(".md.tmp")
    tmp.write_text(new, encoding="utf-8")
    os.replace(tmp, path)
    print(f"figures written into {os.path.relpath(path)} (block {name})")
