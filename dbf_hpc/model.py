"""Scene -> operators: the structure a scene describes, assembled on a communicator."""
from __future__ import annotations

import dataclasses
import hashlib

import numpy as np
from petsc4py import PETSc

from .cache import file_digest

from .errors import InputError
from .matrices import load_operators
from .operators import Operators
from .scene import Scene
from .structure import assemble_beam


def build_operators(scene: Scene, comm=None) -> Operators:
    """K, M (C) and, for base excitation, the influence vector of the scene's structure. Collective."""
    comm = comm or PETSc.COMM_WORLD
    s, e = scene["structure"], scene["excitation"]
    if scene.is_beam:
        points = [c.x for c in scene.constraints] + list(scene["output"]["probes"])
        if e["kind"] == "force":
            points.append(e["x"])
        if e["kind"] == "random":
            points.extend(e["span"])
        return assemble_beam(scene.beam(), comm, points=points,
                             base_end=e["end"] if e["kind"] == "base" else None)
    files = {key: scene.resolve(s[key]) if s[key] else None
             for key in ("stiffness", "mass", "damping", "influence", "base_mass_load")}
    return load_operators(files["stiffness"], files["mass"], damping=files["damping"],
                          influence=files["influence"], base_mass_load=files["base_mass_load"], comm=comm)


def constraint_rows(scene: Scene, ops: Operators) -> np.ndarray:
    """Global row of the DOF each constraint acts on. A constraint on a fixed DOF is an error."""
    rows = []
    for c in scene.constraints:
        if ops.mesh is not None:
            row = ops.mesh.w_row(c.x)
            if row < 0:
                raise InputError(f"constraint at {c.label} acts on a fixed DOF (a support); move it or remove it")
        else:
            row = c.dof
            if row >= ops.size:
                raise InputError(f"constraint at {c.label} is outside the {ops.size} DOFs of the matrices")
        rows.append(row)
    return np.asarray(rows, dtype=np.int64)


def operators_fingerprint(scene: Scene, ops: Operators) -> dict:
    """What identifies the operators for the basis cache: the beam and its mesh, or the matrix
    files' contents. Collective."""
    if ops.mesh is not None:
        return {"beam": dataclasses.asdict(scene.beam()),
                "nodes": hashlib.sha256(ops.mesh.x.tobytes()).hexdigest()}
    s = scene["structure"]
    return {key: file_digest(scene.resolve(s[key]), ops.comm) for key in ("stiffness", "mass")}
