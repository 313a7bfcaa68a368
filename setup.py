"""dbf_hpc: the method of discontinuous basis functions (Brake & Segalman 2011) on PETSc/SLEPc.

petsc4py and slepc4py are deliberately not install requirements: pip would try to build PETSc from
source. scripts/setup provides them (Debian's packages, or a site PETSc on a cluster).

The reduced integrator's C callbacks (dbf_hpc/_romc: rom_core.c and the Cython glue core.pyx) are an
optional extension: built when PETSc's C headers (PETSC_DIR[/PETSC_ARCH]/include/petsc.h), Cython,
numpy and petsc4py are found, and skipped with a one-line note otherwise (the Python callbacks remain;
[integrator] callbacks = "c" is then a one-line error). DBF_HPC_NO_C=1 skips it on purpose.
"""
import os
import subprocess
import sys

from setuptools import find_packages, setup

DEBIAN_PETSC = "/usr/lib/petscdir/petsc3.18/x86_64-linux-gnu-real"


def c_extensions():
    if os.environ.get("DBF_HPC_NO_C", "") not in ("", "0"):
        return []
    petsc_dir = os.environ.get("PETSC_DIR") or DEBIAN_PETSC
    arch = os.environ.get("PETSC_ARCH", "")
    include = [os.path.join(petsc_dir, arch, "include"), os.path.join(petsc_dir, "include")]
    lib = os.path.join(petsc_dir, arch, "lib")
    why = None
    if not any(os.path.exists(os.path.join(d, "petsc.h")) for d in include):
        why = f"no petsc.h under {petsc_dir} (Debian: apt-get install libpetsc-real3.18-dev)"
    try:
        import numpy
        import petsc4py
        from Cython.Build import cythonize
    except ImportError as e:
        why = why or f"{e.name} is missing (Debian: apt-get install cython3 python3-petsc4py)"
    if why:
        print(f"dbf_hpc: building without the C callbacks: {why}", file=sys.stderr)
        return []
    try:  # petsc.h includes mpi.h
        flags = subprocess.run(["mpicc", "--showme:compile"], capture_output=True, text=True, check=True).stdout.split()
        include += [f[2:] for f in flags if f.startswith("-I")]
    except (OSError, subprocess.CalledProcessError):
        pass
    from setuptools import Extension
    library = "petsc_real" if os.path.exists(os.path.join(lib, "libpetsc_real.so")) else "petsc"
    here = "dbf_hpc/_romc"
    ext = Extension("dbf_hpc._romc.core", [f"{here}/core.pyx", f"{here}/rom_core.c", f"{here}/ritz_kernels.c"],
                    include_dirs=[here, petsc4py.get_include(), numpy.get_include()] + include,
                    library_dirs=[lib], runtime_library_dirs=[lib], libraries=[library],
                    depends=[f"{here}/rom_core.h", f"{here}/ritz_kernels.h"],
                    extra_compile_args=["-O3", "-fopenmp-simd", "-Wno-unused-function", "-Werror=implicit-function-declaration"])
    return cythonize([ext], language_level=3, quiet=True)


setup(
    name="dbf_hpc",
    version="0.2.5",
    description="Discontinuous basis functions for structures with many nonlinear constraints, on PETSc/SLEPc",
    long_description=open("README.md", encoding="utf-8").read() if os.path.exists("README.md") else "",
    long_description_content_type="text/markdown",
    license="BSD-2-Clause",
    packages=find_packages(include=["dbf_hpc", "dbf_hpc.*"]),
    ext_modules=c_extensions(),
    python_requires=">=3.11",   # tomllib
    install_requires=["numpy", "mpi4py", "h5py"],
    extras_require={"plot": ["matplotlib"], "test": ["pytest"]},
    entry_points={"console_scripts": ["dbf-hpc = dbf_hpc.cli:main"]},
)
