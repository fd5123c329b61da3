"""Start Taichi once per process, whoever gets there first.

hwsim may share a process with the tracker (in tests and benchmarks); a second `ti.init` would reset the
runtime and invalidate every field already allocated, so later callers reuse the running one.
"""

from __future__ import annotations

import taichi as ti

_started = False


def ensure_taichi(arch: str = "cpu", cpu_threads: int | None = None) -> None:
    """ti.init on first call only. `arch` is 'cpu', 'cuda' or 'vulkan'; `cpu_threads` caps the CPU pool."""
    global _started
    if _started or ti.lang.impl.get_runtime().prog is not None:
        _started = True
        return
    kwargs: dict[str, object] = {"arch": getattr(ti, arch), "log_level": ti.WARN, "random_seed": 0}
    if cpu_threads is not None:
        kwargs["cpu_max_num_threads"] = cpu_threads
    ti.init(**kwargs)
    _started = True
