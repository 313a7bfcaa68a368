"""The reduced integrator's C callbacks (rom_core.c, core.pyx), an optional compiled extension.

`core` is the extension module, or None when it was not built (no PETSc headers, Cython or compiler
when the package was installed); `why` then says what is missing, in one line.
"""
try:
    from . import core
    why = None
except ImportError as exc:  # not built, or built against another PETSc
    core = None
    why = (f"the C callbacks of the reduced integrator are not built ({exc}); run scripts/setup (Debian: "
           f"libpetsc-real3.18-dev and cython3), or set [integrator] callbacks = \"python\"")
