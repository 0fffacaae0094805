"""Training checkpoints: what one holds, how it is written and read, and its validation.

A checkpoint holds only tensors and plain data (dict/list/tuple/str/int/float/bool/None) and is
read with torch.load(weights_only=True): a file in the run folder is data, never code. Every
field is validated (checked_state) before the trainer changes anything, so a bad one leaves the
trainer as it was. Every tensor is stored on the CPU, so a checkpoint written on one device
resumes on another.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import pickle
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from gaussians.densify import DensifyStats
from gaussians.model import Gaussians
from gaussians.optim import Adam
from runfs.errors import one_line

__all__ = ["CHECKPOINT_NAME", "CHECKPOINT_VERSION", "checked_state", "plain_number", "read", "trainer_state",
           "write"]

CHECKPOINT_NAME = "checkpoint.pt"
CHECKPOINT_VERSION = 3  # 2: numpy RNG state as plain data (weights_only loading); 3: appearance


def trainer_state(tr) -> dict:
    """Trainer `tr`'s state: tensors and plain data only (what torch.load(weights_only=True)
    accepts), every tensor on the CPU."""
    return _to_cpu({
        "version": CHECKPOINT_VERSION,
        "fingerprint": tr.cfg.fingerprint() + tr.extra_fingerprint,
        "iteration": tr.iteration,
        "gaussians": {k: v.detach().clone() for k, v in tr.g.tensors().items()},
        "opt": tr.opt.state_dict(),
        "stats": tr.stats.state_dict(),
        "gen": tr.gen.get_state(),
        "torch_rng": torch.get_rng_state(),
        "np_rng": _np_rng_to_plain(np.random.get_state()),
        "active_sh": tr.active_sh,
        "stack": list(tr.stack),
        "ema": {k: plain_number(v) for k, v in asdict(tr.ema).items()},
        "appearance": None if tr.appearance is None else tr.appearance.state_dict(),
        "records": list(tr.records),
        "train_seconds": tr.train_seconds,
        "nonfinite_steps": int(tr.nonfinite_steps),
    })


def write(state: dict, path: Path) -> None:
    """Write `state` to `path` atomically (temporary file, then rename). On failure the temporary
    file is removed; an OSError is re-raised naming `path` (a full disk would otherwise read as an
    anonymous "[Errno 28] No space left on device")."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save(state, tmp)
        os.replace(tmp, path)
    except BaseException as e:  # also Ctrl-C mid-write: never leave a half file behind
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        if isinstance(e, OSError):
            reason = e.strerror or str(e) or type(e).__name__
            raise OSError(e.errno, f"cannot write the training checkpoint: {reason}", str(path)) from e
        raise


def read(path: Path) -> object:
    """What a checkpoint file holds (validate it with checked_state). A file that cannot be read
    or holds anything but tensors and plain data raises ValueError."""
    path = Path(path)
    try:
        # weights_only: the unpickler builds tensors and plain containers, never calls code
        s = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        # torch's message suggests weights_only=False: the one thing not to do with such a file
        raise ValueError("not a checkpoint: damaged, or holds objects other than tensors and plain data"
                         ) from None
    except OSError:
        raise
    except Exception as e:  # noqa: BLE001 (zip, EOF, storage errors of a damaged file)
        raise ValueError(f"not a readable checkpoint ({_short(e) or type(e).__name__})") from None
    return s


