"""Fields for ParaView: XDMF files that describe, in a few lines of XML, displacement fields stored in
HDF5 (a run's snapshots, or a basis's mode shapes), as a time series of vectors at the nodes: a
polyline along x for a beam (w along y), for a matrix model its cells when [structure] cells gives
them (hexahedra, tetrahedra ...: ParaView shows the solid), else points (at its nodes with a node map,
else DOF i at (i, 0, 0)). Open the .xdmf in ParaView ("Xdmf3 Reader") and warp by the vector.
Nothing here is collective."""
from __future__ import annotations

import os

import numpy as np

from .errors import replacing

# XDMF topology of a cell by its node count (one type a mesh; nodes in XDMF's order, which is VTK's)
CELL_TYPES = {2: "Polyline", 3: "Triangle", 4: "Tetrahedron", 5: "Pyramid", 6: "Wedge", 8: "Hexahedron",
              10: "Tetrahedron_10", 20: "Hexahedron_20"}
# every type [structure] cell_type may name, with its node count (4, 6 and 8 nodes are each two types)
XDMF_TYPES = {"Polyline": 2, "Triangle": 3, "Quadrilateral": 4, "Tetrahedron": 4, "Pyramid": 5, "Wedge": 6,
              "Triangle_6": 6, "Hexahedron": 8, "Quadrilateral_8": 8, "Tetrahedron_10": 10, "Hexahedron_20": 20}


def node_vectors(geometry: tuple, values: np.ndarray, prefix: str, name: str = "displacement") -> dict:
    """The datasets `{prefix}/{name}/NNNNNN` (nodes x 3), one per row of values at the field points
    (one dataset a step: readers such as meshio take no hyperslabs)."""
    coordinates, node, component = geometry[1:4]
    out = {}
    for i, row in enumerate(np.atleast_2d(values)):
        vectors = np.zeros((coordinates.shape[0], 3))
        vectors[node, component] = row
        out[f"{prefix}/{name}/{i:06d}"] = vectors
    return out


def geometry_datasets(geometry: tuple, prefix: str) -> dict:
    """The datasets that place a field in space: the nodes' coordinates, each value's node and
    direction, and a beam's elements or a matrix model's cells (written into the HDF5 file the XDMF
    points at)."""
    kind, coordinates, node, component, cells = geometry[:5]
    out = {f"{prefix}/points": coordinates, f"{prefix}/node": node, f"{prefix}/component": component}
    if cells is not None:
        out[f"{prefix}/cells"] = np.asarray(cells, dtype=np.int64)
    if kind == "beam" and coordinates.shape[0] > 1:
        out[f"{prefix}/polyline"] = np.column_stack([np.arange(coordinates.shape[0] - 1),
                                                     np.arange(1, coordinates.shape[0])])
    return out


MARK = "<!-- written by dbf-hpc -->"


def sidecar(h5_path: str) -> str:
    """The XDMF file written beside an HDF5 output: the same name with .xdmf."""
    return os.path.splitext(h5_path)[0] + ".xdmf"


def is_dbf_xdmf(path: str) -> bool:
    """Whether `path` is an XDMF file dbf-hpc wrote (a later run may replace it, nothing else)."""
    try:
        with open(path, "rb") as f:
            head = f.read(256)
    except OSError:
        return False
    return head.startswith(b'<?xml version="1.0" ?>') and (MARK.encode() in head or
                                                           b'<Xdmf Version="3.0"><Domain><Grid Name="' in head)


def check_sidecar(h5_path: str, inputs=()) -> None:
    """Refuse, before any work, an output whose XDMF sidecar would overwrite the output itself, an
    input, a directory or a file dbf-hpc did not write."""
    from .errors import InputError
    from .output import check_output_path

    path = sidecar(h5_path)
    if os.path.abspath(path) == os.path.abspath(h5_path):
        raise InputError(f"output {h5_path!r} ends in .xdmf, the name of the ParaView file written beside it: "
                         f"name the output .h5")
    if os.path.isdir(path):
        raise InputError(f"output {h5_path!r}: its ParaView file {path!r} would replace a directory: "
                         f"choose another output name")
    check_output_path(path, inputs, replaceable=is_dbf_xdmf)


