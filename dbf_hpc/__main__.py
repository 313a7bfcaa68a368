"""`python -m dbf_hpc ...` is `dbf-hpc ...` (for an interpreter whose scripts are not on the PATH)."""
import sys

from .cli import main

sys.exit(main())
