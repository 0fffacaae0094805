"""What a run's numbers mean when they are poor, said where the user looks (the run banner, the
end-of-run summary, the report): a run without priors, and a model that overfits its training views.

A run without priors: the layout and depth stages were both skipped (no layout or depth files, no
model in the cache), so training starts from random points. What that costs was measured (the
figure in NO_PRIORS_COST, the command in docs/evaluation.md, "Runs without priors").

A model that overfits: held-out PSNR OVERFIT_GAP_DB or more below the training PSNR. The likely
causes are named in order: no priors first (where the run had none), then too few or too distant
views (the run's own counts and distances).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Held-out PSNR this many dB or more below the training PSNR: the model overfits the training views.
OVERFIT_GAP_DB = 10.0

#: What training from random points cost where it was measured (docs/evaluation.md, "Runs without
#: priors", has the command and the whole table).
NO_PRIORS_COST = ("on the simulated demo room that cost 8.7 dB of held-out PSNR (27.5 dB from random points "
                  "against 36.2 dB with the layout), 7.2 dB with the held-out views away from the cameras "
                  "(20.6 against 27.8 dB)")


def fetch_commands() -> str:
    """The commands that fetch the recommended layout and depth models."""
    from models.registry import RECOMMENDED

    return " && ".join(f"pano-pipe models fetch {RECOMMENDED[k]}" for k in ("layout", "depth"))


def no_priors_message() -> str:
    """One line: a run without priors, what it costs and the commands that fetch the models."""
    return (f"no priors: the layout and depth stages are both skipped (no layout or depth files, no model), so "
            f"training starts from random points; {NO_PRIORS_COST}; see docs/evaluation.md, \"Runs without "
            f"priors\"; get the models: {fetch_commands()}")


def plans_without_priors(plans: dict, selected: list[str]) -> bool:
    """Whether a planned run trains without priors: it trains, and layout and depth are both skipped
    (`plans`: Engine.plan(); `selected`: the stages the run touches)."""
    return ("train" in selected and all(name in plans and plans[name].state == "skipped"
                                        for name in ("layout", "depth")))


def trained_without_priors(init: str | None, upstream: dict | None) -> bool:
    """Whether a trained model started from random points because no prior reached training: its init
    was random and its align and sampling inputs were skipped (train's meta.upstream), which is what
    skipped layout and depth stages leave (a random init asked for beside a layout is not this)."""
    up = upstream or {}
    return init == "random" and up.get("align") == "skipped" and up.get("sampling") == "skipped"


@dataclass
class ViewSpacing:
    """How many training panoramas there are and how far apart (metres, from the poses)."""

    n_train: int
    #: median over the training cameras of the distance to the nearest other training camera
    train_neighbour_m: float | None = None
    #: median over the held-out cameras of the distance to the nearest training camera
    test_to_train_m: float | None = None


def view_spacing(scene) -> ViewSpacing | None:
    """The spacing of `scene`'s cameras (poses completed); None without a scene or poses."""
    if scene is None:
        return None
    try:
        train = np.array([v.position for v in scene.views if v.split == "train"])
        test = np.array([v.position for v in scene.views if v.split == "test"])
    except ValueError:  # a view without a pose
        return None
    out = ViewSpacing(n_train=len(train))
    if len(train) >= 2:
        d = np.linalg.norm(train[:, None] - train[None], axis=-1)
        np.fill_diagonal(d, np.inf)
        out.train_neighbour_m = float(np.median(d.min(axis=1)))
    if len(train) and len(test):
        out.test_to_train_m = float(np.median(np.linalg.norm(test[:, None] - train[None], axis=-1).min(axis=1)))
    return out


def _finite(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def overfit_message(train_psnr: float | None, heldout_psnr: float | None, split: str | None,
                    no_priors: bool, spacing: ViewSpacing | None = None) -> str | None:
    """One line when held-out PSNR is OVERFIT_GAP_DB or more below the training PSNR: the model
    overfits the training views, and the likely causes, in order; None otherwise (also when the
    evaluation ran on the training views, which hold nothing out)."""
    if split != "test" or not (_finite(train_psnr) and _finite(heldout_psnr)):
        return None
    gap = train_psnr - heldout_psnr
    if gap < OVERFIT_GAP_DB:
        return None
    causes = []
    if no_priors:
        causes.append("no priors: training started from random points, which fit the training panoramas "
                      "without making a room")
    views = "too few or too distant views"
    if spacing is not None:
        facts = [f"{spacing.n_train} training panorama{'s' if spacing.n_train != 1 else ''}"]
        if spacing.train_neighbour_m is not None:
            facts.append(f"{spacing.train_neighbour_m:.2f} m from each to the nearest other (median)")
        if spacing.test_to_train_m is not None:
            facts.append(f"held-out views {spacing.test_to_train_m:.2f} m from the nearest training one (median)")
        views += f": {', '.join(facts)}"
    causes.append(views + "; more panoramas, closer together, constrain the room")
    numbered = "; ".join(f"{i}. {c}" for i, c in enumerate(causes, 1))
    return (f"the model overfits the training views: held-out PSNR {heldout_psnr:.1f} dB is {gap:.1f} dB below "
            f"the training PSNR {train_psnr:.1f} dB (a gap of {OVERFIT_GAP_DB:g} dB or more); likely causes, "
            f"most likely first: {numbered}")


def run_notes(train_data, train_upstream: dict | None, ev_data, scene=None) -> list[str]:
    """The notes a finished run calls for (no priors, overfitting), each one line. `train_data` and
    `ev_data`: the train and evaluate artifacts' data (typed or plain dicts; either may be None)."""
    def get(obj, key):
        if obj is None:
            return None
        return obj.get(key) if isinstance(obj, dict) else getattr(obj, key, None)

    notes = []
    no_priors = trained_without_priors(get(train_data, "init"), train_upstream)
    if no_priors:
        notes.append(no_priors_message())
    mean = get(ev_data, "mean") or {}
    overfit = overfit_message(get(train_data, "final_train_psnr"), mean.get("psnr"), get(ev_data, "split"),
                              no_priors, view_spacing(scene))
    if overfit:
        notes.append(overfit)
    return notes
