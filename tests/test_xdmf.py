"""xdmf.py: the ParaView files of a matrix model with [structure] cells describe its hexahedra (the
topology, the points and the displacement vectors, with shapes that match the HDF5 datasets they
name), and the vectors they show are the structure's motion: a free vibration in its lowest simple mode,
checked against a dense eigensolution of the K and M files."""
import hashlib
import os
import re
import sys
import xml.etree.ElementTree as ET

import h5py
import numpy as np
import pytest
import scipy.linalg
from mpi4py import MPI
from petsc4py import PETSc

from dbf_hpc import xdmf
from dbf_hpc.cli import main
from dbf_hpc.report import describe
from dbf_hpc.run import run
from dbf_hpc.scene import load_scene

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ELEMENTS = (4, 2, 2)            # 45 nodes, 16 hexahedra, 108 free DOFs
SIZE = (1.0, 0.1, 0.1)          # scripts/solid3d.py's bar, m
AMPLITUDE = 1e-4                # m, the peak at t = 0 of mode 3, the lowest of a simple frequency
# (the square section bends in pairs: modes 1-2 and 4-5 are repeated frequencies, whose shapes are any mix)

FREE = """[structure]
kind = "matrices"
stiffness = "K.bin"
mass = "M.bin"
nodes = "nodes.txt"
dofs = "dofs.txt"
{cells}
[initial]
mode = 3
amplitude = {amplitude}

[basis]
modes = 5
cache = "off"

[integrator]
t_end = 0.01

[output]
snapshots = 5
"""


def solid(folder, cells=True):
    """scripts/solid3d.py's bar on ELEMENTS (rank 0 writes it) and a scene of its undamped free
    vibration from mode 3 (the lowest simple frequency); returns the scene's path."""
    if MPI.COMM_WORLD.rank == 0:
        sys.path.insert(0, os.path.join(ROOT, "scripts"))
        try:
            import solid3d
        finally:
            sys.path.pop(0)
        assert solid3d.main([str(folder), "--elements", *map(str, ELEMENTS), "--stops", "2"]) == 0
        scene = "free.toml" if cells else "points.toml"
        (folder / scene).write_text(FREE.format(cells='cells = "cells.txt"' if cells else "", amplitude=AMPLITUDE))
    MPI.COMM_WORLD.Barrier()
    return str(folder / ("free.toml" if cells else "points.toml"))


def dense(path):
    """A PETSc binary matrix as a dense numpy array (read on this rank alone)."""
    viewer = PETSc.Viewer().createBinary(str(path), "r", comm=PETSc.COMM_SELF)
    A = PETSc.Mat().create(comm=PETSc.COMM_SELF)
    A.load(viewer)
    viewer.destroy()
    B = A.convert("dense")
    out = B.getDenseArray().copy()
    A.destroy(), B.destroy()
    return out


def free_dofs(folder):
    """(node, direction) of each free DOF, from the generator's DOF map."""
    table = np.loadtxt(folder / "dofs.txt", dtype=str)
    return table[:, 0].astype(int), np.array(["xyz".index(d) for d in table[:, 1]])


def data_items(root, tag):
    """The DataItems under every element `tag` of the XDMF tree."""
    return [item for element in root.iter(tag) for item in element.iter("DataItem")]


def check_paraview_file(xdmf_path, h5, prefix, name, steps):
    """The XDMF file is a time series of `steps` grids of 16 hexahedra whose every DataItem names a
    dataset of `h5` with the Dimensions it says."""
    root = ET.parse(xdmf_path).getroot()
    grids = [g for g in root.iter("Grid") if g.get("GridType") == "Uniform"]
    assert len(grids) == steps
    for grid in grids:
        topology = grid.find("Topology")
        assert topology.get("TopologyType") == "Hexahedron" and topology.get("NumberOfElements") == "16"
        assert grid.find("Geometry").get("GeometryType") == "XYZ"
        assert grid.find("Attribute").get("Center") == "Node"
    for tag, shape in (("Topology", (16, 8)), ("Geometry", (45, 3)), ("Attribute", (45, 3))):
        items = data_items(root, tag)
        assert len(items) == steps
        for item in items:
            file, dataset = item.text.split(":")
            assert file == os.path.basename(h5.filename)
            assert tuple(map(int, item.get("Dimensions").split())) == h5[dataset].shape == shape
    assert [item.text.split(":")[1] for item in data_items(root, "Attribute")] == \
        [f"/{prefix}/{name}/{i:06d}" for i in range(steps)]
    cells = f"{os.path.basename(h5.filename)}:/{prefix}/cells"
    assert [item.text for item in data_items(root, "Topology")] == [cells] * steps


