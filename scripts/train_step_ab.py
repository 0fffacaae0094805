"""The whole training step of another checkout (its Trainer.step, Adam and photometric loss;
the kernel is this checkout's) against this one's, alternating step by step on one trainer
in one process, so both see the same load:

    PYTHONPATH=$PWD python scripts/train_step_ab.py RUN_DIR SCENE ITERATIONS OTHER_CHECKOUT

RUN_DIR holds the stages before train (`pano-pipe run all SCENE --out RUN_DIR --until align`);
the paper preset at 512x1024. Prints the median seconds per step of each and the ratio.
"""

import importlib.util
import statistics
import sys
import time
from pathlib import Path

import gaussians.losses as L
import gaussians.optim as Onew
import gaussians.trainer as T
from pipeline.engine import Engine
from pipeline.registry import build_registry
from schemas.scene_loader import load_scene


def load(name, path):
    """The module at `path` under `name` (the other checkout's copy)."""
    spec = importlib.util.spec_from_file_location(name, path)
    m = importlib.util.module_from_spec(spec)
    sys.modules[name] = m
    spec.loader.exec_module(m)
    return m


base = sys.argv[4]
Lold = load("losses_old", f"{base}/gaussians/losses.py")
Oold = load("optim_old", f"{base}/gaussians/optim.py")
Told = load("trainer_old", f"{base}/gaussians/trainer.py")
new_step, new_ssim, new_photo = T.Trainer.step, L.ssim, T.photometric_loss
res = {"old": [], "new": []}
def step(self):
    old = self.iteration % 2 == 0
    self.opt.__class__ = Oold.Adam if old else Onew.Adam
    T.photometric_loss = Lold.photometric_loss if old else new_photo
    Told.photometric_loss = T.photometric_loss
    self._has_layout = None  # the old step caches the flag only, the new one the rows too
    t = time.perf_counter()
    r = (Told.Trainer.step if old else new_step)(self)
    res["old" if old else "new"].append(time.perf_counter() - t)
    return r
T.Trainer.step = step
cfg = {"train": {"preset": "paper", "device": "cpu", "height": 512, "iterations": int(sys.argv[3])}}
Engine(load_scene(Path(sys.argv[2])), Path(sys.argv[1]), build_registry(), cfg).run(until="train")
for k, v in res.items():
    v = v[1:]
    print(k, "median s/step", round(statistics.median(v), 3), [round(x, 2) for x in v])
print("old/new", round(statistics.median(res["old"][1:]) / statistics.median(res["new"][1:]), 2))
