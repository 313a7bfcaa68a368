"""dbf_hpc: the method of discontinuous basis functions (Brake & Segalman 2011) on PETSc/SLEPc.

petsc4py and slepc4py are deliberately not install requirements: pip would try to build PETSc from
source. scripts/setup provides them (Debian's packages, or a site PETSc on a cluster).
"""
from setuptools import find_packages, setup

setup(
    name="dbf_hpc",
    version="0.1.0",
    description="Discontinuous basis functions for structures with many nonlinear constraints, on PETSc/SLEPc",
    long_description=open("README.md", encoding="utf-8").read() if __import__("os").path.exists("README.md") else "",
    long_description_content_type="text/markdown",
    license="BSD-2-Clause",
    packages=find_packages(include=["dbf_hpc", "dbf_hpc.*"]),
    python_requires=">=3.11",   # tomllib
    install_requires=["numpy", "mpi4py", "h5py"],
    extras_require={"plot": ["matplotlib"], "test": ["pytest"]},
    entry_points={"console_scripts": ["dbf-hpc = dbf_hpc.cli:main"]},
)
