"""Processes sharing the compiled-kernel cache ($PANO_PIPE_CACHE): builds at the same
time, a builder killed mid-compile, the build lock. See splatting/raster_cpp.py and
docs/splatting.md, "Build cache and concurrent processes".

One fresh compile in all (about 60-90 s on 2 cores): a builder is killed mid-compile, then
three processes start together in what it left and one of them builds for all. The other
tests need no compiler.

That compile is the build for a machine without AVX-512 (`PANO_PIPE_MARCH=x86-64-v3`: AVX2
and FMA, one tile row per vector instead of two), and one test checks that it renders and
differentiates as this machine's native build does: the native build on CI machines (and ours)
has AVX-512, so without it the one-row code path, which laptops and AMD machines run, would
never execute in CI. One compile serves both.
"""

from __future__ import annotations

import fcntl
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import torch

from splatting import raster_cpp

BUILD_TIMEOUT_S = 900  # a compile is ~1-1.5 min alone on 2 cores; generous for a loaded machine
ROOT = Path(__file__).resolve().parents[2]
PORTABLE = {"PANO_PIPE_MARCH": "x86-64-v3"}  # what every process of the shared cache builds

# Waits for a "go" file (so the processes call load() together), builds or loads the
# kernel, renders a small float64 scene with both backends and prints one JSON line.
CHILD = textwrap.dedent(
    r"""
    import json, os, sys, time
    from pathlib import Path
    import torch
    import splatting
    from splatting import raster_cpp

    go = os.environ.get("GO_FILE")
    if go:
        Path(os.environ["READY_FILE"]).touch()
        t_end = time.time() + 300
        while not os.path.exists(go) and time.time() < t_end:
            time.sleep(0.01)
    t0 = time.time()
    mod = raster_cpp.load()
    t_load = time.time() - t0
    g = torch.Generator().manual_seed(3)
    n = 30
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * 2
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.3 + 0.05
    opac = torch.rand(n, generator=g, dtype=torch.float64) * 0.9 + 0.05
    cols = torch.rand(n, 3, generator=g, dtype=torch.float64)
    cam = splatting.EquirectCamera(16, 32)
    vm = torch.eye(4, dtype=torch.float64)
    a = splatting.render(means, quats, scales, opac, cols, vm, cam, backend="cpp")
    b = splatting.render(means, quats, scales, opac, cols, vm, cam, backend="torch")
    print(json.dumps({
        "backend": a.backend,
        "module": None if mod is None else getattr(mod, "__name__", None),
        "image_diff": float((a.image - b.image).abs().max()),
        "alpha_diff": float((a.alpha - b.alpha).abs().max()),
        "alpha_max": float(a.alpha.max()),
        "image_sum": float(a.image.sum()),
        "load_s": t_load,
    }))
    """
)


def _env(cache: Path, **extra) -> dict:
    env = dict(os.environ)
    env.pop("GO_FILE", None)
    env.update(PANO_PIPE_CACHE=str(cache), OMP_NUM_THREADS="1", PYTHONWARNINGS="default", **PORTABLE, **extra)
    return env


def _start(cache: Path, tag: str, **extra) -> subprocess.Popen:
    log = cache.parent / f"{tag}.log"
    return subprocess.Popen(
        [sys.executable, "-c", CHILD],
        env=_env(cache, **extra),
        cwd=cache.parent,
        stdout=subprocess.PIPE,
        stderr=open(log, "w"),  # noqa: SIM115 - closed with the process
        text=True,
        start_new_session=True,  # its own process group: a kill reaches ninja and the compiler too
    )


def _finish(p: subprocess.Popen, tag: str, cache: Path, deadline: float) -> tuple[dict, str]:
    try:
        out, _ = p.communicate(timeout=max(1.0, deadline - time.monotonic()))
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        p.communicate()
        pytest.fail(f"{tag} did not finish: {(cache.parent / f'{tag}.log').read_text()[-3000:]}")
    err = (cache.parent / f"{tag}.log").read_text()
    assert p.returncode == 0, f"{tag} exit {p.returncode}:\n{err[-3000:]}"
    return json.loads(out.strip().splitlines()[-1]), err


def _check_render(res: dict, err: str) -> None:
    assert res["backend"] == "cpp", err[-3000:]
    assert res["alpha_max"] > 0.05  # the scene is actually visible
    assert res["image_diff"] < 1e-9 and res["alpha_diff"] < 1e-9, res


def _check_published(cache: Path) -> Path:
    """Exactly one published build folder holding the library, and no leftovers."""
    entries = sorted(p.name for p in cache.iterdir())
    published = [cache / n for n in entries if n.startswith("splatting-") and "." not in n]
    assert len(published) == 1, entries
    leftovers = [n for n in entries if ".build-" in n or ".trash-" in n]
    assert leftovers == [], entries
    bdir = published[0]
    lib = bdir / (raster_cpp.module_name(bdir) + ".so")
    assert lib.is_file() and lib.stat().st_size > 10_000, sorted(os.listdir(bdir))
    assert not (bdir / "lock").exists()  # torch's baton never lives in a published folder
    return bdir


