"""dbf_hpc: the method of discontinuous basis functions (Brake & Segalman 2011) on PETSc/SLEPc.

The Python API (README "Python API"; docs/design.md for the objects and the parallel layout):

    FullOrderModel.build(structure, constraints, excitation, damping, probes, initial)   fom.py
        structure: Beam (structure.py) or MatrixFiles (matrices.py)
        constraints: Constraint(law, x=... or dof=...) (constraints.py), law(...) (laws.py)
        excitation: NoExcitation, BaseMotion, PointForce, RandomForce, Turbulence (excitation.py)
    Reductor(fom, BasisSettings(...), cache_dir).reduce() -> ReducedModel             reductor.py
    simulate_reduced(rom, IntegratorSettings(...)) -> Result                         simulate.py
    simulate_full(fom, IntegratorSettings(...)) -> Result

The names listed below by module are loaded with their module on first use, and PETSc starts then
(the command line starts it itself first, with the options it was given); help(dbf_hpc.NAME) gives
each one's own documentation. Only this list names them in help(dbf_hpc), as they load lazily.
"""

__version__ = "0.2.5"

_API = {
    "Beam": "structure", "MatrixFiles": "matrices", "Constraint": "constraints", "ConstraintSet": "constraints",
    "Law": "laws", "law": "laws", "NoExcitation": "excitation", "BaseMotion": "excitation",
    "PointForce": "excitation", "RandomForce": "excitation", "Turbulence": "excitation", "Harmonic": "excitation",
    "Damping": "damping",
    "InitialState": "fom", "FullOrderModel": "fom", "BasisSettings": "basis", "DbfEnrichment": "enrichment",
    "StaticEnrichment": "enrichment", "NoEnrichment": "enrichment", "Reductor": "reductor",
    "ReducedModel": "rom", "IntegratorSettings": "timestepping", "Result": "recorder",
    "simulate_reduced": "simulate", "simulate_full": "simulate", "load_scene": "scene", "run": "run",
    "DbfError": "errors", "InputError": "errors", "SolverError": "errors",
}
__all__ = sorted(_API)


def _listing() -> str:
    import textwrap

    modules: dict = {}
    for name, module in _API.items():
        modules.setdefault(module, []).append(name)
    lines = ["", "Names (module: names):", ""]
    for module in sorted(modules):
        lines += textwrap.wrap(", ".join(modules[module]), 96, initial_indent=f"    {module}: ",
                               subsequent_indent=" " * (6 + len(module)))
    return "\n".join(lines) + "\n"


if __doc__:   # None under python -OO
    __doc__ += _listing()


def __getattr__(name):
    if name not in _API:
        raise AttributeError(f"module 'dbf_hpc' has no attribute {name!r}")
    import importlib

    from . import _petsc

    _petsc.init()
    return getattr(importlib.import_module(f".{_API[name]}", __name__), name)
