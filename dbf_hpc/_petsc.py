"""PETSc/SLEPc start-up for the command line: hand PETSc exactly the options meant for it."""
import os
import sys

# Debian's PETSc without its -dev package needs these to import (PETSC-NOTES.md).
_DEBIAN = {"PETSC_DIR": "/usr/lib/petscdir/petsc3.18/x86_64-linux-gnu-real",
           "SLEPC_DIR": "/usr/lib/slepcdir/slepc3.18/x86_64-linux-gnu-real"}


def init(options=()) -> None:
    """Initialize SLEPc (and PETSc) with `options`. Only the first initialization takes effect, so
    call this before any dbf_hpc module that imports petsc4py.PETSc."""
    for key, value in _DEBIAN.items():
        if key not in os.environ and os.path.isdir(value):
            os.environ[key] = value
    import slepc4py

    slepc4py.init([sys.argv[0] or "dbf-hpc", *options])
