from __future__ import annotations

from pathlib import Path

import pytest
import torch

from train_helpers import tiny_scene


@pytest.fixture(scope="session")
def tiny_room(tmp_path_factory) -> Path:
    return tiny_scene(tmp_path_factory.mktemp("train") / "room")


@pytest.fixture(autouse=True)
def _one_thread():
    # bitwise determinism (resume tests) needs a fixed thread count; one is also kindest to a shared CPU
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)
