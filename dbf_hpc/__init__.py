"""dbf_hpc: the method of discontinuous basis functions (Brake & Segalman 2011) on PETSc/SLEPc."""

__version__ = "0.1.0"
