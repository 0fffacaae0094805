"""What an `ablate` grid will cost, said before it starts (`ablate --paper` trains for hours on a CPU).

The time per iteration comes from this machine: the earlier trainings of the scene in its run
folder (the main run and earlier ablation runs), the one nearest in height, scaled by the
pixels of a panorama (a splatting step's cost grows with the pixels rendered). Without an
earlier training there is no honest figure, and the line says how to get one.
"""

from __future__ import annotations

from pathlib import Path


def measured_step_seconds(run_dir: Path, height: int) -> tuple[float, int] | None:
    """(seconds per iteration, training height) of the training in `run_dir` (or its earlier
    ablation runs) nearest in height to `height`; None when there is none."""
    from pipeline.engine import read_output
    from runfs.errors import PanoError

    found = []
    for folder in [run_dir, *sorted((run_dir / "ablate").glob("*/"))]:
        try:
            train = read_output(folder, "train")
        except PanoError:  # an unreadable artifact times nothing
            continue
        if train is not None and train.iterations > 0 and train.train_seconds > 0:
            found.append((train.train_seconds / train.iterations, int(train.resolution[0])))
    if not found:
        return None
    return min(found, key=lambda f: abs(f[1] - height))


def ablation_estimate(run_dir: Path, trainings: int, iterations: int, height: int) -> str:
    """One line: how many trainings of how many iterations at what size, and about how long."""
    what = f"{trainings} trainings of {iterations} iterations at {height}x{2 * height} (H×W)"
    measured = measured_step_seconds(run_dir, height)
    if measured is None:
        return (f"ablate: {what}; no earlier training of this scene to time it from "
                f"(`pano-pipe run train` on the scene first gives an estimate)")
    step_s, measured_height = measured
    seconds = trainings * iterations * step_s * (height / measured_height) ** 2
    return (f"ablate: {what}: about {_duration(seconds)} on this machine (measured: {step_s:.3g} s per "
            f"iteration at {measured_height}x{2 * measured_height}, scaled by pixels)")


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"