def write(path: str, h5_file: str, prefix: str, kind: str, nodes: int, steps, name: str = "displacement",
          cells=None, cell_type: str = "", notes=None) -> None:
    """Write the XDMF `path` for `{prefix}/{name}/NNNNNN` (nodes x 3 each) and `{prefix}/points` in
    `h5_file` (referred to by its name: keep the two side by side). `steps` label the time series
    (times in s, or mode numbers). With `cells` (E x k, as `{prefix}/cells`; only its shape is read),
    the topology is those cells, of `cell_type` (default CELL_TYPES by k), else a beam's polyline or
    points. `notes`: {step index: text}, an XDMF Information element "note" in that step's grid (a
    shape of a repeated frequency)."""
    content = text(h5_file, prefix, kind, nodes, steps, name, cells, cell_type, notes)
    with replacing(path) as tmp, open(tmp, "w") as f:
        f.write(content)


def describes(path: str, h5) -> bool:
    """Whether the XDMF `path` is the one write() makes for the snapshots of the open run output `h5`
    (its times, nodes, field kind and cells): a rerun whose ParaView file was not written (a full
    disk, a kill after the output's rename) leaves an earlier run's beside a complete output, with
    that run's times and snapshot count (red team). Not collective."""
    try:
        with open(path, encoding="utf-8") as f:
            found = f.read()
        cells = h5.get("snapshots/cells")
        expected = text(h5.filename, "snapshots", str(h5.attrs["field_kind"]), h5["snapshots/points"].shape[0],
                        h5["snapshots/time"][()], cells=cells, cell_type=str(h5.attrs.get("field_cells", "")))
    except (OSError, KeyError, ValueError, UnicodeDecodeError):
        return False
    return found == expected


def text(h5_file: str, prefix: str, kind: str, nodes: int, steps, name: str = "displacement", cells=None,
         cell_type: str = "", notes=None) -> str:
    """The XDMF document write() writes."""
    from xml.sax.saxutils import quoteattr

    notes = notes or {}
    h5 = os.path.basename(h5_file)
    if cells is not None:
        count, k = np.shape(cells)
        cell_type = cell_type or CELL_TYPES[k]
        per = f' NodesPerElement="{k}"' if cell_type == "Polyline" else ""
        topology = (f'<Topology TopologyType="{cell_type}" NumberOfElements="{count}"{per}>'
                    f'<DataItem Format="HDF" Dimensions="{count} {k}" NumberType="Int" Precision="8">'
                    f'{h5}:/{prefix}/cells</DataItem></Topology>')
    else:
        topology = (f'<Topology TopologyType="Polyline" NodesPerElement="2" NumberOfElements="{nodes - 1}">'
                    f'<DataItem Format="HDF" Dimensions="{nodes - 1} 2" NumberType="Int" Precision="8">'
                    f'{h5}:/{prefix}/polyline</DataItem></Topology>'
                    if kind == "beam" and nodes > 1 else
                    f'<Topology TopologyType="Polyvertex" NumberOfElements="{nodes}" NodesPerElement="1"/>')
    grids = []
    for i, step in enumerate(steps):
        grids.append(
            f'<Grid Name="{name} {i}" GridType="Uniform"><Time Value="{float(step):.12g}"/>'
            + (f'<Information Name="note" Value={quoteattr(notes[i])}/>' if i in notes else "") + f'{topology}'
            f'<Geometry GeometryType="XYZ"><DataItem Format="HDF" Dimensions="{nodes} 3" NumberType="Float" '
            f'Precision="8">{h5}:/{prefix}/points</DataItem></Geometry>'
            f'<Attribute Name="{name}" AttributeType="Vector" Center="Node">'
            f'<DataItem Format="HDF" Dimensions="{nodes} 3" NumberType="Float" Precision="8">'
            f'{h5}:/{prefix}/{name}/{i:06d}</DataItem></Attribute></Grid>')
    return (f'<?xml version="1.0" ?>\n{MARK}\n<Xdmf Version="3.0"><Domain>'
            f'<Grid Name="{name}" GridType="Collection" CollectionType="Temporal">\n'
            + "\n".join(grids) + "\n</Grid></Domain></Xdmf>\n")
