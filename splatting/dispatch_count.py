"""Count what one call dispatches to the device: aten operations (through a
``TorchDispatchMode``) and Triton kernel launches, and flag the operations that make the
host wait for the device (``.item()``, ``nonzero``, boolean-mask indexing and the other
operations whose output shape depends on the data).

On CPU tensors with the Triton interpreter this shows, without a GPU, how many launches a
CUDA render would issue and whether it would ever synchronise: the aten operations the
interpreter itself runs to emulate a kernel are not counted (the kernel counts once).

    with DispatchCounter() as counter:
        splatting.render(..., backend="cuda")
    counter.device_ops, counter.syncs

``DispatchCounter(run_kernels=False)`` counts the interpreter's launches without running them:
a render whose shapes never depend on the data issues the same operations either way, at any
image size, in a fraction of the time (the outputs are then meaningless).
"""

from __future__ import annotations

from collections import Counter

import torch
from torch.utils._python_dispatch import TorchDispatchMode

aten = torch.ops.aten

# operations whose result the host must read (a value, or a shape that depends on values)
_SYNC_PACKETS = {aten._local_scalar_dense, aten.nonzero, aten.masked_select, aten.repeat_interleave,
                 aten.bincount, aten.unique_consecutive, aten._unique2, aten.unique_dim, aten.argwhere}
# bookkeeping that launches nothing on a device
_FREE = {aten.detach, aten.view, aten._unsafe_view, aten.alias, aten.t, aten.transpose, aten.permute,
         aten.expand, aten.reshape, aten.squeeze, aten.unsqueeze, aten.select, aten.slice, aten.as_strided,
         aten.split, aten.split_with_sizes, aten.unbind, aten.lift_fresh, aten.set_}


def _packet(func):
    return func.overloadpacket


def _needs_sync(func, args) -> bool:
    if _packet(func) in _SYNC_PACKETS:
        return True
    if _packet(func) in (aten.index, aten.index_put, aten.index_put_):
        idx = args[1] if len(args) > 1 else ()
        return any(isinstance(t, torch.Tensor) and t.dtype in (torch.bool, torch.uint8) for t in idx if t is not None)
    return False


class DispatchCounter(TorchDispatchMode):
    """Counts aten operations and Triton launches while active (see the module docstring)."""

    def __init__(self, run_kernels: bool = True):
        super().__init__()
        self.run_kernels = run_kernels  # False: count Triton launches without running them (interpreter)
        self.ops = Counter()  # aten overload name -> count (operations that run on the device)
        self.views = Counter()  # metadata-only operations (not counted as device work)
        self.sync_ops = Counter()
        self.kernels = Counter()
        self._inside_kernel = 0
        self._restore = None

    @property
    def device_ops(self) -> int:
        return sum(self.ops.values()) + sum(self.kernels.values())

    @property
    def syncs(self) -> int:
        return sum(self.sync_ops.values())

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if not self._inside_kernel:
            name = str(func.overloadpacket.__name__)
            if _packet(func) in _FREE:
                self.views[name] += 1
            else:
                self.ops[name] += 1
                if _needs_sync(func, args):
                    self.sync_ops[name] += 1
        return func(*args, **(kwargs or {}))

    def __enter__(self):
        self._patch_triton()
        return super().__enter__()

    def __exit__(self, *exc):
        try:
            return super().__exit__(*exc)
        finally:
            if self._restore:
                self._restore()
                self._restore = None

    def _patch_triton(self):
        """Count Triton launches: the interpreter's grid executor, or the compiled launch hook."""
        try:
            from triton import knobs
            from triton.runtime import interpreter
        except ImportError:
            return
        counter = self
        original = interpreter.GridExecutor.__call__

        def call(executor, *args, **kwargs):
            counter.kernels[executor.fn.__name__] += 1
            if not counter.run_kernels:
                return None
            counter._inside_kernel += 1
            try:
                return original(executor, *args, **kwargs)
            finally:
                counter._inside_kernel -= 1

        interpreter.GridExecutor.__call__ = call
        chain = knobs.runtime.launch_enter_hook  # a HookChain in triton 3.8, a plain slot before

        def hook(metadata):  # compiled launches: a LazyDict whose get() holds the kernel's name
            data = metadata.get() if hasattr(metadata, "get") else {}
            counter.kernels[data.get("name", "triton") if isinstance(data, dict) else "triton"] += 1

        if hasattr(chain, "add"):
            chain.add(hook)
        else:
            knobs.runtime.launch_enter_hook = hook

        def restore():
            interpreter.GridExecutor.__call__ = original
            if hasattr(chain, "remove"):
                chain.remove(hook)
            else:
                knobs.runtime.launch_enter_hook = chain

        self._restore = restore

    def summary(self) -> str:
        parts = [f"{n}×{c}" for n, c in (self.ops + self.kernels).most_common()]
        return f"{self.device_ops} device ops ({', '.join(parts)}); {self.syncs} needing a host sync"


class AllocationTracker(DispatchCounter):
    """Also follows the memory the counted operations allocate: live bytes per storage (freed
    when the last tensor using it is gone) and their peak. On CPU tensors with the Triton
    interpreter this is the device memory a CUDA render would hold (docs/gpu.md), without the
    caching allocator's rounding and without memory held before the tracker started."""

    def __init__(self):
        super().__init__(run_kernels=True)
        self.live = 0
        self.peak = 0
        self._users = {}  # storage pointer -> [bytes, number of live tensors]

    def _release(self, key):
        entry = self._users.get(key)
        if entry is None:
            return
        entry[1] -= 1
        if entry[1] == 0:
            self.live -= entry[0]
            del self._users[key]

    def _track(self, out):
        import weakref

        for t in out if isinstance(out, (tuple, list)) else (out,):
            if not isinstance(t, torch.Tensor) or t.device.type == "meta":
                continue
            try:
                st = t.untyped_storage()
            except (RuntimeError, NotImplementedError):
                continue
            key = st.data_ptr()
            if key == 0:
                continue
            entry = self._users.get(key)
            if entry is None:
                entry = self._users[key] = [st.nbytes(), 0]
                self.live += entry[0]
                self.peak = max(self.peak, self.live)
            entry[1] += 1
            weakref.finalize(t, self._release, key)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = super().__torch_dispatch__(func, types, args, kwargs)
        if not self._inside_kernel:
            self._track(out)
        return out