def check_bricks(points, cells):
    """Each cell is one of the bar's bricks, corners in XDMF's order: around the bottom face
    (counter-clockwise seen from above), then the corners above them."""
    h = np.array(SIZE) / np.array(ELEMENTS)
    order = np.array([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]) * h
    np.testing.assert_allclose(points[cells] - points[cells[:, :1]], np.broadcast_to(order, (16, 8, 3)), atol=1e-12)
    assert np.unique(cells).size == 45       # every node is a corner of some brick


def test_a_solid_with_hexahedra_shows_its_cells_in_paraview_swinging_in_its_lowest_simple_mode(shared_tmp_path):
    folder = shared_tmp_path
    out = folder / "free.h5"
    run(load_scene(solid(folder)), str(out), progress=False)
    if MPI.COMM_WORLD.rank == 0:
        K, M = dense(folder / "K.bin"), dense(folder / "M.bin")
        omega2 = scipy.linalg.eigh(K, M, eigvals_only=True, subset_by_index=[2, 2])[0]
        node, direction = free_dofs(folder)
        with h5py.File(out) as f:
            assert f.attrs["field_cells"] == "Hexahedron" and f.attrs["field_cell_count"] == 16
            assert f.attrs["field_cells_sha256"] == hashlib.sha256((folder / "cells.txt").read_bytes()).hexdigest()
            check_paraview_file(folder / "free.xdmf", f, "snapshots", "displacement", 5)
            assert f["snapshots/cells"].attrs["unit"] == "1"
            cells, points = f["snapshots/cells"][:], f["snapshots/points"][:]
            np.testing.assert_array_equal(cells, np.loadtxt(folder / "cells.txt", dtype=np.int64))
            check_bricks(points, cells)
            t = f["snapshots/time"][:]
            vectors = [f[f"snapshots/displacement/{i:06d}"][:] for i in range(t.size)]
        assert t.size == 5 and t[-1] == pytest.approx(0.01)
        assert "snapshots: 5 (drawn on 16 Hexahedron cells)" in "\n".join(describe(str(out)))   # `dbf-hpc info`
        clamped = points[:, 0] == 0.0
        u0 = vectors[0][node, direction]                # the free DOFs, read back from the vectors at the nodes
        # t = 0: mode 3 (K u = omega_3^2 M u: a DOF drawn at a wrong node or direction breaks it), peak
        # AMPLITUDE; the clamped face does not move
        assert np.abs(u0).max() == pytest.approx(AMPLITUDE, rel=1e-12)
        assert np.linalg.norm(K @ u0 - omega2 * M @ u0) <= 1e-8 * np.linalg.norm(K @ u0)
        for i, v in enumerate(vectors):
            assert np.all(v[clamped] == 0.0)
            # undamped, unforced: u(t) = u(0) cos(omega_3 t), to the integrator's tolerance
            assert np.abs(v[node, direction] - u0 * np.cos(np.sqrt(omega2) * t[i])).max() <= 1e-3 * AMPLITUDE, i