def _kill_a_builder(cache: Path) -> dict:
    """SIGKILL a builder mid-compile (its flock, torch's 'lock' baton and a half-built folder
    stay behind) and add what the old build code left after a kill (a baton in the build folder
    itself, a truncated library in a build folder). Returns what it left."""
    victim = _start(cache, "victim")
    t_end = time.monotonic() + 300
    building = []
    while time.monotonic() < t_end and victim.poll() is None:
        building = [b for b in cache.glob("splatting-*.build-*") if (b / "build.ninja").exists()]
        if building:
            break
        time.sleep(0.05)
    assert building, (cache.parent / "victim.log").read_text()
    time.sleep(1.0)  # ninja and the compiler are running
    os.killpg(victim.pid, signal.SIGKILL)
    victim.communicate()
    stale = building[0]
    key = stale.name.split(".build-")[0]
    left = {"returncode": victim.returncode, "key": key, "baton": (stale / "lock").exists(),
            "flock_file": (cache / f"{key}.lock").exists(), "published": (cache / key).exists()}
    # the old code's leftovers: the build folder itself holding a stale baton and no library,
    # and a half-written library in another abandoned build folder
    (cache / key).mkdir()
    (cache / key / "lock").touch()
    half = cache / f"{key}.build-old"
    half.mkdir()
    (half / "lock").touch()
    (half / (raster_cpp.module_name(cache / key) + ".so")).write_bytes(b"\x7fELF" + b"\0" * 100)
    return left


@pytest.fixture(scope="module")
def concurrent_build(tmp_path_factory):
    """A builder killed mid-compile into a fresh cache (`_kill_a_builder`), then three processes
    load() together into what it left (one compile)."""
    base = tmp_path_factory.mktemp("concurrent")
    cache = base / "cache"
    killed = _kill_a_builder(cache)
    go = base / "go"
    procs = [_start(cache, f"p{i}", GO_FILE=str(go), READY_FILE=str(base / f"ready{i}")) for i in range(3)]
    t_ready = time.monotonic() + 300
    while not all((base / f"ready{i}").exists() for i in range(3)) and time.monotonic() < t_ready:
        if any(p.poll() is not None for p in procs):
            break
        time.sleep(0.05)
    go.touch()
    deadline = time.monotonic() + BUILD_TIMEOUT_S
    results = [_finish(p, f"p{i}", cache, deadline) for i, p in enumerate(procs)]
    return cache, results, killed


def test_concurrent_processes_build_once_and_all_render(concurrent_build):
    cache, results, _ = concurrent_build
    for res, err in results:
        _check_render(res, err)
    assert len({res["module"] for res, _ in results}) == 1
    assert len({res["image_sum"] for res, _ in results}) == 1  # the same library everywhere
    compiled = [err for _, err in results if "compiling the C++ CPU kernel" in err]
    assert len(compiled) == 1, [err[-500:] for _, err in results]  # one builder
    assert any("waiting for another process" in err for _, err in results)  # they did overlap
    _check_published(cache)


def test_a_published_build_loads_without_the_lock(concurrent_build):
    """Once published, a new process neither compiles nor waits, even while the lock is held."""
    cache, _, _ = concurrent_build
    bdir = _check_published(cache)
    fd = os.open(cache / f"{bdir.name}.lock", os.O_RDWR)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)  # as if a builder of this key were still at work
        p = _start(cache, "after")
        res, err = _finish(p, "after", cache, time.monotonic() + 300)
    finally:
        os.close(fd)
    _check_render(res, err)
    assert "compiling" not in err and "waiting" not in err, err


def test_a_killed_builder_leaves_nothing_that_blocks_the_next_build(concurrent_build):
    """What a builder killed mid-compile left (its flock file, torch's baton, no published
    folder) plus the old build code's leftovers did not block the next build: the processes
    after it built the same key once and rendered."""
    cache, results, killed = concurrent_build
    assert killed["returncode"] == -signal.SIGKILL
    assert killed["baton"]  # torch's FileBaton: it would block forever where it is
    assert killed["flock_file"] and not killed["published"]
    assert sum("compiling the C++ CPU kernel" in err for _, err in results) == 1
    for res, err in results:
        _check_render(res, err)
    assert _check_published(cache).name == killed["key"]


# Renders a small room (wide splats spanning two 8-column windows, odd row counts, the
# ±180° seam and both poles are all in it) and saves the image and every gradient.
_CASE = """
import sys, torch
from splatting import EquirectCamera, render
from splatting.bench import indoor_scene
means, quats, scales, opac, rgb = indoor_scene(3000, seed=3)
args = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, rgb)]
vm = torch.eye(4, requires_grad=True)
out = render(*args, vm, EquirectCamera(48, 96), backend="cpp")
assert out.backend == "cpp", out.backend
g = torch.Generator().manual_seed(0)
loss = (out.image * torch.rand(out.image.shape, generator=g)).sum() + 0.1 * out.depth.sum() + out.alpha.sum()
loss.backward()
torch.save({"image": out.image.detach(), "depth": out.depth.detach(), "alpha": out.alpha.detach(),
            "grads": [t.grad for t in args] + [vm.grad]}, sys.argv[1])
"""


