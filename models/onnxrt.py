"""onnxruntime, imported in one place with its telemetry off (docs/security.md, "Network").

The official onnxruntime wheels carry Microsoft's 1DS telemetry: importing the library creates a
device id and an event database under ~/.cache/Microsoft/DeveloperTools/.onnxruntime/, and the
library holds an upload address. `ORT_DISABLE_TELEMETRY=1` before the library initializes stops
the uploader, the events and the device id for the process (onnxruntime's Privacy.md);
`disable_telemetry_events()` turns off the events its API controls as well. Every use of
onnxruntime in pano-pipe goes through `onnxruntime()` (tests/pipeline/test_hardening3.py checks).
"""

from __future__ import annotations

import os
from pathlib import Path


def onnxruntime():
    """The onnxruntime module, with telemetry off before anything of it runs."""
    os.environ["ORT_DISABLE_TELEMETRY"] = "1"  # read when the library initializes, i.e. at import
    import onnxruntime as ort

    ort.disable_telemetry_events()
    return ort


def inference_session(path: str | Path, options=None, providers: list[str] | None = None):
    """An onnxruntime InferenceSession of the model at `path` (telemetry off)."""
    ort = onnxruntime()
    return ort.InferenceSession(str(path), sess_options=options, providers=providers)
