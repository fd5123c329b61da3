"""Start Taichi once per process, whoever gets there first.

hwsim may share a process with the tracker (in tests and benchmarks); a second `ti.init` would reset the
runtime and invalidate every field already allocated, so later callers reuse the running one.
"""

import taichi as ti


def ensure_taichi(arch: str = "cpu", cpu_threads: int | None = None) -> None:
    """ti.init unless a runtime is already up. `arch` is 'cpu', 'cuda' or 'vulkan'; `cpu_threads` caps
    the CPU backend's thread pool (default: every core)."""
    if ti.lang.impl.get_runtime().prog is None:
        extra = {} if cpu_threads is None else {"cpu_max_num_threads": cpu_threads}
        ti.init(arch=getattr(ti, arch), log_level=ti.WARN, random_seed=0, **extra)