def _render_case(tmp_path: Path, name: str, env: dict) -> tuple[dict, str]:
    out = tmp_path / f"{name}.pt"
    done = subprocess.run([sys.executable, "-c", _CASE, str(out)], cwd=ROOT, env=env, check=True, timeout=900,
                          stderr=subprocess.PIPE, text=True)
    return torch.load(out), done.stderr


@pytest.mark.skipif(not raster_cpp.available(), reason="no C++ toolchain: the cpp backend is not built")
def test_a_build_without_avx512_gives_the_native_builds_image_and_gradients(concurrent_build, tmp_path):
    cache, _, _ = concurrent_build
    env = {k: v for k, v in os.environ.items() if k != "PANO_PIPE_MARCH"}
    env.update(PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    native, _ = _render_case(tmp_path, "native", env)  # this session's cache: the native build
    portable, err = _render_case(tmp_path, "v3", {**env, **PORTABLE, "PANO_PIPE_CACHE": str(cache)})
    assert "compiling" not in err, err[-2000:]  # the build the processes above published
    for key in ("image", "depth", "alpha"):  # the same operations lane by lane
        assert torch.equal(native[key], portable[key]), key
    for a, b in zip(native["grads"], portable["grads"]):  # only the order of the sums differs
        assert float(a.abs().max()) > 0
        assert float((a - b).abs().max()) <= 1e-5 * float(a.abs().max())


# -- the lock and the key, without a compiler ------------------------------------------------

HOLD = textwrap.dedent(
    r"""
    import sys, time
    from pathlib import Path
    from splatting import raster_cpp
    with raster_cpp.build_lock(Path(sys.argv[1])):
        Path(sys.argv[2]).touch()
        time.sleep(600)
    """
)


def _hold_lock(lock: Path, flag: Path) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-c", HOLD, str(lock), str(flag)], start_new_session=True)
    t_end = time.monotonic() + 120
    while not flag.exists() and time.monotonic() < t_end and p.poll() is None:
        time.sleep(0.02)
    assert flag.exists()
    return p


def test_build_lock_is_freed_when_its_holder_is_killed(tmp_path):
    lock = tmp_path / "k.lock"
    p = _hold_lock(lock, tmp_path / "held")
    try:
        with pytest.raises(TimeoutError, match="k.lock"):
            with raster_cpp.build_lock(lock, wait_s=0.5):
                pass
        assert str(p.pid) in lock.read_text()  # the message names the holder
    finally:
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()
    assert lock.exists()  # the file stays, the lock does not
    t0 = time.monotonic()
    with raster_cpp.build_lock(lock, wait_s=30):
        pass
    assert time.monotonic() - t0 < 5  # loose: only "did not wait for the timeout"


def test_lock_timeout_falls_back_to_torch_with_a_warning(tmp_path, monkeypatch):
    """A builder that never finishes costs a wait of $PANO_PIPE_BUILD_WAIT, not a hang."""
    import splatting
    from splat_helpers import eye, random_scene

    monkeypatch.setenv("PANO_PIPE_CACHE", str(tmp_path))
    monkeypatch.setenv("PANO_PIPE_BUILD_WAIT", "0.5")
    monkeypatch.setattr(raster_cpp, "_module", None)
    monkeypatch.setattr(raster_cpp, "_failed", False)
    bdir = raster_cpp.build_dir()
    p = _hold_lock(tmp_path / f"{bdir.name}.lock", tmp_path / "held")
    try:
        with pytest.warns(RuntimeWarning, match="TimeoutError.*falling back"):
            out = splatting.render(*random_scene(3), eye(), splatting.EquirectCamera(8, 16))
    finally:
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()
    assert out.backend == "torch"
    assert not bdir.exists()


def test_build_key_separates_toolchains_and_installs(monkeypatch, tmp_path):
    """Two checkouts (each its own venv) or two compilers never share, hence never rewrite, a build."""
    import torch

    monkeypatch.setenv("PANO_PIPE_CACHE", str(tmp_path))
    base = raster_cpp.build_dir()
    assert base.parent == tmp_path and base.name.startswith("splatting-")
    assert raster_cpp.build_dir() == base  # stable
    monkeypatch.setenv("CXX", "g++-does-not-exist")
    assert raster_cpp.build_dir() != base
    monkeypatch.delenv("CXX")
    monkeypatch.setattr(torch, "__file__", "/elsewhere/venv/site-packages/torch/__init__.py")
    assert raster_cpp.build_dir() != base
