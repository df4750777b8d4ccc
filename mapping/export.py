"""Export of the surfel map: numpy arrays, open3d point clouds, PLY files and Poisson meshes."""
from __future__ import annotations

import os

import numpy as np

# Poisson vertices whose density is below this quantile are trimmed (the sparse skirt Poisson
# grows where few points support the surface)
MESH_DENSITY_QUANTILE = 0.02
# Poisson vertices farther than this many median surfel radii from the nearest stable surfel are
# trimmed (Poisson extrapolates over holes and borders)
MESH_TRIM_RADIUS_FACTOR = 6.0


def _o3d():
    import open3d as o3d   # imported lazily: heavy, and only needed for export

    return o3d


def point_cloud(points: dict, scale: float = 1e-3):
    """An ``open3d.geometry.PointCloud`` (positions x ``scale``, colours, normals) from ``points``."""
    o3d = _o3d()
    pcd = o3d.geometry.PointCloud()
    if len(points["positions"]):
        pcd.points = o3d.utility.Vector3dVector(points["positions"].astype(np.float64) * scale)
        pcd.colors = o3d.utility.Vector3dVector(np.clip(points["colors"], 0, 1).astype(np.float64))
        pcd.normals = o3d.utility.Vector3dVector(points["normals"].astype(np.float64))
    return pcd


def _ensure_dir(path) -> str:
    path = os.fspath(path)
    d = os.path.dirname(os.path.abspath(path))
    os.makedirs(d, exist_ok=True)
    return path


def _write_empty_ply(path: str, mesh: bool) -> None:
    header = ["ply", "format ascii 1.0", "element vertex 0",
              "property float x", "property float y", "property float z"]
    if mesh:
        header += ["element face 0", "property list uchar int vertex_indices"]
    header.append("end_header")
    with open(path, "w") as f:
        f.write("\n".join(header) + "\n")


def _write_empty_mesh(path: str) -> None:
    if path.lower().endswith(".ply"):
        _write_empty_ply(path, mesh=True)
    else:
        _o3d().io.write_triangle_mesh(path, _o3d().geometry.TriangleMesh())


def save_ply(points: dict, path, scale: float = 1e-3) -> int:
    """Write ``points`` as a binary PLY point cloud with colours and normals; returns the point count.

    An empty map writes a valid PLY with no vertices (open3d refuses to write empty clouds).
    """
    path = _ensure_dir(path)
    n = int(len(points["positions"]))
    if n == 0:
        _write_empty_ply(path, mesh=False)
        return 0
    o3d = _o3d()
    if not o3d.io.write_point_cloud(path, point_cloud(points, scale), write_ascii=False):
        raise OSError(f"{path}: cannot write point cloud")
    return n


def save_mesh(points: dict, path, scale: float = 1e-3, depth: int = 8) -> int:
    """Surface mesh of ``points`` (Poisson, trimmed by density and by distance to the points).

    Falls back to ball pivoting when Poisson yields nothing; returns the triangle count (0 and an
    empty mesh file when there are too few points).
    """
    path = _ensure_dir(path)
    o3d = _o3d()
    n = int(len(points["positions"]))
    if n < 16:
        _write_empty_mesh(path)
        return 0
    pcd = point_cloud(points, scale)
    r_med = float(np.median(points["radii"])) * scale
    mesh = None
    try:
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            mesh, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
                pcd, depth=int(depth), scale=1.1, linear_fit=False)
        dens = np.asarray(dens)
        drop = np.zeros(len(dens), dtype=bool)
        if MESH_DENSITY_QUANTILE > 0 and len(dens):
            drop |= dens < np.quantile(dens, MESH_DENSITY_QUANTILE)
        verts = o3d.geometry.PointCloud(mesh.vertices)
        dist = np.asarray(verts.compute_point_cloud_distance(pcd))
        drop |= dist > MESH_TRIM_RADIUS_FACTOR * max(r_med, 1e-12)
        mesh.remove_vertices_by_mask(drop)
        mesh.remove_unreferenced_vertices()
        if len(mesh.triangles) == 0:
            mesh = None
    except RuntimeError:
        mesh = None
    if mesh is None:
        radii = o3d.utility.DoubleVector([2 * r_med, 4 * r_med, 8 * r_med])
        mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(pcd, radii)
    mesh.compute_vertex_normals()
    ntri = int(len(mesh.triangles))
    if ntri == 0:
        _write_empty_mesh(path)
        return 0
    if not o3d.io.write_triangle_mesh(path, mesh):
        raise OSError(f"{path}: cannot write mesh")
    return ntri
