"""The reduced integrator's C callbacks (rom_core.c, core.pyx), an optional compiled extension.

`core` is the extension module, or None when it was not built (no PETSc headers, Cython or compiler
when the package was installed) or when DBF_HPC_NO_C is set to anything but "" or "0" (it then
behaves as if not built); `why` says so in one line.
"""
import importlib
import os

core = None
why = None
if os.environ.get("DBF_HPC_NO_C", "") not in ("", "0"):
    why = ("the C callbacks of the reduced integrator are switched off (DBF_HPC_NO_C is set); unset it, or "
           "set [integrator] callbacks = \"python\"")
else:
    try:
        core = importlib.import_module(f"{__name__}.core")
    except ImportError as exc:  # not built, or built against another PETSc
        why = (f"the C callbacks of the reduced integrator are not built ({exc}); run scripts/setup (Debian: "
               f"libpetsc-real3.18-dev and cython3), or set [integrator] callbacks = \"python\"")
