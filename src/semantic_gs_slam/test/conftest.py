"""Shared fixtures: tiny synthetic sequences (generated once per session)."""

from __future__ import annotations

import pytest
import torch

torch.set_num_threads(1)


@pytest.fixture(scope="session")
def tiny_home(tmp_path_factory):
    """A 10-frame 120x68 synthetic home sequence in the Replica layout (2 degrees of orbit per frame)."""
    from semantic_gs_slam.synthetic.scenes import generate

    out = tmp_path_factory.mktemp("home")
    generate(str(out), frames=10, width=120, height=68, span_deg=20.0)
    return out
