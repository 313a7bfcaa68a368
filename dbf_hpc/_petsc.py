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


# The options prefixes of the package's solvers: an option under one of them belongs to one command
# (petsctools.command_options); they go in after PETSc starts, the others (-log_view) at its start
SOLVER_PREFIXES = ("modes_", "dbf_", "static_", "buckling_", "rom_", "full_")


def option_pairs(tokens) -> list:
    """[name, value or None] per option of `tokens` as given (-name [value] ...): a token after a
    name that is not itself a name (a dash and a letter) is its value; -1 and -.5 are values."""
    pairs, name = [], None
    for token in tokens:
        if token.startswith("-") and token.lstrip("-")[:1].isalpha():
            name = token.lstrip("-")
            pairs.append([name, None])
        elif name is not None:
            pairs[-1][1] = token
            name = None
    return pairs


def startup_options(tokens) -> list:
    """The tokens of the options that are not a solver's (SOLVER_PREFIXES): what init hands PETSc."""
    out = []
    for name, value in option_pairs(tokens):
        if not name.startswith(SOLVER_PREFIXES):
            out += [f"-{name}"] + ([value] if value is not None else [])
    return out


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
