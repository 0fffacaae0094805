"""splatting.compile_ahead: the projection's later SH-degree variants compiled in a background
thread at a kernel's first launch, with the launch's own arguments (a stand-in kernel records what
Triton's `warmup` would be asked), and the launches of a render that go through it."""

from __future__ import annotations

import threading

import pytest
import torch

from splatting import compile_ahead


class FakeKernel:
    """Records launches and warmups (thread, SH degree, arguments)."""

    def __init__(self, fail=False):
        self.launches, self.warmups, self.fail = [], [], fail

    def __getitem__(self, grid):
        return lambda *args, **options: self.launches.append((grid, args, options))

    def warmup(self, *args, grid, **options):
        if self.fail:
            raise RuntimeError("no compiler here")
        self.warmups.append((threading.get_ident(), options["SH_DEGREE"], grid, args, options))


@pytest.fixture(autouse=True)
def _fresh(monkeypatch):
    monkeypatch.setattr(compile_ahead, "_started", set())
    monkeypatch.setattr(compile_ahead, "_threads", [])
    yield
    compile_ahead.sh_degrees()


def _options(**kw):
    return {"EQUIRECT": True, "SH_DEGREE": 0, "K": 16, "BLOCK": 64, "num_warps": 2, **kw}


def test_the_first_launch_compiles_the_later_degrees_in_a_thread_once():
    k, args = FakeKernel(), (torch.zeros(3), 7, 512)
    compile_ahead.sh_degrees(3, 1, 2)
    compile_ahead.launch(k, (5,), args, _options())
    compile_ahead.wait()
    assert k.launches == [((5,), args, _options())]  # the launch itself, unchanged
    assert [w[1] for w in k.warmups] == [1, 2, 3]  # lowest degree first
    assert all(w[0] != threading.get_ident() and w[2] == (5,) and w[3][0] is args[0] and w[3][1:] == args[1:]
               for w in k.warmups)
    assert all(w[4] == _options(SH_DEGREE=w[1]) for w in k.warmups)  # only the degree differs
    compile_ahead.launch(k, (5,), args, _options(SH_DEGREE=1))  # the raise: its variant is already asked for
    compile_ahead.launch(k, (9,), args, _options())
    compile_ahead.wait()
    assert len(k.warmups) == 3 and len(k.launches) == 3
    compile_ahead.launch(k, (5,), args, _options(EQUIRECT=False))  # other options: another key
    compile_ahead.wait()
    assert [w[1] for w in k.warmups[3:]] == [1, 2, 3]


def test_nothing_is_compiled_ahead_unless_asked_and_possible():
    k, args = FakeKernel(), (torch.zeros(3),)
    compile_ahead.launch(k, (1,), args, _options())  # nothing asked
    compile_ahead.sh_degrees(1, 2, 3)
    compile_ahead.launch(k, (1,), args, _options(SH_DEGREE=-1, K=1))  # RGB colours: no SH variants
    compile_ahead.launch(k, (1,), args, _options(K=4, BLOCK=32))  # 4 coefficients hold degree 1 only
    compile_ahead.wait()
    assert [w[1] for w in k.warmups] == [1] and len(k.launches) == 3


def test_a_failed_compile_warns_and_the_launch_stands():
    k = FakeKernel(fail=True)
    compile_ahead.sh_degrees(1)
    with pytest.warns(RuntimeWarning, match="compiles at its first launch"):
        compile_ahead.launch(k, (1,), (torch.zeros(1),), _options())
        compile_ahead.wait()
    assert len(k.launches) == 1


def _sh_scene(device):
    from splat_helpers import random_scene

    m, q, s, o, _ = (t.float().to(device).requires_grad_(True) for t in random_scene(6, seed=3))
    sh = (torch.randn(6, 16, 3, generator=torch.Generator().manual_seed(1)) * 0.3).to(device).requires_grad_(True)
    return m, q, s, o, sh


def _render_and_backward(scene, degree, device):
    from splat_helpers import eye

    import splatting

    m, q, s, o, sh = scene
    out = splatting.render(m, q, s * 0.2, o, sh, eye(torch.float32).to(device), splatting.EquirectCamera(16, 32),
                           sh_degree=degree, backend="cuda")
    out.image.sum().backward()


@pytest.mark.cuda
def test_a_render_and_its_backward_launch_the_projection_through_it(monkeypatch):
    pytest.importorskip("triton")
    from splatting import raster_triton

    if not raster_triton.interpreted() and not torch.cuda.is_available():
        pytest.skip("the cuda backend needs CUDA or the Triton interpreter")
    seen = []
    real = compile_ahead.launch
    monkeypatch.setattr(compile_ahead, "launch", lambda k, g, a, o: (seen.append((k.__name__, o["SH_DEGREE"])),
                                                                      real(k, g, a, o)))
    device = "cuda" if torch.cuda.is_available() else "cpu"
    _render_and_backward(_sh_scene(device), 2, device)
    assert seen == [("_project_fwd", 2), ("_project_bwd", 2)]


@pytest.mark.cuda
def test_on_a_gpu_the_raises_find_their_kernels_compiled_ahead():
    """The variants compiled ahead are the ones the later launches look up: after the degree-0
    render and the compiles, rendering at degrees 1-3 compiles nothing new (Triton's in-memory
    caches, `kernel_report.loaded_variants`)."""
    if not torch.cuda.is_available():
        pytest.skip("needs CUDA: the interpreter compiles nothing")
    from splatting.kernel_report import loaded_variants

    names = ("project_triton._project_fwd", "project_triton_backward._project_bwd")
    scene = _sh_scene("cuda")
    compile_ahead.sh_degrees(1, 2, 3)
    _render_and_backward(scene, 0, "cuda")
    compile_ahead.wait()
    ahead = {k: v for k, v in loaded_variants().items() if k in names}
    for degree in (1, 2, 3):
        _render_and_backward(scene, degree, "cuda")
    after = {k: v for k, v in loaded_variants().items() if k in names}
    assert after == ahead and all(v >= 4 for v in after.values()), (ahead, after)


def test_the_trainer_asks_for_the_degrees_it_will_raise_to_on_a_gpu_only():
    from types import SimpleNamespace

    from gaussians.trainer import Trainer

    tr = Trainer.__new__(Trainer)  # the method reads the device, the schedule and the model's bands
    tr.cfg = SimpleNamespace(optim=SimpleNamespace(sh_degree=3, sh_degree_every=1000))
    tr.g = SimpleNamespace(sh_degree=3)
    tr.active_sh, tr.device = 0, torch.device("cuda")
    assert tr.sh_degrees_ahead() == (1, 2, 3)
    tr.active_sh = 2  # resumed after two raises
    assert tr.sh_degrees_ahead() == (3,)
    tr.active_sh, tr.g = 0, SimpleNamespace(sh_degree=1)  # the model holds one band
    assert tr.sh_degrees_ahead() == (1,)
    tr.device = torch.device("cpu")
    assert tr.sh_degrees_ahead() == ()
    tr.device, tr.cfg.optim.sh_degree_every = torch.device("cuda"), 0
    assert tr.sh_degrees_ahead() == ()
