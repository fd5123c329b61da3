"""Taichi's runtime, started once per process by the program's entry point, from `taichi.arch`.

A process has one Taichi runtime: a second `ti.init` would reset it and invalidate every field already
allocated, so a later start is a no-op. Whoever starts it decides its settings, so each entry point does
so first (the compute process, and `clothd replay` / `bench`, which may then record hwsim scenarios in
the same runtime). hwsim's own entry points start theirs the same way (hwsim/taichi_runtime.py).
"""

import taichi as ti

# One CPU thread: the mass-spring kernel is serial by design, and the camera's decoding and the daemon's
# event loop (another process) need the remaining cores.
CPU_THREADS = 1


def start_taichi(arch: str = "cpu") -> None:
    """ti.init unless a runtime is already up. `arch` is 'cpu', 'cuda' or 'vulkan' (config taichi.arch)."""
    if ti.lang.impl.get_runtime().prog is None:
        ti.init(arch=getattr(ti, arch), log_level=ti.WARN, cpu_max_num_threads=CPU_THREADS, random_seed=0)
