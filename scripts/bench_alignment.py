"""Accuracy and time of the Manhattan alignment (layoutnet/alignment.py) on known rotations.

    PYTHONPATH=. python scripts/bench_alignment.py [--demo ../shared/data/horizonnet_demo/demo_aligned_rgb.png]

A simulated textured room (simulate/, camera level and square to the walls) and, when given,
HorizonNet's aligned demo panorama, each turned by random rotations (|yaw| < 44°, tilt < 10°);
prints the angle between the estimated and the true rotation, gravity estimated and given.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from layoutnet.alignment import estimate_alignment
from panogeom.rotate import rotate_equirect, yaw_matrix


def _simulated() -> np.ndarray:
    from simulate.geometry import Camera, build_world
    from simulate.render import render_view

    rng = np.random.default_rng(0)
    world = build_world("cuboid", rng)
    x0, z0, x1, z1 = world.camera_regions[0][0]
    cam = Camera("v", "train", np.array([0.4 * x0 + 0.6 * x1, -1.5, 0.55 * z0 + 0.45 * z1]), 1.5, 0.0)
    return render_view(world, [], cam, 512, {"texture"}, 1, rng, {}).image.astype(np.float32)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--demo", type=Path, default=None)
    ap.add_argument("--trials", type=int, default=10)
    args = ap.parse_args()
    images = {"simulated": _simulated()}
    if args.demo and args.demo.is_file():
        from panogeom.images import read_rgb

        images["demo"] = read_rgb(args.demo)
    rng = np.random.default_rng(1)
    for name, img in images.items():
        errs, errs_g, times = [], [], []
        for _ in range(args.trials):
            az = rng.uniform(0, 2 * np.pi)
            tilt = Rotation.from_rotvec(np.radians(rng.uniform(0, 10)) * np.array([np.cos(az), 0, np.sin(az)]))
            M = yaw_matrix(np.radians(rng.uniform(-44, 44))) @ tilt.as_matrix()
            view = rotate_equirect(img, M.T)
            t0 = time.perf_counter()
            a = estimate_alignment(view)
            times.append(time.perf_counter() - t0)
            errs.append(np.degrees(Rotation.from_matrix(a.rotation @ M.T).magnitude()))
            g = estimate_alignment(view, down=M.T @ np.array([0.0, 1.0, 0.0]))
            errs_g.append(np.degrees(Rotation.from_matrix(g.rotation @ M.T).magnitude()))
        print(f"{name} {img.shape[1]}x{img.shape[0]}: error mean {np.mean(errs):.3f}° max {np.max(errs):.3f}°; "
              f"gravity given: mean {np.mean(errs_g):.3f}° max {np.max(errs_g):.3f}°; "
              f"{np.median(times):.2f} s per panorama (median)")


if __name__ == "__main__":
    main()
