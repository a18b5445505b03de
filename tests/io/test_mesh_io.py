"""The capture's mesh: found by name, read as one triangle mesh, one-line errors otherwise."""

import numpy as np
import pytest
import trimesh

from pipeline.errors import UserError
from pipeline.io.mesh import mesh_path, read_mesh


def test_mesh_found_and_read_exactly(tmp_path):
    """mesh_path finds a capture's mesh.obj and read_mesh reads its 12 faces and extents to OBJ's 7 digits."""
    box = trimesh.creation.box(extents=(0.1, 0.2, 0.3))
    box.export(tmp_path / "mesh.obj")
    assert mesh_path(tmp_path) == tmp_path / "mesh.obj"
    mesh = read_mesh(mesh_path(tmp_path))
    assert len(mesh.faces) == 12
    np.testing.assert_allclose(mesh.extents, (0.1, 0.2, 0.3), rtol=1e-6)  # OBJ text keeps ~7 digits


def test_mesh_errors_are_user_errors(tmp_path):
    """No mesh, a missing file and a broken PLY are each a UserError (the last naming mesh.ply), not a traceback."""
    with pytest.raises(UserError, match="no mesh found"):
        mesh_path(tmp_path)
    with pytest.raises(UserError, match="not found"):
        read_mesh(tmp_path / "mesh.ply")
    (tmp_path / "mesh.ply").write_bytes(b"ply\nformat nonsense\n")
    with pytest.raises(UserError, match="mesh.ply"):
        read_mesh(tmp_path / "mesh.ply")
