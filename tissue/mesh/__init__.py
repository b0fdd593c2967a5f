"""Meshes: the tet mesh type and its checks (:mod:`tissue.mesh.core`), files in and out
(:mod:`tissue.mesh.io`), the parametric breast phantom at the paper's nine resolutions
(:mod:`tissue.mesh.phantom`), the authors' published scene (:mod:`tissue.mesh.paper_scene`),
block meshes for analytic checks (:mod:`tissue.mesh.block`) and points embedded in tets
(:mod:`tissue.mesh.embedding`)."""

from tissue.mesh.core import (
    CollisionSurface,
    Landmarks,
    TetMesh,
    boundary_faces,
    check_rigid_motion_removed,
    node_dofs,
    signed_tet_volumes,
    top_surface_nodes,
    triangle_grid,
)

__all__ = [
    "CollisionSurface",
    "Landmarks",
    "TetMesh",
    "boundary_faces",
    "check_rigid_motion_removed",
    "node_dofs",
    "signed_tet_volumes",
    "top_surface_nodes",
    "triangle_grid",
]