def test_the_mode_shapes_of_a_solid_with_hexahedra_are_drawn_on_its_cells_its_bending_pairs_marked_as_any_mix(
        shared_tmp_path, capfd):
    folder = shared_tmp_path
    shapes = folder / "shapes.xdmf"
    capfd.readouterr()
    assert main(["basis", solid(folder), "--xdmf", str(shapes), "--no-cache"]) == 0
    printed = capfd.readouterr().out
    if MPI.COMM_WORLD.rank == 0:
        # the square section's bending pairs, modes 1-2 and 4-5, are drawn as the eigensolver returned them:
        # marked in the .h5, the XDMF grids and the printout; mode 3 (simple) is not
        assert re.search(r"shapes 1 to 2: one repeated frequency, [0-9.]+ Hz, drawn in the directions", printed)
        assert re.search(r"shapes 4 to 5: one repeated frequency", printed) and "shapes 3 " not in printed
        notes = [g.find("Information") for g in ET.parse(shapes).getroot().iter("Grid") if g.get("GridType") == "Uniform"]
        assert [n is not None and "any mix of them" in n.get("Value") for n in notes] == [True, True, False, True, True]
        K, M = dense(folder / "K.bin"), dense(folder / "M.bin")
        omega2 = scipy.linalg.eigh(K, M, eigvals_only=True, subset_by_index=[0, 4])
        node, direction = free_dofs(folder)
        with h5py.File(folder / "shapes.h5") as f:
            assert f.attrs["field_cells"] == "Hexahedron" and f.attrs["field_cell_count"] == 16
            check_paraview_file(shapes, f, "shapes", "shape", 5)
            check_bricks(f["shapes/points"][:], f["shapes/cells"][:])
            np.testing.assert_allclose(f["shapes/omega"][:] ** 2, omega2, rtol=1e-8)
            assert list(f["shapes/repeated"][:]) == [1, 1, 0, 4, 4]
            for i in range(5):     # shape i is mode i + 1 (M-normalized; of a pair, any mix)
                u = f[f"shapes/shape/{i:06d}"][:][node, direction]
                assert np.linalg.norm(K @ u - omega2[i] * M @ u) <= 1e-7 * np.linalg.norm(K @ u), i
                assert u @ M @ u == pytest.approx(1.0, rel=1e-8)


def test_without_cells_a_matrix_model_stays_points(shared_tmp_path):
    folder = shared_tmp_path
    out = folder / "points.h5"
    run(load_scene(solid(folder, cells=False)), str(out), progress=False)
    if MPI.COMM_WORLD.rank == 0:
        root = ET.parse(folder / "points.xdmf").getroot()
        assert {t.get("TopologyType") for t in root.iter("Topology")} == {"Polyvertex"}
        assert {t.get("NumberOfElements") for t in root.iter("Topology")} == {"45"}
        with h5py.File(out) as f:
            assert "snapshots/cells" not in f and "field_cells" not in f.attrs and f.attrs["field_kind"] == "nodes"
        assert "snapshots: 5\n" in "\n".join(describe(str(out))) + "\n"


def test_the_xdmf_topology_of_a_cell_follows_its_node_count(tmp_path):
    for k, name in xdmf.CELL_TYPES.items():
        path = tmp_path / f"{k}.xdmf"
        xdmf.write(str(path), str(tmp_path / "x.h5"), "snapshots", "nodes", 30, [0.0], cells=np.zeros((3, k), int))
        topology = ET.parse(path).getroot().find(".//Topology")
        assert topology.get("TopologyType") == name and topology.get("NumberOfElements") == "3"
        assert topology.find("DataItem").get("Dimensions") == f"3 {k}"
        assert topology.get("NodesPerElement") == ("2" if k == 2 else None)
    for name, k in xdmf.XDMF_TYPES.items():       # a cell_type given: the types 4, 6 and 8 nodes share
        path = tmp_path / f"{name}.xdmf"
        xdmf.write(str(path), str(tmp_path / "x.h5"), "shapes", "nodes", 30, [1], "shape", np.zeros((2, k), int), name)
        topology = ET.parse(path).getroot().find(".//Topology")
        assert topology.get("TopologyType") == name and topology.find("DataItem").get("Dimensions") == f"2 {k}"
