"""Start Taichi once per process, whoever gets there first.

hwsim may share a process with the tracker (in tests and benchmarks); a second `ti.init` would reset the
runtime and invalidate every field already allocated, so later callers reuse the running one.
"""

import taichi as ti


def ensure_taichi(arch: str = "cpu") -> None:
    """ti.init unless a runtime is already up. `arch` is 'cpu', 'cuda' or 'vulkan'."""
    if ti.lang.impl.get_runtime().prog is None:
        ti.init(arch=getattr(ti, arch), log_level=ti.WARN, random_seed=0)