def checked_state(s: object, tr) -> dict:
    """The state of trainer `tr` that checkpoint `s` describes, every field checked (type, shape,
    range) so that a crafted or damaged file cannot leave a trainer that fails later; nothing
    of `tr` is changed. Raises ValueError saying what is wrong."""
    if not isinstance(s, dict):
        raise ValueError(f"checkpoint is a {type(s).__name__}, not a dict")
    # plain comparisons only: `tensor != value` would be a tensor, not a bool
    version = s.get("version")
    if not _is_int(version) or version != CHECKPOINT_VERSION:
        raise ValueError(f"checkpoint version {_short(version, 40)} is not {CHECKPOINT_VERSION}")
    missing = sorted(_STATE_KEYS - set(s))
    if missing:
        raise ValueError(f"checkpoint lacks {', '.join(missing)}")
    fp = s["fingerprint"]
    if not isinstance(fp, str) or fp != tr.cfg.fingerprint() + tr.extra_fingerprint:
        raise ValueError("checkpoint was made with different training settings")
    out: dict = {}
    out["iteration"] = _int_in(s["iteration"], "iteration", 0, tr.cfg.iterations)

    # the model: the fields, dtypes and SH bands of this trainer's; Gaussians checks the shapes
    ref = tr.g.tensors()
    gs = s["gaussians"]
    if not isinstance(gs, dict) or set(gs) != set(ref):
        raise ValueError(f"checkpoint gaussians must hold exactly {', '.join(ref)}")
    for k, v in gs.items():
        if not _is_dense(v, ref[k].dtype) or v.ndim == 0:
            raise ValueError(f"checkpoint gaussians.{k} is not a {ref[k].dtype} tensor")
        if v.is_floating_point() and not bool(torch.isfinite(v).all()):
            raise ValueError(f"checkpoint gaussians.{k} has non-finite values")
    g = Gaussians(**{k: v.detach().clone() for k, v in gs.items()})  # raises ValueError on bad shapes
    if g.sh_rest.shape[1] != tr.g.sh_rest.shape[1]:
        raise ValueError(f"checkpoint model has SH degree {g.sh_degree}, not {tr.g.sh_degree}")
    n = len(g)

    # a fresh optimiser: validating into it leaves tr.opt untouched
    opt = Adam(dict(tr.opt.lrs), tr.opt.betas, tr.opt.eps)
    opt.load_state_dict(s["opt"])
    if set(opt.lrs) != set(tr.opt.lrs):
        raise ValueError("checkpoint optimiser covers other parameters")
    for k, m in opt.exp_avg.items():
        p = getattr(g, k)
        if m.shape != p.shape or m.dtype != p.dtype:
            raise ValueError(f"checkpoint optimiser moments of {k} do not match the model")
    out["g"], out["opt"] = g, opt

    st = s["stats"]
    names = ("grad_accum", "count", "max_radius")
    if not isinstance(st, dict) or any(
            not _is_dense(st.get(k), g.means.dtype) or tuple(st[k].shape) != (n,) for k in names):
        raise ValueError(f"checkpoint stats must be {', '.join(names)}: "
                         f"{g.means.dtype} tensors of length {n}")
    out["stats"] = DensifyStats.from_state(st)

    # RNG states: tried on throw-away generators first
    for k in ("gen", "torch_rng"):
        try:  # torch checks the size and the MT19937 fields
            torch.Generator().set_state(s[k])
        except (TypeError, RuntimeError) as e:
            raise ValueError(f"checkpoint {k} is not a torch generator state ({_short(e)})") from None
        out[k] = s[k]
    out["np_rng"] = _np_rng_from_plain(s["np_rng"])

    out["active_sh"] = _int_in(s["active_sh"], "active_sh", 0, g.sh_degree)
    stack = s["stack"]
    if not isinstance(stack, list | tuple):
        raise ValueError("checkpoint stack is not a list")
    out["stack"] = [_int_in(i, "stack entry", 0, len(tr.views) - 1) for i in stack]
    ema = s["ema"]
    if not isinstance(ema, dict) or set(ema) != {"loss", "psnr"} or \
            any(v is not None and not _is_real(v) for v in ema.values()):
        raise ValueError("checkpoint ema must be {loss, psnr} numbers or None")
    out["ema"] = {k: None if v is None else float(v) for k, v in ema.items()}
    recs = s["records"]
    if not isinstance(recs, list | tuple) or not all(isinstance(r, dict) for r in recs):
        raise ValueError("checkpoint records must be a list of dicts")
    try:  # they are written back to the JSON lines log
        json.dumps(recs)
    except (TypeError, ValueError):
        raise ValueError("checkpoint records are not JSON data") from None
    out["records"] = [dict(r) for r in recs]
    if not _is_real(s["train_seconds"]) or not s["train_seconds"] >= 0:
        raise ValueError("checkpoint train_seconds must be a number >= 0")
    out["train_seconds"] = float(s["train_seconds"])
    out["nonfinite_steps"] = _int_in(s["nonfinite_steps"], "nonfinite_steps", 0, None)
    out["appearance"] = tr.new_appearance()
    if out["appearance"] is None:
        if s["appearance"] is not None:
            raise ValueError("checkpoint has appearance transforms, this run has appearance off")
    else:
        out["appearance"].load_state_dict(s["appearance"])
    return out



