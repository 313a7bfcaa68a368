"""PETSc/SLEPc start-up: hand PETSc exactly the options meant for it.

The command line calls init(options) before importing any module that imports petsc4py.PETSc.
Python users need not call anything: the first use of the package's API (dbf_hpc/__init__.py)
calls init() with no options, so PETSc reads only PETSC_OPTIONS. Either way the Debian paths
are set when the environment has none, so that slepc4py imports without an activated venv.
init() is called by every rank (it initializes MPI through petsc4py).
"""
import os
import sys

# Debian's PETSc without its -dev package needs these to import (PETSC-NOTES.md).
_DEBIAN = {"PETSC_DIR": "/usr/lib/petscdir/petsc3.18/x86_64-linux-gnu-real",
           "SLEPC_DIR": "/usr/lib/slepcdir/slepc3.18/x86_64-linux-gnu-real"}


def init(options=()) -> bool:
    """Initialize SLEPc (and PETSc) with `options`; True if this call did it. Only the first
    initialization takes effect, so call this before any dbf_hpc module that imports
    petsc4py.PETSc (a later command's options go in through petsctools.command_options)."""
    for key, value in _DEBIAN.items():
        if key not in os.environ and os.path.isdir(value):
            os.environ[key] = value
    if "slepc4py.SLEPc" in sys.modules or "petsc4py.PETSc" in sys.modules:
        return False  # already initialized
    import slepc4py

    # the program's name, never sys.argv[0]: under `python -c` that is "-c", which PETSc took for an option
    slepc4py.init(["dbf-hpc", *options])
    return True
