"""Loading a user's PyTorch checkpoint (a model to export, LPIPS weights) as weights only.

`torch.load(weights_only=True)` builds tensors and plain containers and refuses anything else,
so a pickled `os.system` in a .pth never runs. Its refusal message, cut short, read like advice:
"Re-running `torch.load` with `weights_only` set to `False`" is the one thing not to do with such a
file. Here a refusal says what was refused and why, in one line.
"""

from __future__ import annotations

import pickle
import re
from pathlib import Path

from runfs.errors import PanoError

#: torch's words for the object it refused: "unsupported GLOBAL posix.system", "Unsupported global: GLOBAL x.y".
_REFUSED = re.compile(r"GLOBAL ([\w.]+)")


def checkpoint_problem(e: BaseException) -> str:
    """One line saying why torch.load(weights_only=True) failed, without torch's advice."""
    text = " ".join(str(e).split())
    if isinstance(e, pickle.UnpicklingError):
        found = _REFUSED.search(text)
        if found:
            return (f"refused: it holds a Python object ({found.group(1)}), and loading it would run code; "
                    "pano-pipe loads checkpoints as weights only (tensors, numbers, dicts, lists) and never runs "
                    "code from a file")
        detail = text.split("WeightsUnpickler error:")[-1].split(" Check the documentation")[0].strip()
        return f"not a readable PyTorch checkpoint: damaged, or not a checkpoint ({detail[:120]})"
    if "central directory" in text or "zip archive" in text or isinstance(e, EOFError):
        return "not a readable PyTorch checkpoint: truncated or damaged (not a complete zip archive)"
    return f"not a readable PyTorch checkpoint: {type(e).__name__}: {text[:160]}"


def load_weights(path: Path):
    """A checkpoint's content, loaded as weights only; PanoError naming the file on any failure."""
    import torch

    path = Path(path)
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except OSError as e:
        raise PanoError(path, f"cannot read: {e.strerror or e}") from None
    except Exception as e:  # torch raises UnpicklingError, RuntimeError, EOFError, ... for a bad file
        raise PanoError(path, checkpoint_problem(e)) from None
