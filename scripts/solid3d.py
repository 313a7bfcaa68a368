#!/usr/bin/env python3
"""A 3-D structure at scale: a steel cantilever block (1 m x 0.1 m x 0.1 m) meshed with trilinear
hexahedra (linear elasticity, 3 DOFs a node, consistent mass, 2x2x2 Gauss), clamped at x = 0,
written as PETSc binary K and M over the free DOFs, with the node coordinates, the DOF map and the
hexahedra (cells.txt, in XDMF's node order) that dbf-hpc uses for its XDMF output, and a scene
that runs it: a bar in a guide channel, N_L stops with a clearance on the z DOFs of the top centre
line, driven by a harmonic force at the tip.

    python scripts/solid3d.py OUT_DIR [--elements NX NY NZ] [--stops N] [--surface]

Default 120 x 16 x 16 elements: 104 040 free DOFs, 100 stops. Writes OUT_DIR/K.bin, OUT_DIR/M.bin,
OUT_DIR/nodes.txt, OUT_DIR/dofs.txt, OUT_DIR/cells.txt, OUT_DIR/scene.toml and OUT_DIR/dofs.json
(the free DOF of each node's z displacement along the top edge at y = W/2 (`top_z`, from the clamp
to the tip), the tip's z DOF (`tip_z`), and the element sizes). jobs/solid_cantilever.toml is that
scene for the default mesh: `python scripts/solid3d.py jobs/solid_cantilever` writes the matrices,
node map and cells it reads.

The element is stiff in bending (full integration): the first bending frequency is 87.2, 83.1, 81.9
and 81.70 Hz on 20x2x2, 40x4x4, 80x8x8 and the default 120x16x16 meshes, converging from above to
about the Timoshenko beam's 81.16 Hz (kappa = 5/6: at L/H = 10 shear and rotary inertia take 0.8 %
off Euler-Bernoulli's 81.80 Hz, which the finer meshes pass; tests/test_solid3d.py checks it through
dbf-hpc's own modes). Torsion 723.5 Hz (Saint-Venant, J = 0.1406 a^4: 721.1 Hz) and the axial mode
1269.7 Hz (sqrt(E / rho) / 4 L = 1265.9 Hz) on the default mesh.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys

import numpy as np
import scipy.sparse as sp

E, NU, RHO = 200e9, 0.3, 7800.0
LENGTH, WIDTH, HEIGHT = 1.0, 0.1, 0.1


def hex8(dx: float, dy: float, dz: float):
    """(K_e, M_e), 24 x 24, of a dx x dy x dz brick, DOFs node-major (u, v, w), nodes in the order
    (i, j, k) = (0,0,0), (1,0,0), (0,1,0), (1,1,0), (0,0,1), (1,0,1), (0,1,1), (1,1,1); 2x2x2 Gauss."""
    corners = np.array([(i, j, k) for k in (0, 1) for j in (0, 1) for i in (0, 1)], dtype=float)
    lam, mu = E * NU / ((1 + NU) * (1 - 2 * NU)), E / (2 * (1 + NU))
    Dm = np.full((3, 3), lam) + 2 * mu * np.eye(3)
    D = np.zeros((6, 6))
    D[:3, :3] = Dm
    D[3:, 3:] = mu * np.eye(3)
    g = np.array([0.5 - 0.5 / np.sqrt(3), 0.5 + 0.5 / np.sqrt(3)])
    h = np.array([dx, dy, dz])
    volume = dx * dy * dz
    K, M = np.zeros((24, 24)), np.zeros((24, 24))
    for a in g:
        for b in g:
            for c in g:
                p = np.array([a, b, c])
                shape = np.prod(np.where(corners == 1, p, 1 - p), axis=1)            # (8,)
                grad = np.empty((8, 3))
                for d in range(3):
                    others = np.where(corners == 1, p, 1 - p)
                    others[:, d] = np.where(corners[:, d] == 1, 1.0, -1.0)
                    grad[:, d] = np.prod(others, axis=1) / h[d]
                B = np.zeros((6, 24))
                for n in range(8):
                    gx, gy, gz = grad[n]
                    B[:, 3 * n:3 * n + 3] = [[gx, 0, 0], [0, gy, 0], [0, 0, gz], [gy, gx, 0], [0, gz, gy], [gz, 0, gx]]
                w = volume / 8
                K += w * B.T @ D @ B
                N = np.zeros((3, 24))
                for n in range(8):
                    N[:, 3 * n:3 * n + 3] = shape[n] * np.eye(3)
                M += w * RHO * N.T @ N
    return K, M


# hex8's corners (lexicographic in i, j, k) in XDMF's (VTK's) hexahedron order: around the bottom face,
# then around the top one above it
XDMF_ORDER = [0, 1, 3, 2, 4, 5, 7, 6]


def assemble(nx: int, ny: int, nz: int):
    """K, M over all DOFs (scipy CSR), the node numbering and the elements' nodes (elements x 8, in
    XDMF's hexahedron order)."""
    Ke, Me = hex8(LENGTH / nx, WIDTH / ny, HEIGHT / nz)
    node = lambda i, j, k: (k * (ny + 1) + j) * (nx + 1) + i          # noqa: E731
    i, j, k = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    i, j, k = i.ravel(), j.ravel(), k.ravel()
    nodes = np.stack([node(i + a, j + b, k + c) for c in (0, 1) for b in (0, 1) for a in (0, 1)], axis=1)
    dofs = (3 * nodes[:, :, None] + np.arange(3)).reshape(-1, 24)
    rows = np.repeat(dofs, 24, axis=1).ravel()
    cols = np.tile(dofs, (1, 24)).ravel()
    n = 3 * (nx + 1) * (ny + 1) * (nz + 1)
    K = sp.csr_matrix((np.tile(Ke.ravel(), len(dofs)), (rows, cols)), shape=(n, n))
    M = sp.csr_matrix((np.tile(Me.ravel(), len(dofs)), (rows, cols)), shape=(n, n))
    return K, M, node, nodes[:, XDMF_ORDER]


