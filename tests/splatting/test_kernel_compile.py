"""The `cuda` backend's Triton kernels compiled ahead of time for sm_80 (A100) and sm_90 (H100),
no GPU needed: ptxas's register and spill report and the SASS of each kernel's inner loop
(splatting/kernel_report.py; budgets and their reasons in docs/gpu.md)."""

import json

import pytest

pytest.importorskip("triton")

from splatting.kernel_report import last_line_compiled, report_in_subprocess  # noqa: E402

# registers per thread: a forward at <= 128 keeps >= 16 warps resident per SM (65536 registers);
# the backward holds 11 per-pixel values for 8 pixels per thread, so it may use the whole 255.
# The projection's backward walks ~150 per-Gaussian values back through the forward; it runs once
# per Gaussian (no pixel loop), so occupancy matters less than spills: the whole 255, no spills.
# The pair writer holds a splat's 15 packed values for its tile test: 56 registers in float32,
# 114 in float64 (two a value; the tests' dtype).
REG_BUDGET = {"forward": 128, "backward": 255, "backward + depth, alpha": 255, "project (RGB)": 128, "project (SH 3)": 128, "emit pairs": 128,
              "project backward (RGB)": 255, "project backward (SH 3)": 255,
              # the training loss's image passes (2 pixels a thread, 11 taps of 5 moments in flight)
              "loss: moments": 192, "loss: SSIM": 192, "loss: sum": 64, "loss backward: blur": 64,
              "loss backward: combine": 160, "random turn": 128, "densify statistics": 64, "layout loss": 64,
              "adam": 64}
# the trainer's kernels beside the renderer: float32, what training runs
LOSS_KERNELS = [k for k in REG_BUDGET if k.startswith("loss")] + ["random turn", "densify statistics", "layout loss",
                                                                  "adam"]
# SASS instructions per Gaussian-pixel pair in the float32 inner loops (issue 26's targets)
PAIR_BUDGET = {"forward": 40, "backward": 120, "backward + depth, alpha": 120}


@pytest.fixture(scope="module")
def rows():
    return report_in_subprocess()


def test_every_kernel_compiles_for_both_archs(rows):
    seen = {(r.kernel, r.arch, r.dtype) for r in rows}
    expected = {(k, a, d) for k in REG_BUDGET for a in (80, 90) for d in ("float32", "float64")}
    # the projection's gradient: the float32 kernel training runs (its float64 twin runs in the tests)
    expected -= {(k, a, "float64") for k in ("project backward (RGB)", "project backward (SH 3)") for a in (80, 90)}
    expected -= {(k, a, "float64") for k in LOSS_KERNELS for a in (80, 90)}  # training's float32 loss
    assert seen == expected


def test_no_spills_and_register_budget(rows):
    for r in rows:
        where = f"{r.kernel} {r.dtype} sm_{r.arch}"
        assert r.spill_stores == 0 and r.spill_loads == 0, f"{where}: spills {r.spill_stores}/{r.spill_loads} B"
        assert r.registers <= REG_BUDGET[r.kernel], f"{where}: {r.registers} registers"


def test_exact_kernels_divide_as_torch_does(rows):
    """A float32 `/` compiles to an approximate division (2 ulp) on a GPU, where the interpreter
    divides exactly: a kernel whose result must equal torch's bit for bit divides with div_rn."""
    exact = [r for r in rows if r.kernel == "densify statistics"]
    assert exact and all(r.approximate_divisions == 0 for r in exact), exact
    # the count is not vacuous: the projection's float32 divisions are the approximate ones
    assert any(r.approximate_divisions > 0 for r in rows if r.kernel == "project (RGB)" and r.dtype == "float32")


def test_inner_loops_within_instruction_budget(rows):
    for r in rows:
        if r.kernel not in PAIR_BUDGET:
            continue  # per-Gaussian kernels: no pixel loop
        assert r.loop_instructions > 50, f"{r.kernel}: no inner loop found in the SASS"  # the count is not vacuous
        assert r.barriers == 0, f"{r.kernel} {r.dtype} sm_{r.arch}: a barrier in the inner loop"
        if r.dtype == "float32":
            assert r.per_pair <= PAIR_BUDGET[r.kernel], f"{r.kernel} sm_{r.arch}: {r.per_pair:.1f} SASS per pair"


def test_densification_compiles_no_new_kernel_variants():
    """A densification changes the Gaussian count, and every launch argument derived from it: the
    kernels' specialisation keys (hence compiled variants) stay within the count's `% 16` classes,
    at most 3, over 40 sizes of a run (the optimiser's program boundaries made 13), the projection's 1."""
    import random

    rng, n, sizes = random.Random(0), 294_000, []
    for _ in range(40):
        n += rng.randint(-3000, 6000)
        sizes.append(n)
    counts = json.loads(last_line_compiled(
        f"import json; from splatting.kernel_report import variants; print(json.dumps(variants({sizes})))"))
    assert counts["adam"] >= 2  # not vacuous: the count's classes do show
    assert max(counts.values()) <= 3, counts
    # the projection's kernels, the slowest to compile (3.4 s and 8.2 s for SH 3), once for all counts
    assert counts["project (SH 3)"] == counts["project backward (SH 3)"] == 1, counts


def test_loaded_variants_reads_tritons_caches():
    """bench train's count of the kernels' compiled variants (a GPU run's), on caches filled here."""
    out = last_line_compiled(
        "from splatting import adam_triton, kernel_report; "
        "adam_triton._adam.device_caches = {0: ({'a': 1, 'b': 2}, None), 1: ({'c': 3}, None)}; "
        "print(kernel_report.loaded_variants())")
    assert out == "{'adam_triton._adam': 3}"
