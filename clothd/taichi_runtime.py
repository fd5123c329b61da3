"""Start Taichi once, at start-up, from the configuration (Taichi is called from one thread only)."""

import taichi as ti


def start_taichi(arch: str = "cpu") -> None:
    """ti.init unless a runtime is already up (a second init would invalidate every field)."""
    if ti.lang.impl.get_runtime().prog is None:
        # One CPU thread: the mass-spring kernel is serial by design, and the camera's decoding and the
        # daemon's event loop (another process) need the remaining cores.
        ti.init(arch=getattr(ti, arch), log_level=ti.WARN, cpu_max_num_threads=1)
