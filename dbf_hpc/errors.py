"""The errors dbf_hpc raises on purpose.

Each carries one line for the user: what is wrong and what to change. The command prints that line
and exits non-zero; anything else is a bug and ends the whole MPI job.
"""


class DbfError(Exception):
    """An error the user can act on (bad input, a failed solve). Raised on every rank alike."""


class InputError(DbfError):
    """Bad input: a scene, a matrix file, an option."""


class SolverError(DbfError):
    """A numerical failure: non-convergence, breakdown, a diverged step."""


class Interrupted(SolverError):
    """A run stopped by a termination signal after writing its checkpoint: rerun to continue."""