def plain_number(x):
    """A logged value as a plain number (None stays None); reading a device tensor waits for it."""
    return None if x is None else float(x)


def _to_cpu(x):
    """`x` with every tensor in it (nested dicts, lists, tuples) moved to the CPU."""
    if isinstance(x, torch.Tensor):
        return x.detach().cpu()
    if isinstance(x, dict):
        return {k: _to_cpu(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return type(x)(_to_cpu(v) for v in x)
    return x


_STATE_KEYS = frozenset({
    "fingerprint", "iteration", "gaussians", "opt", "stats", "gen", "torch_rng", "np_rng", "active_sh",
    "stack", "ema", "records", "train_seconds", "nonfinite_steps", "appearance",
})


def _short(x: object, limit: int = 120) -> str:
    """An error message or value's first sentence, as one line of at most `limit` characters."""
    return one_line(str(x).strip().split(". ")[0], limit)


_MT_N = 624  # words of MT19937 state


def _is_int(x: object) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _is_real(x: object) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def _is_dense(t: object, dtype: torch.dtype) -> bool:
    """A plain (strided, CPU) tensor of `dtype`: what save_checkpoint writes."""
    return (isinstance(t, torch.Tensor) and t.layout == torch.strided and t.device.type == "cpu"
            and t.dtype == dtype)


def _int_in(x: object, what: str, lo: int, hi: int | None) -> int:
    if not _is_int(x) or x < lo or (hi is not None and x > hi):
        bound = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise ValueError(f"checkpoint {what} must be an integer {bound}, got {_short(repr(x), 40)}")
    return int(x)


def _np_rng_to_plain(state: tuple) -> dict:
    """np.random.get_state() (a tuple holding a uint32 array) as plain data and a tensor."""
    name, keys, pos, has_gauss, cached = state
    return {"name": str(name), "keys": torch.from_numpy(np.asarray(keys, dtype=np.int64)), "pos": int(pos),
            "has_gauss": int(has_gauss), "cached_gaussian": float(cached)}


def _np_rng_from_plain(d: object) -> tuple:
    """The inverse of _np_rng_to_plain, every field checked first (numpy trusts `pos`:
    an out-of-range one crashes the interpreter on the next draw)."""
    ok = (isinstance(d, dict) and isinstance(d.get("name"), str) and d["name"] == "MT19937"
          and _is_dense(d.get("keys"), torch.int64) and tuple(d["keys"].shape) == (_MT_N,)
          and _is_int(d.get("pos")) and 0 <= d["pos"] <= _MT_N
          and _is_int(d.get("has_gauss")) and d["has_gauss"] in (0, 1) and _is_real(d.get("cached_gaussian")))
    keys = d["keys"].numpy() if ok else None
    if keys is None or keys.min() < 0 or keys.max() > np.iinfo(np.uint32).max:
        raise ValueError("checkpoint np_rng is not a numpy MT19937 state")
    return ("MT19937", keys.astype(np.uint32), int(d["pos"]), int(d["has_gauss"]),
            float(d["cached_gaussian"]))