def top_z_dofs(nx: int, ny: int, nz: int) -> list:
    """The free DOF of the z displacement of each node on the top centre line (y = W/2, z = H), from
    the clamp to the tip (free DOFs number the nodes' x, y, z in node order, the clamped face left out)."""
    per_layer = (nx + 1) * (ny + 1)
    node = lambda i, j, k: (k * (ny + 1) + j) * (nx + 1) + i          # noqa: E731
    # free DOFs before node p: 3 (p - clamped nodes before p); the clamped nodes are i = 0
    clamped_before = lambda p: (p // per_layer) * (ny + 1) + (p % per_layer) // (nx + 1) + 1   # noqa: E731
    return [3 * (node(i, ny // 2, nz) - clamped_before(node(i, ny // 2, nz))) + 2 for i in range(1, nx + 1)]


def top_surface_z_dofs(nx: int, ny: int, nz: int) -> list:
    """The free z DOFs of every node on the top face (z = H) off the clamp, row by row in y."""
    node = lambda i, j, k: (k * (ny + 1) + j) * (nx + 1) + i          # noqa: E731
    clamped_before = lambda p: (p // ((nx + 1) * (ny + 1))) * (ny + 1) + (p % ((nx + 1) * (ny + 1))) // (nx + 1) + 1  # noqa: E731
    return [3 * (node(i, j, nz) - clamped_before(node(i, j, nz))) + 2 for j in range(ny + 1) for i in range(1, nx + 1)]


def scene_text(top: list, stops: int, surface: list | None = None, across: int = 16) -> str:
    """The guide-channel scene: `stops` stops spread over the outer 5/6 of the top centre line (or,
    with `surface`, over all the top face's z DOFs off the clamp) (0.2 mm clearance, 1e7 N/m), a 1 kN
    force at 60 Hz at the tip (below the first bending mode, 81.7 Hz), 1 % modal damping. The square
    section's bending modes come in equal pairs, and a count of modes that ends inside one is refused:
    `across` elements over the section (the fewer of NY, NZ) set it, 21 modes for 4 or more (modes 20
    and 21 are a pair there: 40 x 4 x 4 to the default 120 x 16 x 16), 20 below (4 to 20 x 2 x 2, whose
    modes 21 and 22 are one)."""
    modes = 21 if across >= 4 else 20
    where, places = ("top face", surface) if surface is not None else ("top centre line", top)
    first = 0 if surface is not None else len(places) // 6
    if not 1 <= stops <= len(places) - first:   # more would put two stops on one node (silently fewer)
        raise SystemExit(f"solid3d: --stops must be from 1 to {len(places) - first} (the nodes of the {where}"
                         + (" off its first sixth" if first else "") + ")")
    picks = np.unique(np.linspace(first, len(places) - 1, stops).round().astype(int))
    lines = ["# A steel bar (1 m x 0.1 m x 0.1 m, trilinear hexahedra) clamped at x = 0, in a guide channel:",
             f"# {picks.size} stops on the z DOFs of its {where}, driven at the tip. Written by",
             "# scripts/solid3d.py, which also writes the matrices this scene reads.", "",
             "[structure]", 'kind = "matrices"', 'stiffness = "K.bin"', 'mass = "M.bin"',
             'nodes = "nodes.txt"', 'dofs = "dofs.txt"', 'cells = "cells.txt"', "",
             "[excitation]", 'kind = "force"', f"dof = {top[-1]}", "amplitude = 1000.0      # N",
             "frequency_hz = 60.0", "", "[basis]", f"modes = {modes}", "", "[damping]", "zeta = 0.01", "",
             "[integrator]", "t_end = 0.2", "", "[output]", 'file = "solid.h5"', "sample_dt = 1e-4",
             f"probes = [{top[-1]}]",
             "snapshots = 10", ""]
    for i in picks:
        lines += ["[[constraint]]", f"dof = {places[i]}", 'law = "deadband"', "clearance = 2e-4       # m",
                  "k = 1e7                 # N/m", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", metavar="OUT_DIR", help="where to write K.bin, M.bin, nodes.txt, dofs.txt, "
                        "cells.txt, dofs.json and scene.toml (made if missing)")
    parser.add_argument("--elements", type=int, nargs=3, default=(120, 16, 16), metavar=("NX", "NY", "NZ"),
                        help="hexahedra along x, y, z (NY even; default 120 16 16: 104 040 free DOFs)")
    parser.add_argument("--stops", type=int, default=100, help="stops on the top centre line (default 100)")
    parser.add_argument("--surface", action="store_true",
                        help="spread the stops over the whole top face instead (up to NX (NY + 1) of them)")
    args = parser.parse_args(argv)
    from petsc4py import PETSc

    nx, ny, nz = args.elements
    if min(args.elements) < 1 or ny % 2:
        parser.error("--elements: NX, NY, NZ >= 1 and NY even (the top centre line runs through nodes at y = W/2)")
    top = top_z_dofs(nx, ny, nz)
    scene = scene_text(top, args.stops, top_surface_z_dofs(nx, ny, nz) if args.surface else None,  # checks --stops
                       min(ny, nz))
    try:
        K, M, node, hexahedra = assemble(nx, ny, nz)
    except MemoryError:
        raise SystemExit(f"solid3d: not enough memory to assemble {nx} x {ny} x {nz} elements; use fewer") from None
    n_nodes = (nx + 1) * (ny + 1) * (nz + 1)
    clamped = np.zeros(n_nodes, dtype=bool)
    clamped[[node(0, j, k) for j in range(ny + 1) for k in range(nz + 1)]] = True
    free_dofs = np.flatnonzero(~np.repeat(clamped, 3))
    index = -np.ones(3 * n_nodes, dtype=np.int64)
    index[free_dofs] = np.arange(free_dofs.size)
    try:
        os.makedirs(args.out, exist_ok=True)
    except OSError as e:     # e.g. OUT is a file
        raise SystemExit(f"solid3d: cannot make the folder {args.out!r}: {e.strerror}") from None
    # Every file is written into a temporary folder beside them and then renamed over its old self,
    # scene.toml last: an interrupted run leaves the earlier set whole, never a half-written matrix.
    staging = os.path.join(args.out, f".solid3d-{os.getpid()}")
    os.makedirs(staging)
    try:
        for name, A in (("K", K), ("M", M)):
            A = A[free_dofs][:, free_dofs].tocsr()
            A.sort_indices()
            P = PETSc.Mat().createAIJ(size=A.shape, csr=(A.indptr.astype(PETSc.IntType),
                                                         A.indices.astype(PETSc.IntType), A.data), comm=PETSc.COMM_SELF)
            viewer = PETSc.Viewer().createBinary(os.path.join(staging, f"{name}.bin"), "w", comm=PETSc.COMM_SELF)
            P.view(viewer)
            viewer.destroy()
            P.destroy()
        info = {"dofs": int(free_dofs.size), "elements": [nx, ny, nz], "size_m": [LENGTH, WIDTH, HEIGHT],
                "top_z": top, "tip_z": top[-1], "material": {"E": E, "nu": NU, "rho": RHO}}
        with open(os.path.join(staging, "dofs.json"), "w") as f:
            json.dump(info, f)
        coordinates = np.array([(i * LENGTH / nx, j * WIDTH / ny, k * HEIGHT / nz)
                                for k in range(nz + 1) for j in range(ny + 1) for i in range(nx + 1)])
        np.savetxt(os.path.join(staging, "nodes.txt"), coordinates, fmt="%.9g")
        with open(os.path.join(staging, "dofs.txt"), "w") as f:
            f.writelines(f"{dof // 3} {'xyz'[dof % 3]}\n" for dof in free_dofs)
        np.savetxt(os.path.join(staging, "cells.txt"), hexahedra, fmt="%d")
        with open(os.path.join(staging, "scene.toml"), "w") as f:
            f.write(scene)
        for name in ("K.bin", "K.bin.info", "M.bin", "M.bin.info", "dofs.json", "nodes.txt", "dofs.txt", "cells.txt",
                     "scene.toml"):
            if os.path.exists(os.path.join(staging, name)):
                os.replace(os.path.join(staging, name), os.path.join(args.out, name))
    except (OSError, PETSc.Error) as e:     # e.g. a full disk, while writing the temporary folder
        why = e.strerror if isinstance(e, OSError) and e.strerror else str(e).splitlines()[0]
        raise SystemExit(f"solid3d: cannot write into {args.out!r} ({why}): its files were left as they were") \
            from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    print(f"{args.out}: {free_dofs.size} free DOFs, K nnz {K.nnz}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
